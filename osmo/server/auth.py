"""Who may ask the server what: the verb table, token authentication, the owner's token.

:data:`API` is the one table of the server's API: every verb, the roles that may call it,
the handler that serves it, and whether a ``user`` may act only on its own workflows.
:func:`authorize` applies it, default deny: a verb the table does not name is refused for
everyone, a role it does not list is refused. :data:`VERBS` is the same table as
``verb -> roles`` (e.g. for an access-control allow-list of ``api/<verb>`` keys), and
:class:`Router` dispatches a request to the table's handler. The roles, in short:

- ``admin`` — every verb.
- ``user`` — submit, read everything but secret values, cancel, restart, tag, exec into and
  port-forward to its own workflows (``owner`` verbs: checked by their handlers with
  :func:`check_owner`, since only they know a workflow's submitter), list credential
  names, datasets. Not: ``shutdown``, tokens, setting or deleting credentials,
  garbage-collecting artifacts, the worker verbs.
- ``worker`` — only the worker verbs (and ``ping``); which attempts it may speak for is
  checked by ``osmo.server.worker_access``, which pools it may serve by
  :func:`check_pool` (a worker token names its pools).

:class:`Authenticator` opens the channels requests are sealed on (``osmo.transport.seal``:
a client proves it holds a token without sending it) and turns a channel's token into an
:class:`~osmo.transport.auth.Identity`, once per request, through a cache of token digest →
identity (a revoked token leaves the cache, and loses its channels, at once).

Every refusal is one log line on the server (``refused <verb> from <name> (<role>): <why>``)
and a clear error on the client: :class:`~osmo.errors.NotAuthenticated` (exit 3) for an
unknown or revoked token, :class:`~osmo.errors.NotAllowed` (exit 2) for a role that lacks
the right, :class:`~osmo.errors.UsageError` (exit 2) for a verb the table does not name.

The home's owner gets an admin token in ``OSMO_HOME/auth/admin.token`` (0600, in a 0700
folder) at the server's first start (:func:`owner_token`); the local CLI and SDK read it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from osmo.errors import NotAllowed, NotAuthenticated, UsageError
from osmo.layout import Home
from osmo.names import check_name, shown
from osmo.store.sqlite import Store
from osmo.transport.auth import Identity, Role, new_token, token_digest
from osmo.transport.rpc import field, str_list
from osmo.transport.seal import ChannelTable, Signer, TokenKeys

__all__ = ["API", "EVERY_POOL", "OWNER", "VERBS", "Authenticator", "Router", "Rule",
           "TokenHandlers", "accept_tokens", "authorize", "check_owner", "check_pool",
           "owner_token", "refuse", "token_pools"]

log = logging.getLogger("osmo.server.auth")

OWNER = "admin"
"""The name of the home owner's admin token."""

_MAX_CACHE = 4096
_RELOAD_EVERY = 0.5  # seconds between two reads of the token ids for an unknown one

_ADMIN = frozenset({Role.ADMIN})
_USERS = frozenset({Role.ADMIN, Role.USER})
_WORKERS = frozenset({Role.ADMIN, Role.WORKER})
_ANY = frozenset(Role)


@dataclass(frozen=True)
class Rule:
    """One API verb: who may call it and what serves it.

    Attributes:
        roles: the roles that may call it (every other role is refused).
        handler: ``"<group>.<method>"``: the method of one of the :class:`Router`'s handler
            groups that serves it.
        caller: the handler also takes the caller's :class:`~osmo.transport.auth.Identity`.
        owner: it acts on a workflow, which a ``user`` may do only to its own (the handler
            calls :func:`check_owner`).
    """

    roles: frozenset[Role]
    handler: str
    caller: bool = False
    owner: bool = False


API: Mapping[str, Rule] = MappingProxyType({
    "ping": Rule(_ANY, "api.ping", caller=True),
    # admin only
    "shutdown": Rule(_ADMIN, "api.shutdown"),
    "token_create": Rule(_ADMIN, "tokens.create"),
    "token_list": Rule(_ADMIN, "tokens.list"),
    "token_revoke": Rule(_ADMIN, "tokens.revoke"),
    "credential_set": Rule(_ADMIN, "credentials.set"),
    "credential_delete": Rule(_ADMIN, "credentials.delete"),
    "artifact_gc": Rule(_ADMIN, "artifacts.artifact_gc"),
    # workers (each only for the attempts placed on it, in the pools its token names)
    "worker_register": Rule(_WORKERS, "workers.register", caller=True),
    "worker_drain": Rule(_WORKERS, "workers.drain", caller=True),
    "worker_report": Rule(_WORKERS, "workers.report", caller=True),
    "worker_log": Rule(_WORKERS, "workers.log", caller=True),
    "worker_secrets": Rule(_WORKERS, "workers.secrets", caller=True),
    "worker_session": Rule(_WORKERS, "sessions.worker_session", caller=True),
    "worker_beat": Rule(_WORKERS, "workers.beat", caller=True),
    "worker_swept": Rule(_WORKERS, "workers.swept", caller=True),
    # users: their own workflows
    "cancel": Rule(_USERS, "api.cancel", caller=True, owner=True),
    "restart": Rule(_USERS, "api.restart", caller=True, owner=True),
    "workflow_tag": Rule(_USERS, "api.workflow_tag", caller=True, owner=True),
    "exec_open": Rule(_USERS, "sessions.exec_open", caller=True, owner=True),
    "forward_open": Rule(_USERS, "sessions.forward_open", caller=True, owner=True),
    # users: submit and read
    "submit": Rule(_USERS, "api.submit", caller=True),
    "get": Rule(_USERS, "api.get"),
    "status": Rule(_USERS, "api.status"),
    "list": Rule(_USERS, "api.list"),
    "logs": Rule(_USERS, "api.logs"),
    "events": Rule(_USERS, "api.events"),
    "spec": Rule(_USERS, "api.spec"),
    "pools": Rule(_USERS, "api.pools"),
    "lineage": Rule(_USERS, "artifacts.lineage"),
    "artifact_list": Rule(_USERS, "artifacts.artifact_list"),
    "artifact_get": Rule(_USERS, "artifacts.artifact_get"),
    "credential_list": Rule(_USERS, "credentials.list"),
    "dataset_list": Rule(_USERS, "datasets.list"),
    "dataset_info": Rule(_USERS, "datasets.info"),
    "dataset_tag": Rule(_USERS, "datasets.tag"),
    "dataset_download": Rule(_USERS, "datasets.download"),
    "dataset_upload": Rule(_USERS, "datasets.upload", caller=True),
})
"""Every API verb with its :class:`Rule` (see the module docstring). Default deny: a verb
not here is refused for everyone; a role not in its rule is refused."""

VERBS: Mapping[str, frozenset[Role]] = MappingProxyType(
    {verb: rule.roles for verb, rule in API.items()})
"""``verb -> the roles that may call it``: :data:`API` without its handlers."""


def refuse(verb: str, who: Identity | None, why: str, *, known: bool = True) -> Exception:
    """Log one refusal line and return the error to raise for it."""
    name = str(who) if who is not None else "an unauthenticated caller"
    log.warning("refused %s from %s: %s", shown(verb), name, why)
    return NotAllowed(f"not allowed: {why}") if known else NotAuthenticated(why)


def authorize(verb: str, who: Identity) -> Rule:
    """The rule of ``verb`` in :data:`API`, if ``who``'s role may call it.

    Raises:
        UsageError: the table names no such verb (for every caller).
        NotAllowed: ``who``'s role may not call ``verb`` (logged once).
    """
    rule = API.get(verb)
    if rule is None:
        raise UsageError(f"unknown API verb {shown(verb)}")
    if who.role not in rule.roles:
        needs = " or ".join(r.value for r in Role if r in rule.roles)
        hint = (" (a token made with `osmo token create NAME --role worker --pool POOL`)"
                if rule.roles == _WORKERS else "")
        raise refuse(verb, who, f"'{verb}' needs role {needs}{hint}; token '{who.name}' "
                                f"has role {who.role.value}")
    return rule


class Router:
    """Serves each verb of :data:`API` with its handler, after :func:`authorize`.

    Args:
        groups: handler group name → the object whose methods serve its verbs. A verb of a
            group that is not given is unknown to this server (e.g. no ``workers``).

    Raises:
        AttributeError: a rule names a method its group lacks (a bug: caught at start).
    """

    def __init__(self, groups: Mapping[str, object]) -> None:
        self._handlers: dict[str, Callable[..., Any]] = {}
        for verb, rule in API.items():
            group, _, method = rule.handler.partition(".")
            if groups.get(group) is not None:
                self._handlers[verb] = getattr(groups[group], method)

    def __call__(self, verb: str, request: dict[str, Any], who: Identity) -> Any:
        """Run ``verb``'s handler for ``who``.

        Raises:
            UsageError: a verb this server does not serve.
            NotAllowed: ``who``'s role may not call it (:func:`authorize`).
        """
        rule = authorize(verb, who)
        handler = self._handlers.get(verb)
        if handler is None:
            raise UsageError(f"this server does not serve {shown(verb)}")
        return handler(request, who) if rule.caller else handler(request)


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


EVERY_POOL = "*"
"""The pool a worker token names to serve every pool (``--pool '*'``)."""
_MAX_POOLS = 256


def token_pools(role: Role, pools: list[str] | tuple[str, ...]) -> list[str] | None:
    """The pools a new token of ``role`` stores: a worker's (at least one), None for others.

    Raises:
        UsageError: a worker token without pools, pools for another role, or a bad pool.
    """
    if role is not Role.WORKER:
        if pools:
            raise UsageError("only worker tokens name pools (--pool); a user's or admin's "
                             "token reaches every pool's workflows as its role allows")
        return None
    if not pools:
        raise UsageError("a worker token names the pools it may serve: --pool POOL "
                         f"(repeatable), or --pool '{EVERY_POOL}' for every pool")
    if len(pools) > _MAX_POOLS or not all(
            isinstance(p, str) and 0 < len(p) <= 256 and p.isprintable() for p in pools):
        raise UsageError(f"pools must be 1 to {_MAX_POOLS} names of printable characters")
    return list(dict.fromkeys(pools))


def check_pool(store: Store, who: Identity, pool: str) -> None:
    """Let ``who`` serve ``pool`` only if it is an admin or its worker token names ``pool``.

    Raises:
        NotAllowed: a worker token bound to other pools (logged once).
    """
    if who.role is Role.ADMIN:
        return
    pools = store.token_pools(who.name) or []
    if pool in pools or EVERY_POOL in pools:
        return
    names = ", ".join(shown(p) for p in pools) or "none"
    raise refuse("worker_register", who, f"token '{who.name}' may serve only pool "
                                         f"{names}, not {shown(pool)} (an admin binds a "
                                         "worker token to pools with `osmo token create "
                                         "NAME --role worker --pool POOL`)")


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


def owner_token(layout: Home, store: Store) -> None:
    """Make sure the home's owner has a live admin token in ``auth/admin.token`` (0600).

    A token file whose token the store does not know (or revoked) is replaced.
    """
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
    """Accept the tokens of ``--accept-token NAME:ROLE[@POOL,...]:FILE`` (Kubernetes Secrets).

    Each file's token becomes the live token ``NAME`` with ``ROLE`` (replacing an earlier
    one of that name: a rotated Secret takes effect at the next start). A worker token names
    the pools it may serve after its role: ``NAME:worker@gpu,cpu:FILE`` (``@*``: every pool).

    Raises:
        UsageError: a spec that is not in that form, an unknown role, a worker token without
            pools (or pools for another role), an unreadable or empty file.
    """
    for spec in specs:
        name, _, rest = spec.partition(":")
        role_part, _, path = rest.partition(":")
        role_name, at, pool_list = role_part.partition("@")
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
        try:
            pools = token_pools(role, pool_list.split(",") if at else [])
        except UsageError as exc:
            raise UsageError(f"--accept-token {spec}: {exc} (write NAME:worker@POOL[,POOL]:FILE, "
                             f"or NAME:worker@{EVERY_POOL}:FILE for every pool)") from None
        store.set_token(check_name(name, "token name"), role.value, token_digest(token),
                        time.time(), pools)
        log.info("accepted token '%s' (role %s%s) from %s", name, role.value,
                 f", pools {', '.join(pools)}" if pools else "", path)


class TokenHandlers:
    """``token_create``, ``token_list``, ``token_revoke`` (admin only, see :func:`authorize`)."""

    def __init__(self, store: Store, authenticator: Authenticator) -> None:
        self._store = store
        self._auth = authenticator

    def create(self, request: dict[str, Any]) -> dict[str, Any]:
        """A new token ``name`` with ``role``; the token is in this reply only.

        A worker token names the ``pools`` it may serve (:func:`token_pools`).
        """
        name = check_name(field(request, "name", str, max_len=128), "token name")
        role_name = field(request, "role", str, default=Role.USER.value, max_len=16)
        try:
            role = Role(role_name)
        except ValueError:
            raise UsageError(f"unknown role {shown(role_name)}; the roles are "
                             f"{', '.join(r.value for r in Role)}") from None
        pools = token_pools(role, str_list(request, "pools"))
        token = new_token()
        if not self._store.add_token(name, role.value, token_digest(token), time.time(), pools):
            raise UsageError(f"a token named '{name}' exists already (revoked names are not "
                             "reused); pick another name")
        self._auth.reload()
        log.info("token '%s' created with role %s%s", name, role.value,
                 f", pools {', '.join(pools)}" if pools else "")
        return {"name": name, "role": role.value, "pools": pools, "token": token}

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
