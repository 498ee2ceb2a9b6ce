"""The one module that imports zenoh: sessions, puts, subscriptions, queries, liveliness.

Everything osmo sends travels under one key prefix per cluster, ``osmo/<cluster>/...``; the
key layout is documented by the modules that use it (``osmo.transport.rpc`` for the client
API, ``osmo.transport.blobs`` for artifact transfer, ``osmo.server.workers`` and
``osmo.worker.remote`` for worker traffic).

The router's access control is an allow-list (:class:`Acl`): for every remote peer, each
zenoh message is allowed only on the key expressions the server names, everything else is
denied, wildcards included (the server's own session is inside the router and not subject to
it). It is the second wall: the first is that nothing is believed for its key
(``osmo.transport.seal``). Rules already in the configuration file are kept.

Defaults keep everything on loopback with scouting off. A zenoh configuration file (JSON5,
zenoh's own format) can be given for TLS, mutual TLS and user/password authentication; osmo
only adds its mode, endpoints, scouting and lease settings on top of it. The transport lease
is 1 s (zenoh's default is 10 s), so a hung or cut-off peer is noticed in about 0.75 s.

zenoh raises one exception type (``ZError``); it is translated here into
``ServerUnreachable`` / ``InfrastructureError`` with a message that says what to check.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import InfrastructureError, ServerUnreachable, UsageError

__all__ = ["MESSAGES", "Acl", "Link", "Request", "Subscription",
           "authenticates", "client_credentials"]

LEASE_MS = 1000


#: zenoh access-control messages a remote peer may be allowed on ingress (the rest: denied).
MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
            "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


def _config(mode: str, *, listen: Sequence[str] = (), connect: Sequence[str] = (),
            config_file: str | None = None, acl: Acl | None = None) -> zenoh.Config:
    if config_file:
        try:
            conf = zenoh.Config.from_file(config_file)
        except (zenoh.ZError, OSError) as exc:
            raise UsageError(f"cannot read zenoh config {config_file}: {exc}") from exc
    else:
        conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("scouting/delay", "0")  # default 500 ms: the whole of a server's start-up
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        conf.insert_json5("connect/timeout_ms", "5000")
    if acl is not None:
        _apply(conf, acl)
    return conf


@dataclass(frozen=True)
class Acl:
    """The router's allow-list: what remote peers may do; everything else is denied.

    Attributes:
        prefix: the cluster's key prefix (``osmo/<cluster>``).
        allow: zenoh message (one of :data:`MESSAGES`) -> key expressions under ``prefix``
            that every remote peer may use it on (on ingress).
        deny: the same, refused even where ``allow`` covers it (deny wins).
    """

    prefix: str
    allow: Mapping[str, Sequence[str]]
    deny: Mapping[str, Sequence[str]] = field(default_factory=dict)


def _apply(conf: zenoh.Config, acl: Acl) -> None:
    """Turn ``acl`` into zenoh access control: default deny, allow-list per message.

    A rule's key expressions are matched by inclusion, so a peer that names a wildcard
    (``osmo/local/*/w1``, ``**``) on a message the list does not cover is refused; a
    subscriber is delivered only samples on keys the list allows. Rules already in the
    configuration file are kept, but its ``default_permission`` becomes ``deny`` (zenoh's
    deny wins over allow, so "deny the rest of osmo's prefix" cannot be written beside a
    default allow): other traffic through this router needs allow rules of its own.
    """
    unknown = {*acl.allow, *acl.deny} - set(MESSAGES)
    if unknown:
        raise ValueError(f"unknown zenoh messages {sorted(unknown)}: not in {MESSAGES}")
    found = json.loads(conf.get_json("access_control") or "{}") or {}
    if not found.get("enabled"):
        found = {}
    rules: list[dict[str, Any]] = [
        {"id": "osmo-egress", "messages": list(MESSAGES), "flows": ["egress"],
         "permission": "allow", "key_exprs": [f"{acl.prefix}/**"]}]
    rules += [{"id": f"osmo-allow-{m}", "messages": [m], "flows": ["ingress"],
               "permission": "allow", "key_exprs": [f"{acl.prefix}/{k}" for k in keys]}
              for m, keys in acl.allow.items() if keys]
    rules += [{"id": f"osmo-deny-{m}", "messages": [m], "flows": ["ingress"],
               "permission": "deny", "key_exprs": [f"{acl.prefix}/{k}" for k in keys]}
              for m, keys in acl.deny.items() if keys]
    out = {**found, "enabled": True, "default_permission": "deny"}
    out["rules"] = [*(found.get("rules") or []), *rules]
    out["subjects"] = [*(found.get("subjects") or []), {"id": "osmo-every-peer"}]
    out["policies"] = [*(found.get("policies") or []),
                       {"id": "osmo-allow-list", "subjects": ["osmo-every-peer"],
                        "rules": [r["id"] for r in rules]}]
    conf.insert_json5("access_control", json.dumps(out))


def authenticates(config_file: str | None) -> bool:
    """True if the zenoh config ``config_file`` makes peers authenticate.

    User/password (``transport.auth.usrpwd`` with a dictionary file) or mutual TLS
    (``transport.link.tls.enable_mtls``).

    Raises:
        UsageError: the file cannot be read.
    """
    if not config_file:
        return False
    try:
        conf = zenoh.Config.from_file(config_file)
        usrpwd = json.loads(conf.get_json("transport/auth/usrpwd") or "{}")
        tls = json.loads(conf.get_json("transport/link/tls") or "{}")
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise UsageError(f"cannot read zenoh config {config_file}: {exc}") from exc
    return bool(usrpwd.get("dictionary_file")) or bool(tls.get("enable_mtls"))


_TLS_FILES = {"root_ca_certificate": "ca.crt", "connect_certificate": "tls.crt",
              "connect_private_key": "tls.key"}
_TLS_KEEP = ("enable_mtls", "verify_name_on_connect")


def client_credentials(config_file: str, folder: str) -> tuple[str, dict[str, str]]:
    """What a client of ``config_file`` shows a router, to hand to another client.

    Returns a zenoh config (JSON text) holding only the user/password and the TLS settings of
    ``config_file`` (nothing else of it: no listener, no dictionary, no access control), and
    the certificates and key it names, as name -> text (``ca.crt``, ``tls.crt``,
    ``tls.key``), named in that config as ``folder/<name>``, where the other client will
    find them.

    Raises:
        UsageError: the file, or a file it names, cannot be read.
    """
    try:
        conf = zenoh.Config.from_file(config_file)
        usrpwd = json.loads(conf.get_json("transport/auth/usrpwd") or "{}") or {}
        tls = json.loads(conf.get_json("transport/link/tls") or "{}") or {}
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise UsageError(f"cannot read zenoh config {config_file}: {exc}") from exc
    files: dict[str, str] = {}
    transport: dict[str, Any] = {}
    if usrpwd.get("user") is not None:
        transport["auth"] = {"usrpwd": {"user": usrpwd["user"],
                                        "password": usrpwd.get("password") or ""}}
    link_tls = {k: tls[k] for k in _TLS_KEEP if tls.get(k) is not None}
    for key, name in _TLS_FILES.items():
        if tls.get(key):
            try:
                with open(tls[key], encoding="utf-8") as f:
                    files[name] = f.read()
            except (OSError, ValueError) as exc:
                raise UsageError(f"cannot read {tls[key]} ({key} of zenoh config "
                                 f"{config_file}): {exc}") from exc
            link_tls[key] = f"{folder}/{name}"
    if link_tls:
        transport["link"] = {"tls": link_tls}
    return json.dumps({"transport": transport}, indent=2), files


def _refused(connect: Sequence[str], config_file: str | None, exc: Exception) -> ServerUnreachable:
    where = ", ".join(connect)
    detail = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()
    hint = ("check the address, and that the TLS certificates / user and password in "
            f"{config_file} match the server's" if config_file else
            "start one with `osmo server start`, or check --server / OSMO_SERVER; a server "
            "that requires TLS or a password needs --zenoh-config / OSMO_ZENOH_CONFIG")
    return ServerUnreachable(f"cannot connect to an osmo server at {where} "
                             f"(refused or unreachable: {detail}); {hint}")


class Request:
    """One query received by a queryable: its key, payload and attachment; answer once.

    A request may be answered from another thread; call :meth:`reply` (or :meth:`fail`)
    exactly once, which also releases it.
    """

    def __init__(self, query: zenoh.Query) -> None:
        self._query = query
        self.key = str(query.key_expr)
        self.payload = query.payload.to_bytes() if query.payload is not None else b""
        self.attachment = (query.attachment.to_bytes() if query.attachment is not None
                           else None)

    def reply(self, payload: bytes, attachment: bytes | None = None) -> None:
        """Send the answer and release the query (a vanished asker is ignored)."""
        try:
            self._query.reply(self._query.key_expr, payload, attachment=attachment)
        except zenoh.ZError:
            pass
        finally:
            self._query.drop()  # type: ignore[no-untyped-call]


class Subscription:
    """A handle on a subscriber, queryable or liveliness token; ``close()`` undeclares it."""

    def __init__(self, entity: Any) -> None:
        self._entity = entity

    def close(self) -> None:
        """Undeclare (idempotent; errors after the session closed are ignored)."""
        try:
            self._entity.undeclare()
        except zenoh.ZError:
            pass


class Link:
    """An open zenoh session scoped to one cluster prefix.

    ``Link.router(listen)`` is the server hosting the router (or joining one with
    ``connect``); ``Link.client(connect)`` is the CLI, SDK or a worker.
    """

    def __init__(self, session: zenoh.Session, cluster: str) -> None:
        self._session = session
        self.cluster = cluster
        self.prefix = f"osmo/{cluster}"

    @classmethod
    def router(cls, listen: Sequence[str], cluster: str = DEFAULT_CLUSTER, *,
               connect: Sequence[str] = (), config_file: str | None = None,
               peer: bool | None = None,
               allow: Mapping[str, Sequence[str]] | None = None,
               deny: Mapping[str, Sequence[str]] | None = None) -> Link:
        """Open the server's session.

        A router listening on ``listen``, or, with ``connect`` (and ``peer``, by default when
        ``listen`` is empty), a peer of an existing ``zenohd`` router. ``allow`` maps messages
        of :data:`MESSAGES` to the key expressions under the cluster's prefix that remote
        peers may use them on; ``deny`` takes keys back out of it (:class:`Acl`). None: no
        access control (a router joined with ``connect`` needs the rules in its own
        configuration).
        """
        mode = "peer" if (peer if peer is not None else connect and not listen) else "router"
        acl = (Acl(f"osmo/{cluster}", allow, deny or {})
               if allow is not None and mode == "router" else None)
        try:
            conf = _config(mode, listen=listen, connect=connect, config_file=config_file,
                           acl=acl)
            return cls(zenoh.open(conf), cluster)
        except zenoh.ZError as exc:
            where = ", ".join([*listen, *connect])
            raise InfrastructureError(f"cannot listen on / connect to {where}: {exc}") from exc

    @classmethod
    def client(cls, connect: Sequence[str], cluster: str = DEFAULT_CLUSTER, *,
               config_file: str | None = None) -> Link:
        """Open a client session to a router; ServerUnreachable if none answers."""
        config_file = config_file or os.environ.get("OSMO_ZENOH_CONFIG") or None
        try:
            conf = _config("client", connect=connect, config_file=config_file)
            return cls(zenoh.open(conf), cluster)
        except zenoh.ZError as exc:
            raise _refused(connect, config_file, exc) from exc

    def key(self, *parts: str) -> str:
        """A key expression under this cluster's prefix."""
        return "/".join((self.prefix, *parts))

    # -- publish / subscribe --------------------------------------------------------------

    def put(self, key: str, data: bytes, attachment: bytes | None = None) -> bool:
        """Put raw bytes, blocking (not dropping) when the link is congested; False on error."""
        try:
            self._session.put(key, data, attachment=attachment,
                              congestion_control=zenoh.CongestionControl.BLOCK)
        except zenoh.ZError:
            return False
        return True

    def subscribe_raw(self, key: str,
                      callback: Callable[[str, bytes, bytes | None], None]) -> Subscription:
        """Call ``callback(key, payload, attachment)`` for every sample on ``key``.

        It runs on a zenoh thread: keep it short.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            callback(str(sample.key_expr), sample.payload.to_bytes(), att)

        return Subscription(self._session.declare_subscriber(key, on_sample))

    # -- queries ---------------------------------------------------------------------------

    def serve(self, key: str, callback: Callable[[Request], object]) -> Subscription:
        """Declare a queryable on ``key``; ``callback`` gets each :class:`Request`.

        It runs on a zenoh thread: hand slow work to another thread and reply from there.
        """
        return Subscription(self._session.declare_queryable(
            key, lambda query: callback(Request(query))))

    def ask(self, key: str, payload: bytes = b"", *, attachment: bytes | None = None,
            timeout: float = 30.0) -> Any:
        """Send a query now; returns a pending answer for :meth:`answer`.

        So several queries can be in flight at once.
        """
        try:
            # every queryable, every reply: any peer may answer, so the asker must see them
            # all to keep the one it can authenticate (zenoh's default asks one "best"
            # queryable, and keeps one reply per key)
            return self._session.get(key, payload=payload, attachment=attachment,
                                     timeout=timeout, target=zenoh.QueryTarget.ALL,
                                     consolidation=zenoh.ConsolidationMode.NONE)
        except zenoh.ZError as exc:
            raise ServerUnreachable(f"query {key} failed: {exc}") from exc

    @staticmethod
    def replies(pending: Any) -> Iterator[tuple[bytes, bytes | None]]:
        """Each good reply of a pending query as it arrives: ``(payload, attachment)``.

        Ends when every queryable answered or the query's timeout passed. Any peer may answer
        a query: the caller believes only replies it can authenticate (``osmo.transport.seal``).
        """
        try:
            for reply in pending:
                if reply.ok is not None:
                    ok = reply.ok
                    att = ok.attachment.to_bytes() if ok.attachment is not None else None
                    yield ok.payload.to_bytes(), att
        except zenoh.ZError:
            return

    # -- liveliness ------------------------------------------------------------------------

    def token(self, key: str) -> Subscription:
        """Declare a liveliness token.

        Peers watching see ``key`` alive until it is closed or this process dies or is cut off
        (noticed within the lease).
        """
        try:
            return Subscription(self._session.liveliness().declare_token(key))
        except zenoh.ZError as exc:
            raise InfrastructureError(f"cannot declare liveliness token {key}: {exc}") from exc

    def watch(self, key: str, callback: Callable[[str, bool], None]) -> Subscription:
        """Call ``callback(key, alive)`` when a token matching ``key`` comes or goes.

        The tokens that exist already count too.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        return Subscription(self._session.liveliness().declare_subscriber(
            key, on_sample, history=True))

    def alive(self, key: str, timeout: float = 2.0) -> list[str]:
        """Keys of the live tokens matching ``key`` right now."""
        try:
            replies: Iterable[Any] = self._session.liveliness().get(key, timeout=timeout)
            return [str(r.ok.key_expr) for r in replies if r.ok is not None]
        except zenoh.ZError:
            return []

    def close(self) -> None:
        """Close the session (idempotent)."""
        try:
            self._session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError:
            pass
