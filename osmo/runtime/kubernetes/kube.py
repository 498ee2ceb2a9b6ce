"""The only module that imports the ``kubernetes`` client; its errors become :class:`KubeError`.

:class:`Kube` is what osmo asks of an API server: create, read, list, watch and delete pods,
Secrets, Services and PodGroups of one namespace (or every one a label selects), stream a
container's log, run a command in a container (:class:`ExecSession`: the exec API's
WebSocket), connect to a pod's port (:meth:`Kube.port_forward`: the port-forward API's
WebSocket), list nodes.
Objects go and come as plain dicts (JSON as the API serves it; responses are not turned into
the client's models, which is slower and loses fields the models do not know).

Connection: a kubeconfig file (``KubePool.kubeconfig``), else the in-cluster ServiceAccount
when ``KUBERNETES_SERVICE_HOST`` is set, else ``~/.kube/config``.

The client is an extra (``pip install "osmo[kubernetes]"``): without it, :func:`connect`
raises a :class:`KubeError` naming that command.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import socket
from collections.abc import Iterator
from typing import Any

from osmo.errors import OsmoError

__all__ = ["ExecSession", "Gone", "Kube", "KubeError", "connect"]

Obj = dict[str, Any]
_REQUEST_TIMEOUT = 30.0  # seconds for one ordinary call (watches and logs have none)
_POOL_SIZE = 128  # connections kept to the API server (one per followed log, and calls)


class KubeError(OsmoError):
    """The API server refused a call or could not be reached (``status``: its HTTP code)."""

    exit_code = 3

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class Gone(KubeError):
    """A watch's resourceVersion is too old (410 Gone): list again."""


def connect(kubeconfig: str | None = None, context: str | None = None) -> Kube:
    """A :class:`Kube` for the cluster the configuration names (see the module docstring).

    Raises:
        KubeError: the client is not installed or the configuration cannot be loaded.
    """
    try:
        client, config = _module("kubernetes.client"), _module("kubernetes.config")
    except ImportError:
        raise KubeError('the Kubernetes runtime needs the kubernetes client: '
                        'pip install "osmo[kubernetes]"') from None
    configuration = client.Configuration()
    try:
        if kubeconfig is None and os.environ.get("KUBERNETES_SERVICE_HOST"):
            config.load_incluster_config(client_configuration=configuration)
        else:
            config.load_kube_config(config_file=kubeconfig, context=context,
                                    client_configuration=configuration)
    except Exception as exc:  # noqa: BLE001 - the client raises several kinds
        raise KubeError(f"cannot load the Kubernetes configuration "
                        f"{kubeconfig or '(default)'}: {exc}") from None
    # a node holds a log stream per running pod beside its calls: a pool of the client's
    # default size (5 per core) would open and drop a connection per call beyond it
    configuration.connection_pool_maxsize = max(configuration.connection_pool_maxsize or 0,
                                                _POOL_SIZE)
    return Kube(client.ApiClient(configuration))


class Kube:
    """Calls to one API server (thread-safe: the client's pool is)."""

    def __init__(self, api: Any) -> None:
        client = _module("kubernetes.client")
        self.api = api
        self.core = client.CoreV1Api(api)
        self.custom = client.CustomObjectsApi(api)

    def close(self) -> None:
        """Let go of the connections."""
        self.api.close()

    # ------------------------------------------------------------ objects

    def create(self, kind: str, namespace: str, body: Obj) -> Obj:
        """Create a ``pod``, ``secret`` or ``service``; the object as stored."""
        call = {"pod": self.core.create_namespaced_pod,
                "secret": self.core.create_namespaced_secret,
                "service": self.core.create_namespaced_service}[kind]
        return _json(self._call(call, namespace, body, _preload_content=False,
                                _request_timeout=_REQUEST_TIMEOUT))

    def create_custom(self, kind: tuple[str, str, str], namespace: str, body: Obj) -> Obj:
        """Create a custom object (``kind``: group, version, plural): a PodGroup."""
        group, version, plural = kind
        return _json(self._call(self.custom.create_namespaced_custom_object, group, version,
                                namespace, plural, body, _preload_content=False,
                                _request_timeout=_REQUEST_TIMEOUT))

    def delete(self, kind: str, namespace: str, name: str, *, grace: int | None = None
               ) -> bool:
        """Delete a ``pod``, ``secret`` or ``service`` (``grace`` seconds); False: not there."""
        call = {"pod": self.core.delete_namespaced_pod,
                "secret": self.core.delete_namespaced_secret,
                "service": self.core.delete_namespaced_service}[kind]
        extra = {} if grace is None else {"grace_period_seconds": grace}
        try:
            self._call(call, name, namespace, _preload_content=False,
                       _request_timeout=_REQUEST_TIMEOUT, **extra)
        except KubeError as exc:
            if exc.status == 404:
                return False
            raise
        return True

    def delete_custom(self, kind: tuple[str, str, str], namespace: str, name: str) -> bool:
        """Delete a custom object; False: it was not there."""
        group, version, plural = kind
        try:
            self._call(self.custom.delete_namespaced_custom_object, group, version, namespace,
                       plural, name, _preload_content=False, _request_timeout=_REQUEST_TIMEOUT)
        except KubeError as exc:
            if exc.status == 404:
                return False
            raise
        return True

    def delete_labelled(self, kind: str | tuple[str, str, str], namespace: str, labels: str
                        ) -> list[str]:
        """Delete every ``secret``/``service``/``pod`` (or custom ``kind``) ``labels`` selects.

        One ``deletecollection`` call: the caller needs that verb, not ``list``. The API
        answers with the deleted objects; only their names are kept (returned).
        """
        if isinstance(kind, tuple):
            group, version, plural = kind
            call: Any = self.custom.delete_collection_namespaced_custom_object
            args: tuple[Any, ...] = (group, version, namespace, plural)
        else:
            call = {"pod": self.core.delete_collection_namespaced_pod,
                    "secret": self.core.delete_collection_namespaced_secret,
                    "service": self.core.delete_collection_namespaced_service}[kind]
            args = (namespace,)
        found = _json(self._call(call, *args, label_selector=labels, _preload_content=False,
                                 _request_timeout=_REQUEST_TIMEOUT))
        return [str((item.get("metadata") or {}).get("name"))
                for item in found.get("items") or []]

    def read_pod(self, namespace: str, name: str) -> Obj | None:
        """The pod (None: there is none)."""
        try:
            return _json(self._call(self.core.read_namespaced_pod, name, namespace,
                                    _preload_content=False,
                                    _request_timeout=_REQUEST_TIMEOUT))
        except KubeError as exc:
            if exc.status == 404:
                return None
            raise

    def list_objects(self, kind: str, namespace: str, labels: str = "", fields: str = ""
             ) -> tuple[list[Obj], str]:
        """``(objects, resourceVersion)`` of the ``pod``/``secret``/``service`` list."""
        call = {"pod": self.core.list_namespaced_pod,
                "secret": self.core.list_namespaced_secret,
                "service": self.core.list_namespaced_service}[kind]
        found = _json(self._call(call, namespace, label_selector=labels, field_selector=fields,
                                 _preload_content=False, _request_timeout=_REQUEST_TIMEOUT))
        return list(found.get("items") or []), str(
            (found.get("metadata") or {}).get("resourceVersion", ""))

    def nodes(self, labels: str = "") -> list[Obj]:
        """The cluster's nodes (``labels``: a selector)."""
        found = _json(self._call(self.core.list_node, label_selector=labels,
                                 _preload_content=False, _request_timeout=_REQUEST_TIMEOUT))
        return list(found.get("items") or [])

    # ------------------------------------------------------------ streams

    def watch_pods(self, namespace: str, *, version: str, fields: str = "",
                   labels: str = "", timeout: int = 60) -> Iterator[tuple[str, Obj]]:
        """``(type, pod)`` events after ``version``, for at most ``timeout`` seconds.

        A watch that stays silent longer than that (a stalled connection) or whose
        connection breaks just ends: the caller lists again.

        Raises:
            Gone: ``version`` is too old (list again).
            KubeError: the watch failed.
        """
        api_exception = _module("kubernetes.client.exceptions").ApiException
        stream = _module("kubernetes.watch").Watch()
        try:
            for event in stream.stream(self.core.list_namespaced_pod, namespace,
                                       resource_version=version, field_selector=fields,
                                       label_selector=labels, timeout_seconds=timeout,
                                       allow_watch_bookmarks=False,
                                       _request_timeout=timeout + 2):
                kind, raw = event["type"], event["raw_object"]
                if kind == "ERROR":
                    code = int(raw.get("code") or 500)
                    raise (Gone if code == 410 else KubeError)(str(raw.get("message")), code)
                yield kind, raw
        except api_exception as exc:
            raise (Gone if exc.status == 410 else KubeError)(_message(exc), exc.status) from None
        except _transport_errors():
            return  # silent too long, or broken: the caller lists again
        finally:
            stream.stop()

    def logs(self, namespace: str, name: str, container: str, *, follow: bool = True
             ) -> Iterator[bytes]:
        """The container's log, as it comes (``follow``: until it ends)."""
        response = self._call(self.core.read_namespaced_pod_log, name, namespace,
                              container=container, follow=follow, _preload_content=False)
        try:
            yield from response.stream(64 * 1024, decode_content=True)
        except _transport_errors() as exc:
            raise KubeError(f"the log of pod {name} broke off: {exc}") from None
        finally:
            response.release_conn()

    def exec(self, namespace: str, name: str, container: str, command: list[str], *,
             tty: bool) -> ExecSession:
        """Run ``command`` in the container through the API's exec (a WebSocket).

        Raises:
            KubeError: the API refused it (the container does not run, no permission).
        """
        stream = _module("kubernetes.stream").stream
        ws = self._call(stream, self.core.connect_get_namespaced_pod_exec, name, namespace,
                        container=container, command=command, stdin=True, stdout=True,
                        stderr=True, tty=tty, _preload_content=False, binary=True)
        return ExecSession(ws)

    def port_forward(self, namespace: str, name: str, port: int) -> socket.socket:
        """A TCP connection to ``port`` of the pod, through the API's port-forward.

        Each connection is a WebSocket of its own (``v4.channel.k8s.io``: a data and an
        error channel for the port), relayed to the returned socket by the client's thread.
        The protocol has no half-close: a ``shutdown(SHUT_WR)`` of the returned socket does
        nothing (the pod's answer still comes back), and the connection ends when either
        side closes it. A port nothing listens on gives a connection that ends at once.

        Raises:
            KubeError: the API refused it (the pod does not run, no permission).
        """
        forward = self._call(_module("kubernetes.stream").portforward,
                             self.core.connect_get_namespaced_pod_portforward, name, namespace,
                             ports=str(port))
        made = forward.socket(port)  # the client's wrapper of its socketpair's end
        try:
            return _Forwarded(fileno=os.dup(made.fileno()))
        finally:
            made.close()

    # ------------------------------------------------------------ errors

    @staticmethod
    def _call(call: Any, *args: Any, **kwargs: Any) -> Any:
        api_exception = _module("kubernetes.client.exceptions").ApiException
        try:
            return call(*args, **kwargs)
        except api_exception as exc:
            raise KubeError(_message(exc), exc.status) from None
        except _transport_errors() as exc:
            raise KubeError(f"the Kubernetes API cannot be reached: {exc}") from None


class ExecSession:
    """One exec's streams (the client's WebSocket of Kubernetes' channel protocol)."""

    def __init__(self, ws: Any) -> None:
        self._ws = ws

    @property
    def open(self) -> bool:
        """Whether the command still runs (or its output is still coming)."""
        return bool(self._ws.is_open())

    def send(self, data: bytes) -> None:
        """To the command's stdin."""
        self._ws.write_stdin(data)

    def close_stdin(self) -> None:
        """The command's stdin ends (the v5 protocol; nothing under v4)."""
        self._ws.close_channel(0)

    def receive(self, timeout: float) -> tuple[bytes, bytes]:
        """``(stdout, stderr)`` that came within ``timeout`` seconds."""
        try:
            self._ws.update(timeout=timeout)
        except _transport_errors() + (Exception,):  # the websocket library's own errors
            return b"", b""
        return self._ws.read_stdout(timeout=0) or b"", self._ws.read_stderr(timeout=0) or b""

    def exit_code(self) -> int:
        """The command's exit code, once it ended."""
        code = self._ws.returncode
        return 0 if code is None else int(code)

    def close(self) -> None:
        """Let go of the connection.

        ``close()`` of the client's WebSocket leaves the socket open when the server closed
        the connection first (it only says goodbye to a connected peer); ``shutdown()``
        closes the socket itself.
        """
        self._ws.close()
        if self._ws.sock is not None:
            self._ws.sock.shutdown()


def _module(name: str) -> Any:
    """A module of the client (untyped: it ships no annotations mypy can use)."""
    return importlib.import_module(name)


def _transport_errors() -> tuple[type[BaseException], ...]:
    """What the client's HTTP layer (urllib3) raises when a connection fails."""
    import urllib3

    return (OSError, urllib3.exceptions.HTTPError)


def _json(response: Any) -> Obj:
    data = response.data
    found = json.loads(data) if data else {}
    return found if isinstance(found, dict) else {}


def _message(exc: Any) -> str:
    """The API's own message from a Status body, else the HTTP reason.

    A refused WebSocket upgrade (exec, port-forward) comes as status 0 with the handshake's
    status, headers and body in the reason: ``Handshake status 400 Bad Request -+-+- {...}
    -+-+- BODY``; its Status is read from there.
    """
    raw, status, reason = exc.body, exc.status, str(exc.reason)
    handshake = re.match(r"Handshake status (\d+)", reason)
    if not raw and handshake:
        status, raw = int(handshake[1]), reason.rsplit(" -+-+- ", 1)[-1]
    try:
        body = json.loads(raw or "{}")
    except ValueError:
        body = {}
    message = body.get("message") if isinstance(body, dict) else None
    return f"Kubernetes API: {message or reason} ({status})"


class _Forwarded(socket.socket):
    """A port-forward's socket, whose write half cannot be shut down alone.

    The API's protocol carries no half-close (see :meth:`Kube.port_forward`).
    """

    def shutdown(self, how: int) -> None:
        """Shut down reading, or both halves; writing alone stays open."""
        if how != socket.SHUT_WR:
            super().shutdown(how)
