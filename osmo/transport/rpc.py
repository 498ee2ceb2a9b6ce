"""The client API over a :class:`~osmo.transport.zenoh_link.Link`: JSON request/reply.

- ``osmo/<cluster>/api/<verb>`` — the server's queryable; a request is a JSON object, the
  reply a JSON object ``{"ok": ...}`` or ``{"error": {"type": ..., "message": ...}}``.
- ``osmo/<cluster>/events/<workflow_id>`` — the server publishes a small JSON notice whenever
  a workflow's state changes (clients waiting on it re-query instead of polling fast).

Every request carries its caller's token as the zenoh attachment (``osmo.transport.auth``);
the server authenticates it once per request and hands the handler the caller's
:class:`~osmo.transport.auth.Identity`. A request without a valid token is refused
(``NotAuthenticated``, exit 3) and logged in one line, before its body is read.

Server-side errors travel as their class name, message and exit code and are rebuilt as the
matching ``osmo.errors`` class on the client. A request that is not a JSON object, or whose
fields have the wrong type (see :func:`field`), is the client's mistake: a ``UsageError``
(exit 2) and one line in the server's log, never an ``InfrastructureError``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from osmo.errors import NotAuthenticated, OsmoError, ServerUnreachable, UsageError
from osmo.names import shown
from osmo.transport.auth import Identity
from osmo.transport.zenoh_link import Link, Request

__all__ = ["ApiClient", "ApiServer", "RemoteError", "field", "str_list", "str_map"]

Handler = Callable[[str, dict[str, Any], Identity], Any]
Authenticate = Callable[[bytes | None], Identity]
log = logging.getLogger("osmo.api")
_REQUIRED: Any = object()
_KINDS = {str: "a string", int: "a whole number", bool: "true or false", dict: "an object",
          list: "a list"}
MAX_INT = 2**63 - 1  # what SQLite stores; larger numbers in a request are refused


def field(request: dict[str, Any], key: str, kind: type, *, default: Any = _REQUIRED,
          max_len: int | None = None, what: str | None = None) -> Any:
    """``request[key]``, checked to be a ``kind`` (str, int, bool, dict or list).

    A missing or null field gives ``default`` if one is given. Integers must fit in 64 bits;
    ``max_len`` bounds a string's length.

    Raises:
        UsageError: naming the field and what it must be.
    """
    name = what or f"'{key}'"
    value = request.get(key)
    if value is None:
        if default is _REQUIRED:
            raise UsageError(f"the request needs {name} ({_KINDS[kind]})")
        return default
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise UsageError(f"{name} must be {_KINDS[kind]}, not {type(value).__name__}")
    if isinstance(value, int) and not -MAX_INT <= value <= MAX_INT:
        raise UsageError(f"{name} is out of range: {shown(value)}")
    if isinstance(value, str | list | dict) and max_len is not None and len(value) > max_len:
        raise UsageError(f"{name} is too long ({len(value)} characters; the limit is {max_len})")
    return value


def str_list(request: dict[str, Any], key: str) -> list[str]:
    """``request[key]`` as a list of strings ([] if absent).

    Raises:
        UsageError: it is not a list of strings.
    """
    items = field(request, key, list, default=[])
    if not all(isinstance(item, str) for item in items):
        raise UsageError(f"'{key}' must be a list of strings")
    return list(items)


def str_map(request: dict[str, Any], key: str) -> dict[str, str]:
    """``request[key]`` as an object of string values ({} if absent).

    Raises:
        UsageError: it is not an object of strings.
    """
    items = field(request, key, dict, default={})
    if not all(isinstance(value, str) for value in items.values()):
        raise UsageError(f"'{key}' must be an object whose values are strings")
    return dict(items)


def _request_body(payload: bytes) -> dict[str, Any]:
    """The JSON object a request carries.

    Raises:
        UsageError: the payload is not JSON, not an object, or nested too deeply.
    """
    try:
        body = json.loads(payload) if payload else {}
    except (ValueError, RecursionError) as exc:
        raise UsageError(f"the request is not valid JSON: {str(exc)[:200]}") from None
    if not isinstance(body, dict):
        raise UsageError(f"the request must be a JSON object, not {type(body).__name__}")
    return body


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
    """Serves ``<prefix>/api/<verb>`` queries with ``handler(verb, request, identity)``.

    ``authenticate(attachment)`` names the caller of each request, once, before anything
    else. Handlers run on a small thread pool so a slow request never blocks zenoh's own
    threads, except the ``inline`` verbs: cheap ones whose order matters (a worker's
    reports), answered on the zenoh thread in the order they arrived. An ``OsmoError``
    becomes an error reply with its class name and exit code; any other exception becomes
    an ``InfrastructureError`` reply (the server logs the traceback).
    """

    def __init__(self, link: Link, handler: Handler, authenticate: Authenticate, *,
                 threads: int = 8, on_crash: Callable[[BaseException], None] | None = None,
                 inline: frozenset[str] = frozenset()) -> None:
        self._handler = handler
        self._authenticate = authenticate
        self._on_crash = on_crash
        self._inline = inline
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-api")
        self._prefix = link.key("api") + "/"
        self._queryable = link.serve(link.key("api", "**"), self._dispatch)

    def _dispatch(self, request: Request) -> None:
        if request.key[len(self._prefix):] in self._inline:
            self._serve(request)
        else:
            self._pool.submit(self._serve, request)

    def _serve(self, request: Request) -> None:
        verb = request.key[len(self._prefix):]
        try:
            who = self._authenticate(request.attachment)
            reply: dict[str, Any] = {
                "ok": self._handler(verb, _request_body(request.payload), who)}
        except NotAuthenticated as exc:
            log.warning("refused %s from an unauthenticated caller: %s", shown(verb), exc)
            reply = {"error": _error_dict(exc)}
        except UsageError as exc:  # the client's mistake: one line, no traceback
            log.warning("refused a %s request: %r", shown(verb), str(exc)[:300])
            reply = {"error": _error_dict(exc)}
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
    """Calls the server's API over a client ``Link``, every request carrying ``token``."""

    def __init__(self, link: Link, *, timeout: float = 30.0, token: str | None = None) -> None:
        self._link = link
        self._timeout = timeout
        self._token = token.strip().encode() if token else None

    @property
    def token(self) -> bytes | None:
        """The token every request carries (also for blob requests to the server)."""
        return self._token

    def send(self, verb: str, request: dict[str, Any]) -> None:
        """Send ``request`` to ``verb`` without waiting for the answer.

        For a stream of small reports whose order matters and whose loss is repaired
        elsewhere (a worker's reports; its exit reports are resent until acknowledged).
        """
        self._link.ask(self._link.key("api", verb), json.dumps(request).encode(),
                       attachment=self._token, timeout=self._timeout)

    def call(self, verb: str, request: dict[str, Any] | None = None,
             *, timeout: float | None = None) -> Any:
        """Send ``request`` to ``verb`` and return the result.

        Raises:
            ServerUnreachable: no server replied within the timeout.
            RemoteError: the server raised an error (type, message and exit code kept).
        """
        payload = json.dumps(request or {}).encode()
        answer = self._link.request(self._link.key("api", verb), payload,
                                    attachment=self._token,
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
