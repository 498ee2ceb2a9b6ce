"""The client API over a :class:`~osmo.transport.zenoh_link.Link`: JSON request/reply.

- ``osmo/<cluster>/api/<verb>`` — the server's queryable; a request is a JSON object, the
  reply a JSON object ``{"ok": ...}`` or ``{"error": {"type": ..., "message": ...}}``.
- ``osmo/<cluster>/events/<workflow_id>`` — the server publishes a small JSON notice whenever
  a workflow's state changes (clients waiting on it re-query instead of polling fast).

Server-side errors travel as their class name, message and exit code and are rebuilt as the
matching ``osmo.errors`` class on the client.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from osmo.errors import OsmoError, ServerUnreachable
from osmo.transport.zenoh_link import Link, Request

__all__ = ["ApiClient", "ApiServer", "RemoteError"]

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


class ApiServer:
    """Serves ``<prefix>/api/<verb>`` queries with ``handler(verb, request) -> result``.

    Handlers run on a small thread pool so a slow request never blocks zenoh's own threads.
    An ``OsmoError`` becomes an error reply with its class name and exit code; any other
    exception becomes an ``InfrastructureError`` reply (the server logs the traceback).
    """

    def __init__(self, link: Link, handler: Handler, *, threads: int = 8,
                 on_crash: Callable[[BaseException], None] | None = None) -> None:
        self._handler = handler
        self._on_crash = on_crash
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-api")
        self._prefix = link.key("api") + "/"
        self._queryable = link.serve(link.key("api", "**"),
                                     lambda req: self._pool.submit(self._serve, req))

    def _serve(self, request: Request) -> None:
        verb = request.key[len(self._prefix):]
        try:
            body = json.loads(request.payload) if request.payload else {}
            reply: dict[str, Any] = {"ok": self._handler(verb, body)}
        except OsmoError as exc:
            reply = {"error": _error_dict(exc)}
        except Exception as exc:  # noqa: BLE001 - reported to the client, logged by the server
            if self._on_crash:
                self._on_crash(exc)
            reply = {"error": {"type": "InfrastructureError", "exit_code": 3,
                               "message": f"server error in '{verb}': {exc!r}"}}
        request.reply(json.dumps(reply).encode())

    def close(self) -> None:
        """Stop serving and wait for in-flight handlers."""
        self._queryable.close()
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

    def call(self, verb: str, request: dict[str, Any] | None = None,
             *, timeout: float | None = None) -> Any:
        """Send ``request`` to ``verb`` and return the result.

        Raises:
            ServerUnreachable: no server replied within the timeout.
            RemoteError: the server raised an error (type, message and exit code kept).
        """
        payload = json.dumps(request or {}).encode()
        answer = self._link.request(self._link.key("api", verb), payload,
                                    timeout=timeout if timeout is not None else self._timeout)
        if answer is None:
            raise ServerUnreachable(
                f"no osmo server answered '{verb}' at {self._link.prefix} "
                "(is it running? `osmo server status`)")
        body = json.loads(answer[0])
        if "error" in body:
            raise _remote_error(body["error"])
        return body["ok"]


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
