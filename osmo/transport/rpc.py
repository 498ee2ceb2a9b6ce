"""The client API over a :class:`~osmo.transport.zenoh_link.Link`: JSON request/reply.

- ``osmo/<cluster>/api/<verb>`` — the server's queryable; a request is a JSON object, the
  reply a JSON object ``{"ok": ...}`` or ``{"error": {"type": ..., "message": ...}}``.
- ``osmo/<cluster>/events/<workflow_id>`` — the server publishes a small JSON notice whenever
  a workflow's state changes (clients waiting on it re-query instead of polling fast).

Every request but ``api/hello`` is sealed on a channel opened with the caller's token
(``osmo.transport.seal``: the token itself never crosses the bus); the server opens it,
checks once that the token is still live and hands the handler the caller's
:class:`~osmo.transport.auth.Identity`, and seals its reply on the same channel. A client
believes only sealed replies. A request that is not sealed on a channel the server knows is
refused (``NotAuthenticated``, exit 3) in one line, before its body is read; the client then
says hello again once (the server restarted) and repeats the request.

Server-side errors travel as their class name, message and exit code and are rebuilt as the
matching ``osmo.errors`` class on the client. A request that is not a JSON object, or whose
fields have the wrong type (see :func:`field`), is the client's mistake: a ``UsageError``
(exit 2) and one line in the server's log, never an ``InfrastructureError``.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

from osmo.errors import NotAuthenticated, OsmoError, ServerUnreachable, UsageError
from osmo.names import shown
from osmo.transport.auth import Identity
from osmo.transport.blobs import Opener, Sealer
from osmo.transport.seal import (
    HEADER,
    Channel,
    ChannelTable,
    HelloError,
    Purpose,
    Verifier,
    finish,
    hello,
    parse_header,
    seal_json,
)
from osmo.transport.zenoh_link import Link, Request

__all__ = ["HELLO", "ApiClient", "ApiServer", "Gate", "Pending", "RemoteError", "ServerAsker",
           "ask_back", "field", "gate_opener", "str_list", "str_map"]

Handler = Callable[[str, dict[str, Any], Identity], Any]
HELLO = "hello"
"""The one verb asked in clear: it opens a sealed channel (``osmo.transport.seal``)."""
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


class Gate(Protocol):
    """What the API needs of the server's authentication (``osmo.server.auth``)."""

    channels: ChannelTable

    def identity(self, digest: str, channel: bytes) -> Identity:
        """The live token with sha256 ``digest`` as an identity on ``channel``.

        Raises:
            NotAuthenticated: the token was revoked.
        """


def _unsealed(message: str) -> bytes:
    """A reply that is not sealed: the caller has no channel here (it says hello again)."""
    err = {"type": "NotAuthenticated", "exit_code": NotAuthenticated.exit_code,
           "message": message}
    return json.dumps({"error": err, "hello": True}).encode()


class ApiServer:
    """Serves ``<prefix>/api/<verb>`` queries with ``handler(verb, request, identity)``.

    ``root``: another key than ``api`` (a node's own small API, e.g. its pods' data).

    ``api/hello`` opens a channel (``osmo.transport.seal``); every other request must be
    sealed on one, and names its caller by it: ``gate.identity`` checks, once per request and
    before anything else, that the channel's token is still live. The reply is sealed on the
    same channel. Handlers run on a small thread pool so a slow request never blocks zenoh's
    own threads, except the ``inline`` verbs: cheap ones whose order matters (a worker's
    reports), answered on the zenoh thread in the order they arrived. An ``OsmoError``
    becomes an error reply with its class name and exit code; any other exception becomes
    an ``InfrastructureError`` reply (the server logs the traceback).
    """

    def __init__(self, link: Link, handler: Handler, gate: Gate, *,
                 threads: int = 8, on_crash: Callable[[BaseException], None] | None = None,
                 inline: frozenset[str] = frozenset(), root: str = "api") -> None:
        self._handler = handler
        self._gate = gate
        self._on_crash = on_crash
        self._inline = inline
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-api")
        self._cut = len(link.prefix) + 1
        self._prefix = link.key(root) + "/"
        self._queryable = link.serve(link.key(root, "**"), self._dispatch)

    def _dispatch(self, request: Request) -> None:
        if request.key[len(self._prefix):] in self._inline:
            self._serve(request)
        else:
            self._pool.submit(self._serve, request)

    def _serve(self, request: Request) -> None:
        verb, rel = request.key[len(self._prefix):], request.key[self._cut:]
        if verb == HELLO:
            self._hello(request)
            return
        opened = self._gate.channels.open(Purpose.REQ, rel, request.attachment,
                                          request.payload)
        if opened is None:  # unsealed, forged, replayed, or a channel this server forgot
            log.warning("refused an unsealed %s request (no channel of this server)",
                        shown(verb))
            request.reply(_unsealed("the request was not sealed on a channel of this server "
                                    "(it restarted, or the request is forged); say hello "
                                    "again"))
            return
        channel, digest, seq, body = opened
        reply = self._answer(verb, digest, channel.id, body)
        attachment, payload = seal_json(channel, Purpose.REP, rel, reply, seq)
        request.reply(payload, attachment)

    def _hello(self, request: Request) -> None:
        try:
            request.reply(self._gate.channels.accept(request.payload))
        except HelloError as exc:
            log.warning("refused a hello: %s", exc)
            request.reply(_unsealed(
                "this osmo server does not know this token (unknown or revoked); ask its "
                "admin for a new one" if str(exc) == "unknown token" else str(exc)))

    def _answer(self, verb: str, digest: str, channel: bytes, body: bytes) -> dict[str, Any]:
        try:
            who = self._gate.identity(digest, channel)
            return {"ok": self._handler(verb, _request_body(body), who)}
        except NotAuthenticated as exc:
            log.warning("refused %s from an unauthenticated caller: %s", shown(verb), exc)
            return {"error": _error_dict(exc)}
        except UsageError as exc:  # the client's mistake: one line, no traceback
            log.warning("refused a %s request: %r", shown(verb), str(exc)[:300])
            return {"error": _error_dict(exc)}
        except OsmoError as exc:
            return {"error": _error_dict(exc)}
        except Exception as exc:  # noqa: BLE001 - reported to the client, logged by the server
            if self._on_crash:
                self._on_crash(exc)
            return {"error": {"type": "InfrastructureError", "exit_code": 3,
                              "message": f"server error in '{verb}': {exc!r}"}}

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


@dataclass(frozen=True)
class Pending:
    """A sealed query in flight, and the purpose its answer must be sealed for."""

    query: Any
    channel: Channel
    seq: int
    rel: str
    reply: Purpose


def _ask(link: Link, channel: Channel, purpose: Purpose, reply: Purpose, rel: str,
         payload: bytes, timeout: float) -> Pending:
    attachment, sealed = channel.seal(purpose, rel, payload)
    query = link.ask(link.key(rel), sealed, attachment=attachment, timeout=timeout)
    return Pending(query, channel, HEADER.unpack(attachment)[3], rel, reply)


def _answer(pending: Pending) -> tuple[bool, bytes] | None:
    """The answer to ``pending``: ``(sealed, payload)``.

    The first reply sealed for it is returned at once (``sealed`` True); an unsealed one only
    if no sealed one came (``sealed`` False); None if nobody answered in time.
    """
    fallback = None
    for payload, attachment in Link.replies(pending.query):
        opened = pending.channel.open(pending.reply, pending.rel, attachment, payload,
                                      seq=pending.seq)
        if opened is not None:
            return True, opened[1]
        fallback = fallback or (False, payload)
    return fallback


def gate_opener(gate: Gate) -> Opener:
    """Opens requests sealed on the server's channels for a blob server (``REQ``/``REP``)."""

    def open_request(rel: str, attachment: bytes | None, payload: bytes
                     ) -> tuple[Identity | None, bytes, Sealer] | None:
        opened = gate.channels.open(Purpose.REQ, rel, attachment, payload)
        if opened is None:
            return None
        channel, digest, seq, body = opened
        try:
            who = gate.identity(digest, channel.id)
        except NotAuthenticated:
            return None
        return who, body, lambda data: channel.seal(Purpose.REP, rel, data, seq)

    return open_request


def ask_back(link: Link, gate: Gate, channel: bytes) -> ServerAsker | None:
    """A :class:`ServerAsker` on the server's channel ``channel`` (None: not open any more)."""
    found = gate.channels.get(channel) if channel else None
    return ServerAsker(link, found[0]) if found is not None else None


class ServerAsker:
    """The server asking a client's own queryable on that client's channel (``SQ``/``SR``).

    So the server pulls a worker's outputs, or an upload's blobs, from the peer that opened
    ``channel``, and believes only that peer's sealed answers (an ``Asker`` of
    ``osmo.transport.blobs``).
    """

    def __init__(self, link: Link, channel: Channel, timeout: float = 30.0) -> None:
        self._link, self._channel, self._timeout = link, channel, timeout

    def ask(self, rel: str, payload: bytes, *, timeout: float | None = None) -> Pending:
        """Send ``payload`` sealed to ``rel``; don't wait."""
        return _ask(self._link, self._channel, Purpose.SQ, Purpose.SR, rel, payload,
                    timeout if timeout is not None else self._timeout)

    @staticmethod
    def answer(pending: Pending) -> tuple[bool, bytes] | None:
        """``(sealed, payload)`` of the answer (see :func:`_answer`)."""
        return _answer(pending)


class ApiClient:
    """Calls the server's API over a client ``Link`` on a sealed channel of ``token``.

    The channel is opened with the first call (``api/hello``) and again whenever the server
    says it does not know it (it restarted). Only replies sealed on the channel are believed;
    an unsealed one (an error, or a forgery) counts only if no sealed one comes.
    """

    def __init__(self, link: Link, *, timeout: float = 30.0, token: str | None = None,
                 root: str = "api") -> None:
        self._link = link
        self._root = root
        self._timeout = timeout
        self._token = token.strip() if token else None
        self._lock = threading.Lock()
        self._channel: Channel | None = None
        self._recent: OrderedDict[bytes, Channel] = OrderedDict()
        self.verifier: Verifier | None = None
        """Checks the server's signed notices (known once a channel is open)."""

    @property
    def link(self) -> Link:
        """The zenoh link this client talks over."""
        return self._link

    def channel(self) -> Channel:
        """The open channel (opened now if there is none).

        Raises:
            NotAuthenticated: no token, or one the server does not know.
            ServerUnreachable: no server answered the hello.
        """
        with self._lock:
            if self._channel is None:
                self._channel, self.verifier = self._hello()
                self._recent[self._channel.id] = self._channel
                while len(self._recent) > _RECENT:
                    self._recent.popitem(last=False)
            return self._channel

    def _hello(self) -> tuple[Channel, Verifier]:
        if not self._token:
            raise NotAuthenticated(
                "this osmo server needs a token: give one with --token, OSMO_TOKEN or "
                "`osmo profile set token TOKEN` (an admin creates it with `osmo token "
                "create NAME --role user`)")
        shake = hello(self._token)
        pending = self._link.ask(self._link.key(self._root, HELLO), shake.request(),
                                 timeout=self._timeout)
        error: dict[str, Any] | None = None
        for payload, _att in Link.replies(pending):
            done = finish(shake, payload)
            if done is not None:
                return done
            error = error or _error_of(payload)
        if error is not None:
            raise _remote_error(error)
        raise ServerUnreachable(f"no osmo server answered at {self._link.prefix} (is it "
                                "running? `osmo server status`)")

    def _forget(self, channel: Channel) -> None:
        with self._lock:
            if self._channel is channel:
                self._channel = None

    def opened(self, purpose: Purpose, rel: str, attachment: bytes | None, data: bytes
               ) -> tuple[Channel, int, bytes] | None:
        """Open a message the server sealed on one of this client's recent channels.

        Returns ``(channel, seq, plaintext)``; None: not the server's (dropped).
        """
        head = parse_header(attachment)
        with self._lock:
            channel = self._recent.get(head[1]) if head is not None else None
        opened = channel.open(purpose, rel, attachment, data) if channel else None
        return (channel, opened[0], opened[1]) if channel and opened else None

    def ask(self, rel: str, payload: bytes, *, timeout: float | None = None) -> Pending:
        """Send ``payload`` sealed to key ``rel`` (under the cluster prefix); don't wait."""
        return _ask(self._link, self.channel(), Purpose.REQ, Purpose.REP, rel, payload,
                    timeout if timeout is not None else self._timeout)

    @staticmethod
    def answer(pending: Pending) -> tuple[bool, bytes] | None:
        """``(sealed, payload)`` of the answer to ``pending`` (see :func:`_answer`)."""
        return _answer(pending)

    def open_asked(self, rel: str, attachment: bytes | None, payload: bytes
                   ) -> tuple[Identity | None, bytes, Sealer] | None:
        """An ``Opener`` of the server's queries to this client (``SQ``, answered ``SR``)."""
        opened = self.opened(Purpose.SQ, rel, attachment, payload)
        if opened is None:
            return None
        channel, seq, body = opened
        return None, body, lambda data: channel.seal(Purpose.SR, rel, data, seq)

    def send(self, verb: str, request: dict[str, Any]) -> None:
        """Send ``request`` to ``verb`` without waiting for the answer.

        For a stream of small reports whose order matters and whose loss is repaired
        elsewhere (a worker's reports; its exit reports are resent until acknowledged). It
        never waits for a hello either: with no channel open (the server restarted and the
        next :meth:`call` has not opened a new one yet), the request is dropped.
        """
        with self._lock:
            channel = self._channel
        if channel is None:
            log.info("dropped a %s request: no channel open yet", shown(verb))
            return
        _ask(self._link, channel, Purpose.REQ, Purpose.REP, f"{self._root}/{verb}",
             json.dumps(request).encode(), self._timeout)

    def call(self, verb: str, request: dict[str, Any] | None = None,
             *, timeout: float | None = None) -> Any:
        """Send ``request`` to ``verb`` and return the result.

        Raises:
            ServerUnreachable: no server replied within the timeout.
            NotAuthenticated: no token, or one the server does not know (or revoked).
            RemoteError: the server raised an error (type, message and exit code kept).
        """
        payload = json.dumps(request or {}).encode()
        for again in (False, True):
            pending = self.ask(f"{self._root}/{verb}", payload, timeout=timeout)
            answer = self.answer(pending)
            if answer is None:
                raise ServerUnreachable(
                    f"no osmo server answered '{verb}' at {self._link.prefix} "
                    "(is it running? `osmo server status`)")
            sealed, data = answer
            body = json.loads(data) if sealed else _unsealed_body(data)
            if not sealed and body.get("hello") and not again:
                self._forget(pending.channel)  # the server restarted: a new channel
                continue
            if "error" in body:
                raise _remote_error(body["error"])
            return body["ok"]
        raise AssertionError("unreachable")


_RECENT = 4  # channels whose server messages a client still opens (a restart, a new hello)


def _unsealed_body(data: bytes) -> dict[str, Any]:
    """An unsealed reply, believed only as an error (never as a result)."""
    error = _error_of(data)
    if error is None:
        error = {"type": "NotAuthenticated", "exit_code": NotAuthenticated.exit_code,
                 "message": "the answer was not sealed by the server (an impostor?)"}
    try:
        again = bool(json.loads(data).get("hello"))
    except (ValueError, AttributeError):
        again = False
    return {"error": error, "hello": again}


def _error_of(payload: bytes) -> dict[str, Any] | None:
    """The error an unsealed reply carries (None: none that reads as one)."""
    try:
        err = json.loads(payload).get("error")
    except (ValueError, AttributeError, RecursionError):
        return None
    if not (isinstance(err, dict) and isinstance(err.get("type"), str)
            and isinstance(err.get("message"), str)):
        return None
    return {"type": err["type"], "message": err["message"][:2000],
            "exit_code": int(err.get("exit_code") or 1) if isinstance(
                err.get("exit_code"), int) else 1}


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
