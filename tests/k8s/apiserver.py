"""A Kubernetes API server stand-in on loopback: the REST wire protocol over :class:`Store`.

It speaks what the official ``kubernetes`` client sends and expects, so the client's
serialisation, watch and error paths run for real:

- ``/api/v1/...`` and ``/apis/GROUP/VERSION/...``, namespaced or not, for the resources of
  ``store.RESOURCES``; verbs get, list, watch (``?watch=true``), create, update (PUT), patch
  (``patches.py``), delete and deletecollection; ``pods/log`` (``follow=true`` streams) and
  ``pods/status``; ``pods/exec`` (a WebSocket upgrade speaking ``v5``/``v4.channel.k8s.io``,
  ``websocket.py``; the node runs the command) and ``pods/portforward`` (``v4.channel.k8s.io``,
  two channels a port; the node dials the pod's port); ``dryRun=All``; label and field
  selectors; ``limit``/``continue``.
- A watch is a chunked stream of JSON lines ``{"type": ..., "object": ...}``; one from a
  version the history no longer holds gets a single ERROR event carrying a 410 Expired Status,
  as the real server's watch cache sends it (HTTP 200). ``timeoutSeconds`` ends it.
- Errors are Status bodies with the real codes and reasons: 400 BadRequest, 404 NotFound,
  405 MethodNotAllowed, 409 AlreadyExists/Conflict, 410 Expired, 415, 422 Invalid (with every
  cause, ``validation.py``).
- Every request is counted by (verb, resource) in ``calls``; ``writes`` keeps the writes
  (create, update, patch, delete, deletecollection) for a benchmark's writes per attempt.

The node side (``kubelet.py``) is separate: it reads the store, publishes pod status and
serves logs through the :class:`LogSource` set as ``log_source``. No authentication: the
server listens on 127.0.0.1 only.
"""

from __future__ import annotations

import base64
import collections
import json
import os
import queue
import re
import select
import socket
import struct
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from tests.k8s import store as st
from tests.k8s.patches import apply_patch
from tests.k8s.selectors import Predicate, SelectorError, field_selector, label_selector
from tests.k8s.store import ApiError, Obj, Resource, Store
from tests.k8s.validation import Cause, SchemaCheck, check, decode_secret_data
from tests.k8s.websocket import CLOSE, WebSocket, accept_key

__all__ = ["ApiServer", "ExecSource", "LogSource"]

_PATH = re.compile(r"^/(?:api/v1|apis/(?P<group>[^/]+)/(?P<version>[^/]+))"
                   r"(?:/namespaces/(?P<ns>[^/]+))?/(?P<plural>[^/]+)"
                   r"(?:/(?P<name>[^/]+)(?:/(?P<sub>[^/]+))?)?$")
WRITES = frozenset({"create", "update", "patch", "delete", "deletecollection"})
KUBE_VERSION = {"major": "1", "minor": "33", "gitVersion": "v1.33.0-osmo-standin",
                "platform": "linux/amd64"}


class LogSource(Protocol):
    """Where container logs come from (the node side)."""

    def pod_logs(self, pod: Obj, container: str, *, follow: bool, tail: int | None,
                 timestamps: bool) -> Iterator[bytes]:
        """The log of ``container`` of ``pod``; ApiError 400 when it has not started."""


class ExecSource(Protocol):
    """How a command runs in a running container, and how a pod's port is reached (the
    node side of ``pods/exec`` and ``pods/portforward``)."""

    def pod_exec(self, pod: Obj, container: str, command: list[str], *,
                 tty: bool) -> subprocess.Popen[bytes]:
        """``command`` in ``container`` of ``pod`` with piped stdin, stdout, stderr.

        Raises:
            ApiError: 400 when the container does not run.
        """

    def pod_connect(self, pod: Obj, port: int) -> socket.socket:
        """A TCP connection to ``port`` where ``pod``'s processes listen.

        Raises:
            OSError: nothing listens there.
        """


class ApiServer:
    """The HTTP stand-in: start it, point a client at ``url``, stop it.

    Args:
        store: the objects (a new one by default).
        validate: a Kubernetes version (``"1.33"``): also check every created, replaced or
            patched object against that version's strict schema (422 when it fails).
    """

    def __init__(self, store: Store | None = None, *, validate: str | None = None) -> None:
        self.store = store or Store()
        self.schema = SchemaCheck(validate) if validate else None
        self.log_source: LogSource | None = None
        self.exec_source: ExecSource | None = None
        self.calls: collections.Counter[tuple[str, str]] = collections.Counter()
        self.stopping = threading.Event()
        self._http = _Server(self)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        """``http://127.0.0.1:PORT``."""
        host, port = self._http.server_address[:2]
        return f"http://{host!s}:{port}"

    @property
    def writes(self) -> collections.Counter[tuple[str, str]]:
        """The writes so far, by (verb, resource)."""
        return collections.Counter({k: n for k, n in self.calls.items() if k[0] in WRITES})

    def kubeconfig(self, path: Path, namespace: str = "default") -> Path:
        """Write a kubeconfig for this server (for processes that load one); return its path."""
        config = {"apiVersion": "v1", "kind": "Config", "current-context": "standin",
                  "clusters": [{"name": "standin", "cluster": {"server": self.url}}],
                  "users": [{"name": "standin", "user": {}}],
                  "contexts": [{"name": "standin", "context": {
                      "cluster": "standin", "user": "standin", "namespace": namespace}}]}
        path.write_text(json.dumps(config))  # JSON is YAML
        return path

    def start(self) -> ApiServer:
        """Serve in a background thread; return self."""
        self._thread = threading.Thread(target=self._http.serve_forever, name="k8s-apiserver",
                                        kwargs={"poll_interval": 0.1}, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving; end open watches and log streams; close every connection."""
        self.stopping.set()
        self.store.stop_watches()
        self._http.shutdown()
        self._http.close_all()
        self._http.server_close()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def __enter__(self) -> ApiServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ checks

    def causes(self, res: Resource, obj: Obj) -> list[Cause]:
        """Every reason to refuse ``obj`` (always-on checks, then the schema if asked)."""
        causes = check(res.kind, obj)
        if self.schema is not None:
            causes += self.schema(obj)
        return causes


def invalid(res: Resource, name: str, causes: list[Cause]) -> ApiError:
    """422 Invalid listing ``causes``, worded as the real server words it."""
    shown = ", ".join(map(str, causes))
    message = f'{res.kind} "{name}" is invalid: ' + (f"[{shown}]" if len(causes) > 1 else shown)
    details = {"name": name, "kind": res.kind,
               "causes": [{"reason": c.reason, "message": c.message, "field": c.field}
                          for c in causes]}
    if res.group:
        details["group"] = res.group
    return ApiError(422, "Invalid", message, details)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 1024  # a real API server's listen backlog is the system's maximum

    def __init__(self, api: ApiServer) -> None:
        self.api = api
        self.connections: set[socket.socket] = set()
        self.guard = threading.Lock()
        super().__init__(("127.0.0.1", 0), _Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        with self.guard:
            self.connections.add(request)
        super().process_request(request, client_address)

    def shutdown_request(self, request: Any) -> None:
        with self.guard:
            self.connections.discard(request)
        super().shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that hung up (a watch it closed, a node killed) is not an error."""
        if isinstance(sys.exc_info()[1], (ConnectionResetError, BrokenPipeError)):
            return
        super().handle_error(request, client_address)

    def close_all(self) -> None:
        with self.guard:
            for conn in list(self.connections):
                try:
                    conn.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: _Server

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        pass  # calls are counted in ApiServer.calls; nothing goes to stderr

    def do_GET(self) -> None:
        self._serve("GET")

    def do_POST(self) -> None:
        self._serve("POST")

    def do_PUT(self) -> None:
        self._serve("PUT")

    def do_PATCH(self) -> None:
        self._serve("PATCH")

    def do_DELETE(self) -> None:
        self._serve("DELETE")

    # ------------------------------------------------------------------ plumbing

    @property
    def api(self) -> ApiServer:
        return self.server.api

    def _serve(self, method: str) -> None:
        self._streaming = False
        url = urlsplit(self.path)
        self.query = {k: v[-1] for k, v in parse_qs(url.query, keep_blank_values=True).items()}
        try:
            body = self._body()
            if url.path in ("/version", "/version/"):
                return self._json(200, KUBE_VERSION)
            if url.path == "/api":
                return self._json(200, {"kind": "APIVersions", "versions": ["v1"]})
            match = _PATH.match(url.path)
            res = match and st.resource(match["group"] or "", match["version"] or "v1",
                                        match["plural"])
            if match is None or res is None or not _served(res, match["ns"], match["name"],
                                                          method):
                raise ApiError(404, "NotFound", "the server could not find the requested resource")
            route = _Route(res, match["ns"], match["name"], match["sub"])
            self._dispatch(method, route, body)
        except ApiError as exc:
            self._json(exc.code, exc.status())
        except SelectorError as exc:
            self._json(400, ApiError(400, "BadRequest", str(exc)).status())
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True
        except Exception as exc:  # noqa: BLE001 - a bug here is a 500, as on a real server
            traceback.print_exc()
            self.close_connection = True
            if not self._streaming:
                self._json(500, ApiError(500, "InternalError", repr(exc)).status())

    def _body(self) -> Any:
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length) if length else b""
        if not raw:
            return None
        try:
            return json.loads(raw)
        except ValueError as exc:
            raise ApiError(400, "BadRequest", f"the request body is not JSON: {exc}") from None

    def _json(self, code: int, body: Any) -> None:
        data = json.dumps(body).encode()
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def _start_chunks(self, content_type: str) -> None:
        self._streaming = True
        self.send_response(200)
        self.send_header("Content-Type", content_type)
        self.send_header("Transfer-Encoding", "chunked")
        self.end_headers()

    def _chunk(self, data: bytes) -> None:
        self.wfile.write(b"%x\r\n%s\r\n" % (len(data), data))
        self.wfile.flush()

    def _count(self, verb: str, route: _Route) -> None:
        name = route.res.qualified + (f"/{route.sub}" if route.sub else "")
        with self.server.guard:
            self.api.calls[(verb, name)] += 1

    # ------------------------------------------------------------------ verbs

    def _dispatch(self, method: str, route: _Route, body: Any) -> None:
        self._count(_verb(method, route.name, self.query), route)  # refused ones count too
        if route.sub not in (None, "status", "log", "exec", "portforward") or (
                route.sub == "log" and (method != "GET" or route.res != st.PODS)) or (
                route.sub in ("exec", "portforward") and (method not in ("GET", "POST")
                                                          or route.res != st.PODS)):
            raise ApiError(404, "NotFound", "the server could not find the requested resource")
        if route.sub == "exec":
            return self._exec(route)
        if route.sub == "portforward":
            return self._portforward(route)
        if method == "GET" and route.name is None:
            if self.query.get("watch") in ("true", "1"):
                return self._watch(route)
            return self._list(route)
        if method == "GET" and route.sub == "log":
            return self._logs(route)
        if method == "GET":
            return self._json(200, self.api.store.get(route.res, route.ns, route.name or ""))
        if method == "POST" and route.name is None:
            return self._create(route, body)
        if method == "DELETE":
            return self._delete(route, body) if route.name else self._delete_all(route)
        if method in ("PUT", "PATCH") and route.name:
            return self._change(method, route, body)
        raise ApiError(405, "MethodNotAllowed", f"the server does not allow this method on "
                       f"the requested resource ({method} {self.path})")

    def _selects(self, route: _Route) -> Predicate:
        labels = label_selector(self.query.get("labelSelector"))
        fields = field_selector(self.query.get("fieldSelector"), route.res.kind)
        return lambda obj: labels(obj) and fields(obj)

    def _list(self, route: _Route) -> None:
        items, rv = self.api.store.list(route.res, route.ns, self._selects(route))
        start = 0
        meta: dict[str, Any] = {"resourceVersion": str(rv)}
        if self.query.get("continue"):
            start, rv = _continued(self.query["continue"])
            meta["resourceVersion"] = str(rv)
        limit = int(self.query.get("limit") or 0)
        if limit and start + limit < len(items):
            token = json.dumps({"start": start + limit, "rv": rv}).encode()
            meta["continue"] = base64.urlsafe_b64encode(token).decode()
            meta["remainingItemCount"] = len(items) - start - limit
        shown = items[start:start + limit] if limit else items[start:]
        self._json(200, {"kind": f"{route.res.kind}List", "apiVersion": route.res.api_version,
                         "metadata": meta, "items": shown})

    def _watch(self, route: _Route) -> None:
        store = self.api.store
        timeout = float(self.query.get("timeoutSeconds") or 1800)
        deadline = time.monotonic() + timeout
        try:
            watch = store.watch(route.res, route.ns, self._selects(route),
                                self.query.get("resourceVersion"))
        except ApiError as exc:
            if exc.code != 410:
                raise
            self._start_chunks("application/json")
            self._chunk(json.dumps({"type": "ERROR", "object": exc.status()}).encode() + b"\n")
            self._chunk(b"")
            return
        self._start_chunks("application/json")
        try:
            while not self.api.stopping.is_set():
                if watch.stalled.is_set():
                    if self._client_gone():
                        return
                    continue  # held open, silent, until the client or the server goes
                if time.monotonic() >= deadline:
                    break
                try:
                    event = watch.events.get(timeout=min(0.25, deadline - time.monotonic()))
                except queue.Empty:
                    continue
                if event is None:
                    break
                line = json.dumps({"type": event.type, "object": event.obj}).encode() + b"\n"
                self._chunk(line)
            self._chunk(b"")
        finally:
            store.close_watch(watch)

    def _client_gone(self) -> bool:
        readable, _, _ = select.select([self.connection], [], [], 0.25)
        if not readable:
            return False
        try:
            return bool(self.connection.recv(1, socket.MSG_PEEK) == b"")
        except OSError:
            return True

    def _logs(self, route: _Route) -> None:
        pod = self.api.store.get(st.PODS, route.ns, route.name or "")
        container = self._log_container(pod)
        source = self.api.log_source
        if source is None:
            raise ApiError(400, "BadRequest", f'container "{container}" in pod '
                           f'"{route.name}" is waiting to start: no node runs this pod')
        tail = self.query.get("tailLines")
        limit = int(self.query.get("limitBytes") or 0)
        chunks = source.pod_logs(pod, container, follow=self.query.get("follow") == "true",
                                 tail=int(tail) if tail else None,
                                 timestamps=self.query.get("timestamps") == "true")
        first = next(chunks, b"")  # an ApiError (not started) comes before any byte is sent
        self._start_chunks("text/plain")
        sent = 0
        for chunk in _chain(first, chunks):
            if limit:
                chunk = chunk[:max(0, limit - sent)]
            if chunk:
                self._chunk(chunk)
                sent += len(chunk)
            if (limit and sent >= limit) or self.api.stopping.is_set():
                break
        self._chunk(b"")

    def _exec(self, route: _Route) -> None:
        """``pods/exec``: a WebSocket carrying Kubernetes' channel protocol (v5 or v4)."""
        pod = self.api.store.get(st.PODS, route.ns, route.name or "")
        container = self._log_container(pod)
        query = parse_qs(urlsplit(self.path).query)
        command = query.get("command") or []
        protocol = self._protocol(("v5.channel.k8s.io", "v4.channel.k8s.io"))
        if protocol is None or not command:
            raise ApiError(400, "BadRequest", "you must specify at least 1 command and a "
                           "channel protocol (v4 or v5.channel.k8s.io)")
        proc = self._node().pod_exec(pod, container, command,
                                     tty=query.get("tty", ["false"])[-1] == "true")
        _relay(self._upgrade(protocol), proc, v5=protocol.startswith("v5"))

    def _portforward(self, route: _Route) -> None:
        """``pods/portforward``: a WebSocket of ``v4.channel.k8s.io``, two channels a port.

        As the kubelet serves it: port ``i`` (in the order of ``ports``) has data channel
        ``2i`` and error channel ``2i+1``, each opened by a frame carrying the port (2 bytes,
        little-endian); the node dials the pod's port, and a dial that fails is a message
        on the error channel. The WebSocket closes once every port's connection ended (no
        half-close: the protocol has no message for it).
        """
        pod = self.api.store.get(st.PODS, route.ns, route.name or "")
        ports = _ports(parse_qs(urlsplit(self.path).query).get("ports") or [])
        protocol = self._protocol(("v4.channel.k8s.io",))
        if protocol is None:
            raise ApiError(400, "BadRequest", "port forwarding needs the v4.channel.k8s.io "
                           "WebSocket protocol")
        phase = (pod.get("status") or {}).get("phase")
        if phase != "Running":
            raise ApiError(400, "BadRequest", f"unable to forward port: pod "
                           f"{pod['metadata']['name']} is not running (phase {phase})")
        node = self._node()
        _forward(self._upgrade(protocol), ports,
                 lambda port: node.pod_connect(pod, port), pod["metadata"]["name"])

    def _protocol(self, served: tuple[str, ...]) -> str | None:
        """The first of ``served`` the client offers; 400 without a WebSocket upgrade."""
        if self.headers.get("Upgrade", "").lower() != "websocket" or \
                not self.headers.get("Sec-WebSocket-Key"):
            raise ApiError(400, "BadRequest", "Upgrade request required")
        offered = [p.strip() for p in (self.headers.get("Sec-WebSocket-Protocol") or "")
                   .split(",")]
        return next((p for p in served if p in offered), None)

    def _node(self) -> ExecSource:
        if self.api.exec_source is None:
            raise ApiError(400, "BadRequest", "no node runs this pod")
        return self.api.exec_source

    def _upgrade(self, protocol: str) -> WebSocket:
        """Switch to a WebSocket speaking ``protocol``."""
        self._streaming = True
        self.close_connection = True
        self.send_response(101, "Switching Protocols")
        self.send_header("Upgrade", "websocket")
        self.send_header("Connection", "Upgrade")
        self.send_header("Sec-WebSocket-Accept", accept_key(self.headers["Sec-WebSocket-Key"]))
        self.send_header("Sec-WebSocket-Protocol", protocol)
        self.end_headers()
        self.wfile.flush()
        return WebSocket(self.rfile, self.wfile)

    def _log_container(self, pod: Obj) -> str:
        spec = pod.get("spec") or {}
        names = [c["name"] for c in spec.get("containers") or []]
        inits = [c["name"] for c in spec.get("initContainers") or []]
        name = self.query.get("container")
        if not name:
            if len(names) == 1:
                return str(names[0])
            raise ApiError(400, "BadRequest", "a container name must be specified for pod "
                           f"{pod['metadata']['name']}, choose one of: [{' '.join(names)}] or "
                           f"one of the init containers: [{' '.join(inits)}]")
        if name not in names + inits:
            raise ApiError(400, "BadRequest", f"container {name} is not valid for pod "
                           f"{pod['metadata']['name']}")
        return name

    def _create(self, route: _Route, body: Any) -> None:
        res = route.res
        obj = self._admit(route, body)
        name = obj["metadata"].get("name") or obj["metadata"].get("generateName") or ""
        causes = self.api.causes(res, obj) if obj["metadata"].get("name") else [
            c for c in self.api.causes(res, _named(obj)) if c.field != "metadata.name"]
        if causes:
            raise invalid(res, name, causes)
        if self.query.get("dryRun") == "All":
            return self._json(201, obj)
        self._json(201, self.api.store.create(res, route.ns, obj))

    def _admit(self, route: _Route, body: Any) -> Obj:
        """The body checked against the route, decoded, and given the server's defaults."""
        res = route.res
        if not isinstance(body, dict):
            raise ApiError(400, "BadRequest", f"the body of a {res.kind} must be a JSON object")
        if body.get("apiVersion", res.api_version) != res.api_version or body.get(
                "kind", res.kind) != res.kind:
            raise ApiError(400, "BadRequest",
                           f"the API version in the data ({body.get('apiVersion')}) or kind "
                           f"({body.get('kind')}) does not match the expected "
                           f"{res.api_version} {res.kind}")
        meta = body.setdefault("metadata", {})
        if not isinstance(meta, dict):
            raise ApiError(400, "BadRequest", "metadata must be a JSON object")
        if meta.get("namespace") not in (None, route.ns) and res.namespaced:
            raise ApiError(400, "BadRequest", "the namespace of the provided object does not "
                           "match the namespace sent on the request")
        body.update(apiVersion=res.api_version, kind=res.kind)
        _defaults(res, body, self.api.store.resource_version)
        return body

    def _change(self, method: str, route: _Route, body: Any) -> None:
        res, store = route.res, self.api.store
        current = store.get(res, route.ns, route.name or "")
        if method == "PATCH":
            changed = apply_patch(current, body, self.headers.get("Content-Type") or "")
        else:
            changed = self._admit(route, body)
            wanted = changed["metadata"].get("resourceVersion")
            if wanted and wanted != current["metadata"]["resourceVersion"]:
                raise ApiError(409, "Conflict", f'Operation cannot be fulfilled on '
                               f'{res.qualified} "{route.name}": the object has been modified; '
                               "please apply your changes to the latest version and try again",
                               {"name": route.name, "kind": res.plural})
        _keep_identity(current, changed)
        if res == st.PODS:
            _pod_change(current, changed, status_only=route.sub == "status")
        causes = self.api.causes(res, changed)
        if causes:
            raise invalid(res, route.name or "", causes)
        if self.query.get("dryRun") == "All":
            return self._json(200, changed)

        def replace(obj: Obj) -> None:
            obj.clear()
            obj.update(changed)
        self._json(200, store.update(res, route.ns, route.name or "", replace))

    def _delete(self, route: _Route, body: Any) -> None:
        options = body if isinstance(body, dict) else {}
        grace = self.query.get("gracePeriodSeconds", options.get("gracePeriodSeconds"))
        policy = self.query.get("propagationPolicy", options.get("propagationPolicy"))
        store, name = self.api.store, route.name or ""
        current = store.get(route.res, route.ns, name)
        pre = options.get("preconditions") or {}
        for key in ("uid", "resourceVersion"):
            if pre.get(key) and pre[key] != current["metadata"][key]:
                raise ApiError(409, "Conflict", f"Precondition failed: {key}: {pre[key]}, "
                               f"{key} in object meta: {current['metadata'][key]}")
        if self.query.get("dryRun") == "All":
            return self._json(200, current)
        obj, _ = store.delete(route.res, route.ns, name,
                              grace=int(grace) if grace is not None else None,
                              propagation=policy or "Background")
        if route.res == st.PODS:
            return self._json(200, obj)
        self._json(200, {"kind": "Status", "apiVersion": "v1", "metadata": {},
                         "status": "Success",
                         "details": {**st.details(route.res, name),
                                     "uid": obj["metadata"]["uid"]}})

    def _delete_all(self, route: _Route) -> None:
        store = self.api.store
        items, _ = store.list(route.res, route.ns, self._selects(route))
        grace = self.query.get("gracePeriodSeconds")
        gone = []
        for obj in items:
            try:
                last, _ = store.delete(route.res, route.ns, obj["metadata"]["name"],
                                       grace=int(grace) if grace is not None else None,
                                       propagation=self.query.get("propagationPolicy")
                                       or "Background")
                gone.append(last)
            except ApiError:
                continue  # went meanwhile (garbage-collected with its owner)
        self._json(200, {"kind": f"{route.res.kind}List", "apiVersion": route.res.api_version,
                         "metadata": {"resourceVersion": str(store.resource_version)},
                         "items": gone})


class _Route:
    def __init__(self, res: Resource, ns: str | None, name: str | None, sub: str | None) -> None:
        self.res, self.ns, self.name, self.sub = res, ns, name, sub


def _relay(ws: WebSocket, proc: subprocess.Popen[bytes], *, v5: bool) -> None:
    """Carry an exec's streams over ``ws`` until the process ends; then its Status."""
    assert proc.stdin is not None and proc.stdout is not None and proc.stderr is not None

    def pump(pipe: Any, channel: int) -> None:
        while data := os.read(pipe.fileno(), 65536):
            ws.send(bytes([channel]) + data)

    def feed() -> None:
        try:
            _feed()
        except OSError:
            pass  # the client went away
        if proc.poll() is None:
            proc.kill()

    def _feed() -> None:
        while (message := ws.receive()) is not None:
            opcode, data = message
            if opcode == CLOSE:
                break
            if data[:1] == b"\0" and proc.stdin is not None:
                try:
                    proc.stdin.write(data[1:])
                    proc.stdin.flush()
                except OSError:
                    pass
            elif v5 and data[:2] == b"\xff\0" and proc.stdin is not None:
                proc.stdin.close()  # the client closed stdin

    pumps = [threading.Thread(target=pump, args=(proc.stdout, 1), daemon=True),
             threading.Thread(target=pump, args=(proc.stderr, 2), daemon=True)]
    for thread in pumps:
        thread.start()
    threading.Thread(target=feed, daemon=True).start()
    for thread in pumps:
        thread.join()
    code = proc.wait()
    for pipe in (proc.stdin, proc.stdout, proc.stderr):
        try:
            pipe.close()
        except OSError:
            pass
    status: dict[str, Any] = {"metadata": {}, "status": "Success"}
    if code != 0:
        status = {"metadata": {}, "status": "Failure", "reason": "NonZeroExitCode",
                  "message": f"command terminated with non-zero exit code: {code}",
                  "details": {"causes": [{"reason": "ExitCode", "message": str(code)}]}}
    try:
        ws.send(bytes([3]) + json.dumps(status).encode())
        ws.send(struct.pack("!H", 1000), CLOSE)
    except OSError:
        pass


def _ports(values: list[str]) -> list[int]:
    """The ``ports`` of a port-forward request; 400 when one is not a port."""
    ports: list[int] = []
    for value in values:
        for text in value.split(","):
            if not text.strip().isdigit() or not 0 < int(text) < 65536 or int(text) in ports:
                raise ApiError(400, "BadRequest", f"invalid port {text!r}")
            ports.append(int(text))
    if not ports:
        raise ApiError(400, "BadRequest", "at least 1 port is required (ports=N)")
    return ports


def _forward(ws: WebSocket, ports: list[int], dial: Callable[[int], socket.socket],
             pod: str) -> None:
    """Carry each port's bytes over ``ws`` (see ``_Handler._portforward``) until all ended."""
    conns: dict[int, socket.socket] = {}
    for index, port in enumerate(ports):
        prefix = struct.pack("<H", port)
        ws.send(bytes([2 * index]) + prefix)
        ws.send(bytes([2 * index + 1]) + prefix)
        try:
            conns[index] = dial(port)
        except OSError as exc:
            ws.send(bytes([2 * index + 1]) + f"error forwarding port {port} to pod {pod}: "
                    f"dial tcp4 127.0.0.1:{port}: {exc.strerror or exc}".encode())

    def pump(index: int, conn: socket.socket) -> None:
        try:
            while data := conn.recv(65536):
                ws.send(bytes([2 * index]) + data)
        except OSError:
            pass  # the client went away (its side closed the connection)

    def feed() -> None:
        try:
            while (message := ws.receive()) is not None and message[0] != CLOSE:
                conn = conns.get(message[1][0] // 2) if message[1] else None
                if conn is not None and message[1][0] % 2 == 0:
                    conn.sendall(message[1][1:])
        except OSError:
            pass
        for conn in conns.values():  # the client is gone: so are its connections
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    pumps = [threading.Thread(target=pump, args=item, daemon=True) for item in conns.items()]
    for thread in pumps:
        thread.start()
    threading.Thread(target=feed, daemon=True).start()
    for thread in pumps:
        thread.join()
    for conn in conns.values():
        conn.close()
    try:
        ws.send(struct.pack("!H", 1000), CLOSE)
    except OSError:
        pass


def _verb(method: str, name: str | None, query: dict[str, str]) -> str:
    """The API verb of a request, as audit logs name it."""
    if method == "GET":
        return "get" if name else ("watch" if query.get("watch") in ("true", "1") else "list")
    if method == "DELETE":
        return "delete" if name else "deletecollection"
    return {"POST": "create", "PUT": "update", "PATCH": "patch"}.get(method, method.lower())


def _served(res: Resource, ns: str | None, name: str | None, method: str) -> bool:
    """Whether the path's shape fits ``res``: namespaced objects live in a namespace (listed
    or watched across all of them too); cluster-scoped ones never do."""
    if not res.namespaced:
        return ns is None
    return ns is not None or (name is None and method == "GET")


def _continued(token: str) -> tuple[int, int]:
    try:
        data = json.loads(base64.urlsafe_b64decode(token.encode()))
        return int(data["start"]), int(data["rv"])
    except (ValueError, KeyError, TypeError):
        raise ApiError(400, "BadRequest", "continue key is not valid") from None


def _chain(first: bytes, rest: Iterator[bytes]) -> Iterator[bytes]:
    yield first
    yield from rest


def _named(obj: Obj) -> Obj:
    """``obj`` with a placeholder name (generateName: the name is not chosen yet)."""
    out = dict(obj)
    out["metadata"] = {**obj["metadata"], "name": "x"}
    return out


def _defaults(res: Resource, obj: Obj, serial: int) -> None:
    """The defaults the real server fills in (the ones a client reads back); ``serial``
    numbers a Service's cluster IP."""
    if res == st.SECRETS:
        try:
            data = decode_secret_data(obj.get("data") or {})
        except ValueError as exc:
            raise ApiError(400, "BadRequest", f'Secret in version "v1" cannot be handled as a '
                           f"Secret: {exc}") from None
        for key, value in (obj.pop("stringData", None) or {}).items():
            data[key] = str(value).encode()
        obj["data"] = {k: base64.b64encode(v).decode() for k, v in data.items()}
        obj.setdefault("type", "Opaque")
    elif res == st.SERVICES:
        spec = obj.setdefault("spec", {})
        spec.setdefault("type", "ClusterIP")
        if spec.get("clusterIP") is None:
            spec["clusterIP"] = f"10.96.{serial // 250 % 250}.{serial % 250 + 1}"
    elif res == st.PODS:
        spec = obj.setdefault("spec", {})
        spec.setdefault("restartPolicy", "Always")
        spec.setdefault("terminationGracePeriodSeconds", 30)
        spec.setdefault("schedulerName", "default-scheduler")
        spec.setdefault("dnsPolicy", "ClusterFirst")
        for container in (spec.get("initContainers") or []) + (spec.get("containers") or []):
            if isinstance(container, dict):
                image = str(container.get("image") or "")
                latest = ":" not in image.rsplit("/", 1)[-1] or image.endswith(":latest")
                container.setdefault("imagePullPolicy",
                                     "Always" if latest and "@" not in image else "IfNotPresent")
        obj["status"] = {"phase": "Pending", "qosClass": _qos(spec)}


def _qos(spec: Obj) -> str:
    containers = [c for c in spec.get("containers") or [] if isinstance(c, dict)]
    resources = [c.get("resources") or {} for c in containers]
    if not any(r.get("requests") or r.get("limits") for r in resources):
        return "BestEffort"
    guaranteed = all(
        r.get("limits", {}).get(k) and r.get("requests", {}).get(k, r["limits"][k])
        == r["limits"][k] for r in resources for k in ("cpu", "memory"))
    return "Guaranteed" if guaranteed else "Burstable"


def _keep_identity(current: Obj, changed: Obj) -> None:
    """What an update may not change: name, namespace, uid, creation time."""
    meta, was = changed.setdefault("metadata", {}), current["metadata"]
    for key in ("name", "namespace", "uid", "creationTimestamp", "deletionTimestamp",
                "deletionGracePeriodSeconds"):
        if key in was:
            meta[key] = was[key]
    meta["resourceVersion"] = was["resourceVersion"]
    changed.update(apiVersion=current["apiVersion"], kind=current["kind"])


def _pod_change(current: Obj, changed: Obj, status_only: bool) -> None:
    """A pod's status changes only through pods/status; its spec hardly ever changes."""
    if status_only:
        changed["spec"], changed["metadata"] = current["spec"], current["metadata"]
        return
    changed["status"] = current.get("status", {})
    if _without_images(changed.get("spec")) != _without_images(current["spec"]):
        raise invalid(st.PODS, current["metadata"]["name"], [Cause(
            "spec", "FieldValueForbidden", "Forbidden: pod updates may not change fields "
            "other than `spec.containers[*].image`, `spec.initContainers[*].image`, "
            "`spec.activeDeadlineSeconds`, `spec.tolerations` (only additions to existing "
            "tolerations) or `spec.terminationGracePeriodSeconds`")])


def _without_images(spec: Any) -> Any:
    if not isinstance(spec, dict):
        return spec
    out = {k: v for k, v in spec.items()
           if k not in ("activeDeadlineSeconds", "tolerations", "terminationGracePeriodSeconds")}
    for group in ("initContainers", "containers"):
        if isinstance(out.get(group), list):
            out[group] = [{k: v for k, v in c.items() if k != "image"} if isinstance(c, dict)
                          else c for c in out[group]]
    return out
