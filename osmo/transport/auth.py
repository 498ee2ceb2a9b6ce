"""Who is asking: tokens, their digests, and the identity a request is served as.

A token is ``osmo_`` + 43 URL-safe characters (32 random bytes). The server keeps only its
sha256 (:func:`token_digest`). The token never crosses the bus: client and server derive a
channel's keys from it (``osmo.transport.seal``), and each request is sealed on that
channel, so a request names its caller by the channel it was sealed on.

Roles: ``admin`` may do everything; ``user`` submits and reads, and controls only its own
workflows; ``worker`` may speak only the worker verbs, for the attempts placed on it.
"""

from __future__ import annotations

import enum
import hashlib
import secrets
from dataclasses import dataclass, field

__all__ = ["Identity", "Role", "new_token", "token_digest"]

TOKEN_PREFIX = "osmo_"


class Role(enum.Enum):
    """What an identity may do (see the module docstring)."""

    ADMIN = "admin"
    USER = "user"
    WORKER = "worker"


@dataclass(frozen=True)
class Identity:
    """An authenticated caller: its token's name and role.

    ``channel``: the id of the sealed channel the request came on (``osmo.transport.seal``;
    empty when not asked over one), so the server can answer on it later: a worker's
    orders, a pull of its blobs.
    """

    name: str
    role: Role
    channel: bytes = field(default=b"", compare=False, repr=False)

    def __str__(self) -> str:
        return f"{self.name} ({self.role.value})"


def new_token() -> str:
    """A fresh random token (shown to its owner once; only its digest is stored)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def token_digest(token: str | bytes) -> str:
    """The sha256 hex digest a token is stored and looked up by."""
    raw = token.encode() if isinstance(token, str) else token
    return hashlib.sha256(raw.strip()).hexdigest()
