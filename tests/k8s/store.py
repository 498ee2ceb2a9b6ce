"""The stand-in's objects: what etcd and the API server's registry hold, without HTTP.

- **Resources** — :data:`RESOURCES`: core/v1 pods, secrets, services, nodes (cluster-scoped),
  and the three PodGroup kinds (KAI ``scheduling.run.ai/v2alpha2``, Volcano
  ``scheduling.volcano.sh/v1beta1``, coscheduling ``scheduling.x-k8s.io/v1alpha1``).
- **Versions and watches** — one ``resourceVersion`` counter for everything, as etcd's
  revision. Every change is an :class:`Event` kept in a bounded history; a :class:`Watch`
  replays the history after the version it asks for, then follows live changes. A version
  older than the history raises :class:`ApiError` 410 Expired (``compact()`` forgets it all,
  as etcd's compaction does). ``stall_watches()`` silences the watches open at that moment:
  they deliver nothing more and stay open.
- **Deletion** — Pods bound to a node are deleted gracefully: ``deletionTimestamp`` is set
  and the node side (``kubelet.py``) calls :meth:`Store.remove` once the pod has stopped.
  An unbound or finished pod, a grace of 0 and every other kind go at once.
- **Garbage collection** — when an object goes, its dependents (``ownerReferences`` naming
  its uid) lose that reference; one left with no owner is deleted too (``Background``,
  ``Foreground``), or keeps living without it (``Orphan``). An object created with owners
  that do not exist is collected at once, as the real collector does.

Listeners (the kubelet) are called with every event, under the store's lock: they must only
queue work. Errors are :class:`ApiError` carrying the HTTP code and the Status body's fields.
"""

from __future__ import annotations

import collections
import copy
import itertools
import queue
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from tests.k8s.selectors import Predicate

__all__ = ["ApiError", "Event", "RESOURCES", "Resource", "Store", "Watch", "details", "now",
           "resource"]

Obj = dict[str, Any]


def now() -> str:
    """The current time as the API writes it (RFC 3339, seconds, UTC)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass(frozen=True)
class Resource:
    """One REST resource: where it lives (group, version, plural) and what it holds (kind)."""

    group: str
    version: str
    plural: str
    kind: str
    namespaced: bool = True

    @property
    def api_version(self) -> str:
        """``v1`` for the core group, ``group/version`` otherwise."""
        return f"{self.group}/{self.version}" if self.group else self.version

    @property
    def qualified(self) -> str:
        """The name errors use: ``pods``, ``podgroups.scheduling.run.ai``."""
        return f"{self.plural}.{self.group}" if self.group else self.plural


PODS = Resource("", "v1", "pods", "Pod")
SECRETS = Resource("", "v1", "secrets", "Secret")
SERVICES = Resource("", "v1", "services", "Service")
NODES = Resource("", "v1", "nodes", "Node", namespaced=False)
KAI = Resource("scheduling.run.ai", "v2alpha2", "podgroups", "PodGroup")
VOLCANO = Resource("scheduling.volcano.sh", "v1beta1", "podgroups", "PodGroup")
COSCHEDULING = Resource("scheduling.x-k8s.io", "v1alpha1", "podgroups", "PodGroup")
RESOURCES = (PODS, SECRETS, SERVICES, NODES, KAI, VOLCANO, COSCHEDULING)


def resource(group: str, version: str, plural: str) -> Resource | None:
    """The resource served at ``group/version/plural`` (None: not served)."""
    return next((r for r in RESOURCES
                 if (r.group, r.version, r.plural) == (group, version, plural)), None)


class ApiError(Exception):
    """A request the server refuses: HTTP ``code``, Status ``reason`` and ``message``."""

    def __init__(self, code: int, reason: str, message: str,
                 details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.code, self.reason, self.message = code, reason, message
        self.details = details or {}

    def status(self) -> Obj:
        """The Status body the real server sends."""
        body: Obj = {"kind": "Status", "apiVersion": "v1", "metadata": {},
                     "status": "Failure", "message": self.message, "reason": self.reason,
                     "code": self.code}
        if self.details:
            body["details"] = self.details
        return body

    @classmethod
    def not_found(cls, res: Resource, name: str) -> ApiError:
        """404 NotFound for ``name``."""
        return cls(404, "NotFound", f'{res.qualified} "{name}" not found',
                   details(res, name))

    @classmethod
    def expired(cls, asked: int, oldest: int) -> ApiError:
        """410 Expired: a watch from a version the history no longer holds."""
        return cls(410, "Expired", f"too old resource version: {asked} ({oldest})")


def details(res: Resource, name: str) -> dict[str, Any]:
    """A Status body's ``details`` naming one object of ``res``."""
    details = {"name": name, "kind": res.plural}
    if res.group:
        details["group"] = res.group
    return details


@dataclass(frozen=True)
class Event:
    """One change: its version, resource, namespace, type (ADDED/MODIFIED/DELETED), object."""

    rv: int
    res: Resource
    namespace: str | None
    type: str
    obj: Obj


@dataclass
class Watch:
    """A watcher's queue of events (None: the server stops it) and what it selects."""

    res: Resource
    namespace: str | None
    selects: Predicate
    events: queue.Queue[Event | None] = field(default_factory=queue.Queue)
    stalled: threading.Event = field(default_factory=threading.Event)

    def matches(self, event: Event) -> bool:
        """Whether ``event`` is one this watch delivers."""
        return (event.res == self.res and self.namespace in (None, event.namespace)
                and self.selects(event.obj))


Key = tuple[Resource, str | None, str]
Listener = Callable[[Event], None]


class Store:
    """Objects by (resource, namespace, name), with versions, history, watches and GC.

    Args:
        history: how many events watches can be resumed over (older versions get 410).
    """

    def __init__(self, history: int = 10_000) -> None:
        self.lock = threading.RLock()
        self._objects: dict[Key, Obj] = {}
        self._propagation: dict[Key, str] = {}  # of pods deleted gracefully, until they go
        self._rv = 0
        self._history: collections.deque[Event] = collections.deque(maxlen=history)
        self._forgotten = 0  # the newest version no longer in the history
        self._watches: list[Watch] = []
        self._listeners: list[Listener] = []
        self._names = itertools.count()

    # ------------------------------------------------------------------ reading

    @property
    def resource_version(self) -> int:
        """The newest version."""
        return self._rv

    def get(self, res: Resource, namespace: str | None, name: str) -> Obj:
        """A copy of one object; ApiError 404 when absent."""
        with self.lock:
            obj = self._objects.get((res, namespace, name))
            if obj is None:
                raise ApiError.not_found(res, name)
            return copy.deepcopy(obj)

    def find(self, res: Resource, namespace: str | None, name: str) -> Obj | None:
        """A copy of one object, or None."""
        with self.lock:
            obj = self._objects.get((res, namespace, name))
            return copy.deepcopy(obj) if obj is not None else None

    def list(self, res: Resource, namespace: str | None = None,
             selects: Predicate = lambda obj: True) -> tuple[list[Obj], int]:
        """Copies of the objects of ``res`` (in ``namespace``; None: all) ``selects`` accepts,
        in creation order, and the version they are current at."""
        with self.lock:
            items = [copy.deepcopy(obj) for (r, ns, _), obj in self._objects.items()
                     if r == res and namespace in (None, ns) and selects(obj)]
            return items, self._rv

    # ------------------------------------------------------------------ writing

    def create(self, res: Resource, namespace: str | None, body: Obj) -> Obj:
        """Store a new object (metadata filled in) and return a copy; 409 when it exists."""
        obj = copy.deepcopy(body)
        meta = obj.setdefault("metadata", {})
        with self.lock:
            if not meta.get("name") and meta.get("generateName"):
                meta["name"] = f"{meta['generateName']}{next(self._names):05x}"[-253:]
            key = (res, namespace if res.namespaced else None, meta["name"])
            if key in self._objects:
                raise ApiError(409, "AlreadyExists",
                               f'{res.qualified} "{meta["name"]}" already exists',
                               details(res, meta["name"]))
            if res.namespaced:
                meta["namespace"] = namespace
            meta.update(uid=str(uuid.uuid4()), creationTimestamp=now())
            obj.update(apiVersion=res.api_version, kind=res.kind)
            self._objects[key] = obj
            self._emit(res, key[1], "ADDED", obj)
            created = copy.deepcopy(obj)
            if meta.get("ownerReferences") and not any(
                    self._by_uid(ref.get("uid")) for ref in meta["ownerReferences"]):
                self._remove(key, "Background")
            return created

    def update(self, res: Resource, namespace: str | None, name: str,
               change: Callable[[Obj], None]) -> Obj:
        """Apply ``change`` to the object in place; publish MODIFIED if it changed anything."""
        with self.lock:
            obj = self._objects.get((res, namespace, name))
            if obj is None:
                raise ApiError.not_found(res, name)
            before = copy.deepcopy(obj)
            change(obj)
            obj["metadata"]["resourceVersion"] = before["metadata"]["resourceVersion"]
            if obj != before:
                self._emit(res, namespace, "MODIFIED", obj)
            return copy.deepcopy(obj)

    def delete(self, res: Resource, namespace: str | None, name: str,
               grace: int | None = None, propagation: str = "Background") -> tuple[Obj, bool]:
        """Delete an object; return (its last state, whether it is gone already).

        A pod bound to a node and not finished is only marked (``deletionTimestamp``);
        the node side removes it when it has stopped (a grace of 0 removes it at once).
        """
        with self.lock:
            key = (res, namespace, name)
            obj = self._objects.get(key)
            if obj is None:
                raise ApiError.not_found(res, name)
            if res == PODS and self._graceful(obj, grace):
                meta = obj["metadata"]
                if "deletionTimestamp" not in meta:
                    seconds = grace if grace is not None else int(
                        obj["spec"].get("terminationGracePeriodSeconds", 30))
                    meta.update(deletionTimestamp=now(), deletionGracePeriodSeconds=seconds)
                    self._propagation[key] = propagation  # for remove()
                    self._emit(res, namespace, "MODIFIED", obj)
                return copy.deepcopy(obj), False
            return self._remove(key, propagation), True

    @staticmethod
    def _graceful(pod: Obj, grace: int | None) -> bool:
        phase = (pod.get("status") or {}).get("phase")
        return (grace != 0 and bool(pod["spec"].get("nodeName"))
                and phase not in ("Succeeded", "Failed"))

    def remove(self, res: Resource, namespace: str | None, name: str) -> Obj | None:
        """Take a (terminating) object out for good: DELETED, then its dependents' GC."""
        with self.lock:
            obj = self._objects.get((res, namespace, name))
            if obj is None:
                return None
            key = (res, namespace, name)
            return self._remove(key, self._propagation.pop(key, "Background"))

    def _remove(self, key: Key, propagation: str) -> Obj:
        res, namespace, _ = key
        obj = self._objects.pop(key)
        self._propagation.pop(key, None)
        self._emit(res, namespace, "DELETED", obj)
        self._collect(obj["metadata"]["uid"], orphan=propagation == "Orphan")
        return copy.deepcopy(obj)

    def _collect(self, owner_uid: str, orphan: bool) -> None:
        for key, obj in list(self._objects.items()):
            refs = obj["metadata"].get("ownerReferences") or []
            kept = [ref for ref in refs if ref.get("uid") != owner_uid]
            if len(kept) == len(refs) or key not in self._objects:
                continue
            if kept or orphan:
                def drop(o: Obj, kept: list[Any] = kept) -> None:
                    o["metadata"]["ownerReferences"] = kept
                    if not kept:
                        del o["metadata"]["ownerReferences"]
                self.update(key[0], key[1], key[2], drop)
            else:
                self._remove(key, "Background")

    def _by_uid(self, uid: object) -> Obj | None:
        return next((o for o in self._objects.values() if o["metadata"]["uid"] == uid), None)

    # ------------------------------------------------------------------ events

    def _emit(self, res: Resource, namespace: str | None, kind: str, obj: Obj) -> None:
        self._rv += 1
        obj["metadata"]["resourceVersion"] = str(self._rv)
        if len(self._history) == self._history.maxlen:
            self._forgotten = self._history[0].rv
        event = Event(self._rv, res, namespace, kind, copy.deepcopy(obj))
        self._history.append(event)
        for watch in self._watches:
            if not watch.stalled.is_set() and watch.matches(event):
                watch.events.put(event)
        for listener in self._listeners:
            listener(event)

    def listen(self, listener: Listener) -> None:
        """Call ``listener`` with every event from now on (under the lock: queue work only)."""
        with self.lock:
            self._listeners.append(listener)

    def watch(self, res: Resource, namespace: str | None, selects: Predicate,
              since: str | None) -> Watch:
        """Open a watch from version ``since`` (None, "" or "0": the current objects as
        ADDED, then changes); ApiError 410 when ``since`` is older than the history."""
        watch = Watch(res, namespace, selects)
        with self.lock:
            if since in (None, "", "0"):
                items, _ = self.list(res, namespace, selects)
                for obj in items:
                    watch.events.put(Event(int(obj["metadata"]["resourceVersion"]), res,
                                           obj["metadata"].get("namespace"), "ADDED", obj))
            else:
                try:
                    asked = int(str(since))
                except ValueError:
                    raise ApiError(400, "BadRequest",
                                   f"invalid resource version: {since!r}") from None
                if asked < self._forgotten:
                    raise ApiError.expired(asked, self._forgotten)
                for event in self._history:
                    if event.rv > asked and watch.matches(event):
                        watch.events.put(event)
            self._watches.append(watch)
        return watch

    def close_watch(self, watch: Watch) -> None:
        """Forget a watch (its connection ended)."""
        with self.lock:
            if watch in self._watches:
                self._watches.remove(watch)

    def stop_watches(self) -> None:
        """End every open watch (the server is stopping)."""
        with self.lock:
            for watch in self._watches:
                watch.events.put(None)

    def compact(self) -> int:
        """Forget the history, as etcd's compaction does; return the newest version."""
        with self.lock:
            self._history.clear()
            self._forgotten = self._rv
            return self._rv

    def stall_watches(self) -> int:
        """Silence every watch open now (no more events; connections stay open)."""
        with self.lock:
            for watch in self._watches:
                watch.stalled.set()
            return len(self._watches)

    def objects(self, kinds: Iterable[Resource] = RESOURCES) -> Iterator[tuple[Resource, Obj]]:
        """Copies of every object of ``kinds`` (for checks that nothing is left)."""
        with self.lock:
            for (res, _, _), obj in list(self._objects.items()):
                if res in kinds:
                    yield res, copy.deepcopy(obj)

