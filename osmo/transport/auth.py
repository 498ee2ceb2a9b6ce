"""Who is asking: tokens, their digests, and the identity a request is served as.

A token is ``osmo_`` + 43 URL-safe characters (32 random bytes). The server keeps only its
sha256 (:func:`token_digest`); the client sends the token itself as the zenoh attachment of
every API request (``osmo.transport.rpc``), so request bodies stay as they are. Over a Unix
socket or TLS that attachment is private to the link; over plain TCP it travels in clear,
which is why a network listener needs zenoh authentication or ``--insecure``.

Roles: ``admin`` may do everything; ``user`` submits and reads, and controls only its own
workflows; ``worker`` may speak only the worker verbs, for the attempts placed on it.
"""

from __future__ import annotations

import enum
import hashlib
import secrets
from dataclasses import dataclass

__all__ = ["Identity", "Role", "new_token", "token_digest"]

TOKEN_PREFIX = "osmo_"


class Role(enum.Enum):
    """What an identity may do (see the module docstring)."""

    ADMIN = "admin"
    USER = "user"
    WORKER = "worker"


@dataclass(frozen=True)
class Identity:
    """An authenticated caller: its token's name and role."""

    name: str
    role: Role

    def __str__(self) -> str:
        return f"{self.name} ({self.role.value})"


def new_token() -> str:
    """A fresh random token (shown to its owner once; only its digest is stored)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def token_digest(token: str | bytes) -> str:
    """The sha256 hex digest a token is stored and looked up by."""
    raw = token.encode() if isinstance(token, str) else token
    return hashlib.sha256(raw.strip()).hexdigest()
