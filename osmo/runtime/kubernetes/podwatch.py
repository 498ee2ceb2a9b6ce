"""One list + watch of pods, shared by every attempt that follows one of them.

:class:`PodWatch` owns the watch a node keeps on its pods (those its selector picks: the
node's instance label) and hands each event to the follower of that pod by name
(``osmo.runtime.kubernetes.follow``). A node following a hundred pods thus holds one watch
connection and lists once per :data:`SILENCE`, instead of one watch, one thread and one list
per pod, and the API server filters one stream instead of a hundred.

How it recovers is the follower's rule, made once: a watch that ends, goes silent longer than
``silence`` seconds, or answers 410 Gone is replaced by a fresh list and watch; after a list,
each followed pod gets its listed version, or ``ABSENT`` when the list lacks it (the follower
reads the pod to tell a pod created after the list from one that went). An API error during
a list goes to every follower then (each attempt fails as it would alone). The watch's thread
runs while someone follows a pod, and ends after its watch once nobody does.

It must not decide anything about a pod: verdicts are the follower's
(``osmo.runtime.kubernetes.status``).
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

from osmo.runtime.kubernetes.kube import Gone, Kube, KubeError

__all__ = ["ABSENT", "SILENCE", "Item", "PodWatch"]

Obj = dict[str, Any]
Item = tuple[str, Obj | None] | BaseException
"""What a follower gets: ``(event type, pod)``, ``(ABSENT, None)``, or the API's error."""

SILENCE = 20
"""Seconds a watch may deliver nothing before it is replaced by a list and a new watch."""
_AFTER_ERROR = 1.0  # seconds before a list that failed is tried again
ABSENT = "ABSENT"
"""The event type a follower gets when a list did not have its pod."""


class PodWatch:
    """Pods of ``namespace`` picked by ``labels`` and ``fields``, watched for their followers.

    Args:
        kube: the API.
        namespace: where the pods are.
        labels: a label selector (the node's instance label).
        fields: a field selector (``metadata.name=P`` for a watch of one pod).
        silence: seconds a watch may stay silent before it is replaced.
    """

    def __init__(self, kube: Kube, namespace: str, *, labels: str = "", fields: str = "",
                 silence: int = SILENCE) -> None:
        self.kube, self.namespace = kube, namespace
        self.labels, self.fields, self.silence = labels, fields, silence
        self._followers: dict[str, queue.Queue[Item]] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def follow(self, name: str) -> queue.Queue[Item]:
        """Hand pod ``name``'s events over, on the queue returned, until :meth:`forget`.

        Called before the pod is created, it misses none of them.
        """
        events: queue.Queue[Item] = queue.Queue()
        with self._lock:
            self._followers[name] = events
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="osmo-pod-watch")
                self._thread.start()
        return events

    def forget(self, name: str) -> None:
        """Stop handing pod ``name``'s events over."""
        with self._lock:
            self._followers.pop(name, None)

    def _run(self) -> None:
        version = ""
        while True:
            with self._lock:
                if not self._followers:
                    self._thread = None
                    return
            if not version:
                version = self._list()
                continue
            try:
                for kind, obj in self.kube.watch_pods(self.namespace, version=version,
                                                      fields=self.fields, labels=self.labels,
                                                      timeout=self.silence):
                    version = str(obj.get("metadata", {}).get("resourceVersion") or version)
                    self._hand(str((obj.get("metadata") or {}).get("name", "")), (kind, obj))
            except Gone:
                pass  # too old: list again
            except KubeError as exc:
                self._everyone(exc)
            version = ""  # the watch ended, went silent or was too old: list again

    def _list(self) -> str:
        """List the pods; hand each follower its pod's version (or ABSENT); the version."""
        try:
            items, version = self.kube.list_objects("pod", self.namespace, labels=self.labels,
                                                    fields=self.fields)
        except KubeError as exc:
            self._everyone(exc)
            time.sleep(_AFTER_ERROR)  # its followers give up; a later one lists again
            return ""
        found = {str(item["metadata"]["name"]): item for item in items}
        with self._lock:
            followers = dict(self._followers)
        for name, events in followers.items():
            pod = found.get(name)
            events.put(("MODIFIED", pod) if pod is not None else (ABSENT, None))
        return version

    def _hand(self, name: str, item: Item) -> None:
        with self._lock:
            events = self._followers.get(name)
        if events is not None:
            events.put(item)

    def _everyone(self, error: KubeError) -> None:
        with self._lock:
            followers = list(self._followers.values())
        for events in followers:
            events.put(error)
