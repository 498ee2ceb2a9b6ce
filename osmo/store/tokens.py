"""API tokens: name, role, the sha256 of the secret, created and revoked times, pools.

A worker token names the pools it may serve (``["*"]``: every pool); other roles have none.

A mixin of ``osmo.store.sqlite.Store`` (which owns the connection and the transaction); kept
apart so the store module stays small. Must not import sqlite3. The token itself is never
stored: only ``osmo.transport.auth.token_digest`` of it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager
from typing import Any

__all__ = ["TokenRows"]


class TokenRows:
    """Token rows; needs ``self._read`` and ``self._tx`` of the store."""

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[Any]:
        raise NotImplementedError

    def _tx(self) -> AbstractContextManager[Any]:
        raise NotImplementedError

    def add_token(self, name: str, role: str, digest: str, now: float,
                  pools: Sequence[str] | None = None) -> bool:
        """Record a new token; False if a token (live or revoked) already has ``name``."""
        with self._tx() as db:
            cur = db.execute("INSERT OR IGNORE INTO tokens VALUES (?,?,?,?,NULL,?)",
                             (name, role, digest, now, _pools(pools)))
            return bool(cur.rowcount)

    def set_token(self, name: str, role: str, digest: str, now: float,
                  pools: Sequence[str] | None = None) -> None:
        """Make ``name`` a live token with this role and digest (a rotated Secret replaces it)."""
        with self._tx() as db:
            db.execute("DELETE FROM tokens WHERE name = ? OR digest = ?", (name, digest))
            db.execute("INSERT INTO tokens VALUES (?,?,?,?,NULL,?)",
                       (name, role, digest, now, _pools(pools)))

    def revoke_token(self, name: str, now: float) -> bool:
        """Revoke token ``name``; False if there is no live token of that name."""
        with self._tx() as db:
            cur = db.execute("UPDATE tokens SET revoked_at = ? WHERE name = ? AND "
                             "revoked_at IS NULL", (now, name))
            return bool(cur.rowcount)

    def token_by_digest(self, digest: str) -> tuple[str, str] | None:
        """``(name, role)`` of the live token with this digest, or None."""
        rows = self._read("SELECT name, role FROM tokens WHERE digest = ? AND "
                          "revoked_at IS NULL", (digest,))
        return (str(rows[0][0]), str(rows[0][1])) if rows else None

    def token_pools(self, name: str) -> list[str] | None:
        """The pools token ``name`` may serve (None: not a worker token, or no such token)."""
        rows = self._read("SELECT pools FROM tokens WHERE name = ?", (name,))
        return json.loads(rows[0][0]) if rows and rows[0][0] is not None else None

    def tokens(self) -> list[dict[str, Any]]:
        """Every token's name, role, pools, created and revoked times (never a digest)."""
        rows = self._read("SELECT name, role, created_at, revoked_at, pools FROM tokens "
                          "ORDER BY created_at")
        return [{"name": r[0], "role": r[1], "created_at": r[2], "revoked_at": r[3],
                 "pools": json.loads(r[4]) if r[4] is not None else None} for r in rows]

    def token_rows(self) -> Iterator[tuple[str, str]]:
        """``(name, digest)`` of every live token."""
        yield from ((str(r[0]), str(r[1])) for r in
                    self._read("SELECT name, digest FROM tokens WHERE revoked_at IS NULL"))


def _pools(pools: Sequence[str] | None) -> str | None:
    return json.dumps(list(pools)) if pools is not None else None
