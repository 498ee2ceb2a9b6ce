"""The one module that imports zenoh: sessions, the request/reply API, and event publishing.

Key expressions live under one prefix per cluster: ``osmo/<cluster>/...``.

- ``osmo/<cluster>/api/<verb>`` — the server's queryable; a request is a JSON object, the
  reply a JSON object ``{"ok": ...}`` or ``{"error": {"type": ..., "message": ...}}``.
- ``osmo/<cluster>/events/<workflow_id>`` — the server publishes a small JSON notice whenever
  a workflow's state changes (clients waiting on it re-query instead of polling fast).

Defaults keep everything on loopback with scouting off. zenoh raises one exception type
(``ZError``); it is translated here into ``ServerUnreachable``/``InfrastructureError``.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import zenoh

from osmo.errors import InfrastructureError, OsmoError, ServerUnreachable

__all__ = ["ApiClient", "ApiServer", "Link", "RemoteError"]

Handler = Callable[[str, dict[str, Any]], Any]


class RemoteError(OsmoError):
    """An error raised by the server while handling a request, carried back to the client.

    ``type_name`` is the server-side class name (e.g. ``SpecError``); the CLI exits with
    ``exit_code``, which the server sends along.
    """

    def __init__(self, type_name: str, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.type_name = type_name
        self.exit_code = exit_code


def _config(mode: str, *, listen: list[str] = (), connect: list[str] = ()) -> zenoh.Config:  # type: ignore[assignment]
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


class Link:
    """An open zenoh session scoped to one cluster prefix.

    Use ``Link.router(listen)`` for the server (it hosts the router) and
    ``Link.client(connect)`` for the CLI, SDK and remote workers.
    """

    def __init__(self, session: zenoh.Session, cluster: str) -> None:
        self._session = session
        self.prefix = f"osmo/{cluster}"

    @classmethod
    def router(cls, listen: list[str], cluster: str = "local") -> Link:
        """Open a router session listening on ``listen`` endpoints (``tcp/127.0.0.1:7447``)."""
        try:
            return cls(zenoh.open(_config("router", listen=listen)), cluster)
        except zenoh.ZError as exc:
            raise InfrastructureError(f"cannot listen on {', '.join(listen)}: {exc}") from exc

    @classmethod
    def client(cls, connect: list[str], cluster: str = "local") -> Link:
        """Open a client session to a router; ServerUnreachable if none answers."""
        try:
            return cls(zenoh.open(_config("client", connect=connect)), cluster)
        except zenoh.ZError as exc:
            raise ServerUnreachable(
                f"no osmo server reachable at {', '.join(connect)} "
                "(start one with `osmo server start`, or check --server / OSMO_SERVER)"
            ) from exc

    def key(self, *parts: str) -> str:
        """A key expression under this cluster's prefix."""
        return "/".join((self.prefix, *parts))

    def publish(self, key: str, message: dict[str, Any]) -> None:
        """Put a JSON message on ``key`` (best effort; errors are not fatal to the caller)."""
        try:
            self._session.put(key, json.dumps(message).encode())
        except zenoh.ZError:
            pass

    def subscribe(self, key: str, callback: Callable[[dict[str, Any]], None]) -> Any:
        """Call ``callback(message)`` for every JSON message on ``key``; returns the handle."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(json.loads(sample.payload.to_bytes() or b"{}"))

        return self._session.declare_subscriber(key, on_sample)

    def close(self) -> None:
        """Close the session (idempotent)."""
        try:
            self._session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError:
            pass

    @property
    def session(self) -> zenoh.Session:
        """The raw session, for the few adapters that extend this module."""
        return self._session


class ApiServer:
    """Serves ``<prefix>/api/<verb>`` queries with ``handler(verb, request) -> result``.

    Handlers run on a small thread pool so a slow request never blocks zenoh's own threads.
    An ``OsmoError`` becomes an error reply with its class name and exit code; any other
    exception becomes an ``InfrastructureError`` reply (the server logs the traceback).
    """

    def __init__(self, link: Link, handler: Handler, *, threads: int = 8,
                 on_crash: Callable[[BaseException], None] | None = None) -> None:
        self._link = link
        self._handler = handler
        self._on_crash = on_crash
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-api")
        self._prefix = link.key("api") + "/"
        self._queryable = link.session.declare_queryable(link.key("api", "**"), self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        self._pool.submit(self._serve, query)

    def _serve(self, query: zenoh.Query) -> None:
        verb = str(query.key_expr)[len(self._prefix):]
        try:
            request = json.loads(query.payload.to_bytes()) if query.payload else {}
            reply: dict[str, Any] = {"ok": self._handler(verb, request)}
        except OsmoError as exc:
            reply = {"error": _error_dict(exc)}
        except Exception as exc:  # noqa: BLE001 - reported to the client, logged by the server
            if self._on_crash:
                self._on_crash(exc)
            reply = {"error": {"type": "InfrastructureError", "exit_code": 3,
                               "message": f"server error in '{verb}': {exc!r}"}}
        try:
            query.reply(query.key_expr, json.dumps(reply).encode())
        except zenoh.ZError:
            pass  # the client went away
        finally:
            query.drop()  # type: ignore[no-untyped-call]

    def close(self) -> None:
        """Stop serving and wait for in-flight handlers."""
        self._queryable.undeclare()  # type: ignore[no-untyped-call]
        self._pool.shutdown(wait=True)


def _error_dict(exc: OsmoError) -> dict[str, Any]:
    out: dict[str, Any] = {"type": type(exc).__name__, "message": str(exc),
                           "exit_code": exc.exit_code}
    diags = getattr(exc, "diagnostics", None)
    if diags:
        out["diagnostics"] = [d.__dict__ for d in diags]
    return out


class ApiClient:
    """Calls the server's API over a client ``Link``."""

    def __init__(self, link: Link, *, timeout: float = 30.0) -> None:
        self._link = link
        self._timeout = timeout
        self._lock = threading.Lock()

    def call(self, verb: str, request: dict[str, Any] | None = None,
             *, timeout: float | None = None) -> Any:
        """Send ``request`` to ``verb`` and return the result.

        Raises:
            ServerUnreachable: no server replied within the timeout.
            RemoteError: the server raised an error (type, message and exit code kept).
        """
        payload = json.dumps(request or {}).encode()
        try:
            replies = list(self._link.session.get(
                self._link.key("api", verb), payload=payload,
                timeout=timeout if timeout is not None else self._timeout))
        except zenoh.ZError as exc:
            raise ServerUnreachable(f"request '{verb}' failed: {exc}") from exc
        for reply in replies:
            if reply.ok is None:
                continue
            body = json.loads(reply.ok.payload.to_bytes())
            if "error" in body:
                err = body["error"]
                raise _remote_error(err)
            return body["ok"]
        raise ServerUnreachable(
            f"no osmo server answered '{verb}' at {self._link.prefix} "
            "(is it running? `osmo server status`)"
        )


def _remote_error(err: dict[str, Any]) -> OsmoError:
    """Rebuild the server's error as the matching local class where one exists."""
    from osmo import errors

    diags = err.get("diagnostics")
    if err["type"] == "SpecError" and diags:
        return errors.SpecError([errors.Diagnostic(**d) for d in diags])
    cls = getattr(errors, err["type"], None)
    if isinstance(cls, type) and issubclass(cls, OsmoError) and cls not in (
        errors.SpecError, errors.WorkflowFailed
    ):
        return cls(err["message"])
    return RemoteError(err["type"], err["message"], int(err.get("exit_code", 1)))
