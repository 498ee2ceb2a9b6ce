"""Who may ask the server what: token authentication, roles, the owner's admin token.

:class:`Authenticator` opens the channels requests are sealed on (``osmo.transport.seal``:
a client proves it holds a token without sending it) and turns a channel's token into an
:class:`~osmo.transport.auth.Identity`, once per request, through a cache of token digest →
identity (a revoked token leaves the cache, and loses its channels, at once).
:func:`authorize` is the role policy:

- ``admin`` — everything.
- ``user`` — submit, read everything but secret values, cancel and restart its own
  workflows, list credential names, datasets. Refused: ``shutdown``, the worker verbs,
  tokens, setting or deleting credentials, garbage-collecting artifacts, other users'
  workflows (checked by the handlers, which know a workflow's submitter).
- ``worker`` — only the worker verbs (and ``ping``); which attempts it may speak for is
  checked by ``osmo.server.workers``.

Every refusal is one log line on the server (``refused <verb> from <name> (<role>): <why>``)
and a clear error on the client: :class:`~osmo.errors.NotAuthenticated` (exit 3) for an
unknown or revoked token, :class:`~osmo.errors.NotAllowed` (exit 2) for a role that lacks
the right.

The home's owner gets an admin token in ``OSMO_HOME/auth/admin.token`` (0600, in a 0700
folder) at the server's first start (:func:`owner_token`); the local CLI and SDK read it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from osmo.errors import NotAllowed, NotAuthenticated, UsageError
from osmo.layout import Home
from osmo.names import check_name, shown
from osmo.store.sqlite import Store
from osmo.transport.auth import Identity, Role, new_token, token_digest
from osmo.transport.rpc import field
from osmo.transport.seal import ChannelTable, Signer, TokenKeys

__all__ = ["OWNER", "WORKER_VERBS", "Authenticator", "TokenHandlers", "accept_tokens",
           "authorize", "check_owner", "owner_token", "refuse"]

log = logging.getLogger("osmo.server.auth")

OWNER = "admin"
"""The name of the home owner's admin token."""

WORKER_VERBS = frozenset({"worker_register", "worker_drain", "worker_report", "worker_log",
                          "worker_secrets", "worker_session", "worker_beat"})
"""The verbs a worker speaks (and only a worker or an admin)."""

_ADMIN_ONLY = frozenset({"shutdown", "token_create", "token_list", "token_revoke",
                         "credential_set", "credential_delete", "artifact_gc"})
_ANYONE = frozenset({"ping"})
_MAX_CACHE = 4096
_RELOAD_EVERY = 0.5  # seconds between two reads of the token ids for an unknown one


def refuse(verb: str, who: Identity | None, why: str, *, known: bool = True) -> Exception:
    """Log one refusal line and return the error to raise for it."""
    name = str(who) if who is not None else "an unauthenticated caller"
    log.warning("refused %s from %s: %s", shown(verb), name, why)
    return NotAllowed(f"not allowed: {why}") if known else NotAuthenticated(why)


def authorize(verb: str, who: Identity) -> None:
    """Check the role policy of the module docstring for ``verb``.

    Raises:
        NotAllowed: ``who``'s role may not call ``verb`` (logged once).
    """
    if who.role is Role.ADMIN or verb in _ANYONE:
        return
    if who.role is Role.WORKER:
        if verb not in WORKER_VERBS:
            raise refuse(verb, who, f"'{verb}' needs role user or admin; "
                                    f"token '{who.name}' is a worker's")
        return
    if verb in WORKER_VERBS:
        raise refuse(verb, who, f"'{verb}' is for workers (a token made with "
                                "`osmo token create NAME --role worker`)")
    if verb in _ADMIN_ONLY:
        raise refuse(verb, who, f"'{verb}' needs role admin; token '{who.name}' has role user")


def check_owner(workflow_id: str, owner: str | None, who: Identity, verb: str) -> None:
    """Let ``who`` act on workflow ``workflow_id`` only as an admin or its submitter ``owner``.

    Raises:
        NotAllowed: another user's workflow (logged once).
    """
    if who.role is Role.ADMIN or owner == who.name:
        return
    raise refuse(verb, who, f"workflow {workflow_id} was submitted by "
                            f"{shown(owner) if owner else 'another user'}; only they or "
                            "an admin may change it")


class Authenticator:
    """The server's side of authentication: channels, and token digest -> identity.

    Implements ``osmo.transport.rpc.Gate``. A hello names a token by its id
    (``osmo.transport.seal.TokenKeys``): the ids of the live tokens are kept in memory,
    read again from the store when an unknown id comes (at most every
    :data:`_RELOAD_EVERY` seconds, so a stream of made-up ids costs nothing). Identities
    are cached by digest; a revoked token leaves the cache and loses its channels at once.

    Args:
        store: the state store (its tokens).
        signer: the server's notice signer (its public key goes into every hello).
    """

    def __init__(self, store: Store, signer: Signer) -> None:
        self._store = store
        self._lock = threading.Lock()
        self._cache: dict[str, Identity] = {}
        self._ids: dict[bytes, str] = {}
        self._loaded = float("-inf")
        self.channels = ChannelTable(self._digest_of, signer)

    def _digest_of(self, token_id: bytes) -> str | None:
        with self._lock:
            digest = self._ids.get(token_id)
            stale = digest is None and time.monotonic() - self._loaded > _RELOAD_EVERY
        if stale:
            self.reload()
            with self._lock:
                digest = self._ids.get(token_id)
        if digest is None or self._store.token_by_digest(digest) is None:
            return None
        return digest

    def reload(self) -> None:
        """Read the live tokens' ids from the store again (after a token was added)."""
        ids = {TokenKeys.from_digest(digest).id: digest
               for _name, digest in self._store.token_rows()}
        with self._lock:
            self._ids, self._loaded = ids, time.monotonic()

    def identity(self, digest: str, channel: bytes = b"") -> Identity:
        """The identity of the live token with sha256 ``digest``, asking on ``channel``.

        Raises:
            NotAuthenticated: no live token has it (unknown, or revoked).
        """
        who = self._cache.get(digest)
        if who is None:
            row = self._store.token_by_digest(digest)
            if row is None:
                raise NotAuthenticated("this osmo server does not know this token (unknown or "
                                       "revoked); ask its admin for a new one")
            who = Identity(row[0], Role(row[1]))
            with self._lock:
                if len(self._cache) >= _MAX_CACHE:
                    self._cache.clear()
                self._cache[digest] = who
        return replace(who, channel=channel) if channel else who

    def forget(self, name: str) -> None:
        """Drop a revoked token's cached identity and close its channels."""
        with self._lock:
            self._cache = {d: who for d, who in self._cache.items() if who.name != name}
            digests = set(self._ids.values())
        for digest in digests:
            if self._store.token_by_digest(digest) is None:
                self.channels.revoke(digest)
        self.reload()


def owner_token(home: Path, store: Store) -> None:
    """Make sure the home's owner has a live admin token in ``auth/admin.token`` (0600).

    A token file whose token the store does not know (or revoked) is replaced.
    """
    layout = Home(home)
    layout.auth.mkdir(mode=0o700, exist_ok=True)
    os.chmod(layout.auth, 0o700)
    try:
        known = store.token_by_digest(token_digest(layout.admin_token.read_bytes()))
    except FileNotFoundError:
        known = None
    if known is not None and known[1] == Role.ADMIN.value:
        os.chmod(layout.admin_token, 0o600)
        return
    token = new_token()
    name = OWNER
    if not store.add_token(name, Role.ADMIN.value, token_digest(token), time.time()):
        name = f"{OWNER}-{int(time.time())}"  # the old one was revoked: a new name
        store.add_token(name, Role.ADMIN.value, token_digest(token), time.time())
    tmp = layout.auth / f".admin.token.{os.getpid()}"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    os.replace(tmp, layout.admin_token)
    log.info("created the admin token '%s' in %s", name, layout.admin_token)


def accept_tokens(store: Store, specs: tuple[str, ...]) -> None:
    """Accept the tokens of ``--accept-token NAME:ROLE:FILE`` (e.g. Kubernetes Secrets).

    Each file's token becomes the live token ``NAME`` with ``ROLE`` (replacing an earlier
    one of that name: a rotated Secret takes effect at the next start).

    Raises:
        UsageError: a spec that is not ``NAME:ROLE:FILE``, an unknown role, an unreadable or
            empty file.
    """
    for spec in specs:
        name, _, rest = spec.partition(":")
        role_name, _, path = rest.partition(":")
        try:
            role = Role(role_name)
            token = Path(path).read_text().strip() if path else ""
        except ValueError:
            raise UsageError(f"--accept-token {spec}: the role must be one of "
                             f"{', '.join(r.value for r in Role)}") from None
        except OSError as exc:
            raise UsageError(f"--accept-token {spec}: cannot read {path}: {exc.strerror}") from None
        if not token:
            raise UsageError(f"--accept-token {spec}: write NAME:ROLE:FILE, FILE holding a token")
        store.set_token(check_name(name, "token name"), role.value, token_digest(token),
                        time.time())
        log.info("accepted token '%s' (role %s) from %s", name, role.value, path)


class TokenHandlers:
    """``token_create``, ``token_list``, ``token_revoke`` (admin only, see :func:`authorize`)."""

    def __init__(self, store: Store, authenticator: Authenticator) -> None:
        self._store = store
        self._auth = authenticator

    def verbs(self) -> dict[str, Callable[[dict[str, Any]], Any]]:
        """Verb name → handler."""
        return {"token_create": self.create, "token_list": self.list,
                "token_revoke": self.revoke}

    def create(self, request: dict[str, Any]) -> dict[str, Any]:
        """A new token ``name`` with ``role``; the token is in this reply only."""
        name = check_name(field(request, "name", str, max_len=128), "token name")
        role_name = field(request, "role", str, default=Role.USER.value, max_len=16)
        try:
            role = Role(role_name)
        except ValueError:
            raise UsageError(f"unknown role {shown(role_name)}; the roles are "
                             f"{', '.join(r.value for r in Role)}") from None
        token = new_token()
        if not self._store.add_token(name, role.value, token_digest(token), time.time()):
            raise UsageError(f"a token named '{name}' exists already (revoked names are not "
                             "reused); pick another name")
        self._auth.reload()
        log.info("token '%s' created with role %s", name, role.value)
        return {"name": name, "role": role.value, "token": token}

    def list(self, _request: dict[str, Any]) -> list[dict[str, Any]]:
        """Every token's name, role and times (never the token)."""
        return self._store.tokens()

    def revoke(self, request: dict[str, Any]) -> dict[str, Any]:
        """Revoke token ``name`` now: its next request is refused."""
        name = field(request, "name", str, max_len=128)
        if not self._store.revoke_token(name, time.time()):
            raise UsageError(f"no live token named {shown(name)} (`osmo token list`)")
        self._auth.forget(name)
        log.info("token '%s' revoked", name)
        return {"name": name, "revoked": True}
