"""One attempt's pod, from its creation to its deletion: watch, log, verdict, clean-up.

:class:`PodFollower` is what the Kubernetes runtime runs, on a thread, for each attempt:

1. create the pod, then its Secret owned by it (the pod waits for the Secret, as
   ``CreateContainerConfigError``; the API's garbage collector deletes the Secret with the
   pod). API writes per attempt: pod, Secret (only with credentials), delete. A Secret that
   also holds the image's registry credentials is created first, with no owner (the kubelet
   needs it to pull), and deleted after the pod: one write more.
2. follow the pod's versions as the node's shared watch hands them over
   (``osmo.runtime.kubernetes.podwatch``: one list + watch for all the node's pods, replaced
   when it ends, goes silent longer than :data:`SILENCE`, or answers 410 Gone; a follower
   made without one watches its pod alone the same way). A list that lacks the pod makes
   the follower read it: gone, or created after that list. Each version goes through the
   status table (``osmo.runtime.kubernetes.status``); a new
   waiting reason other than the ordinary ones (pending, ContainerCreating) goes to the
   server (``waiting``: the node's ``AttemptWaiting`` report, so ``osmo query`` and ``osmo
   events`` show ``unschedulable: 0/3 nodes are available: 3 Insufficient cpu.``) and is
   noted in the attempt's log (``note``: ``osmo: pod P: waiting: ...``); ``waiting("")``
   clears it once the pod waits no more.
3. once the task's container runs (or ended), stream its log to ``out`` until it ends.
4. a kill (``stop``): delete the pod with the 3 s grace (``force``: with none); a pod still
   there :data:`FORCE_AFTER` seconds later is deleted with no grace, and the follower gives
   up :data:`GIVE_UP_AFTER` seconds after the kill (the node's next start deletes it).
5. at the end, whatever the verdict, the pod is deleted (its Secret goes with it), after
   the verdict was handed on; ``on_end`` sees it first (a pod that sends its own output
   back is waited for there, while it still exists).

A follower made with ``adopted`` (the pod as the API has it: a restarted node adopts it)
creates nothing: it follows that pod from step 2, and its log from after the ``skip`` bytes
a previous life already sent.
"""

from __future__ import annotations

import copy
import queue
import threading
import time
from collections.abc import Callable
from typing import IO, Any

from osmo.runtime.kubernetes.kube import Kube, KubeError
from osmo.runtime.kubernetes.manifest import CONTAINER
from osmo.runtime.kubernetes.podwatch import ABSENT, SILENCE, Item, PodWatch
from osmo.runtime.kubernetes.status import Outcome, Verdict, verdict

__all__ = ["FORCE_AFTER", "GIVE_UP_AFTER", "SILENCE", "PodFollower"]

Obj = dict[str, Any]

FORCE_AFTER = 5.0
"""Seconds after a graceful delete (3 s grace) before the pod is deleted with no grace."""
GIVE_UP_AFTER = 30.0
"""Seconds after a kill before the follower stops waiting for the pod to go."""
_ORDINARY = frozenset({"pending", "ContainerCreating", "PodInitializing"})  # not worth a line
_LOG_WAIT = 10.0  # seconds the log may take to drain after the container ended


class PodFollower:
    """The life of one attempt's pod (see the module docstring).

    Args:
        kube: the API.
        pod: the Pod manifest.
        secret: its Secret manifest, owned by the pod once created (None: it has none).
        out: where the task container's log goes (bytes, as they come).
        note: where osmo's lines about the pod go (waiting reasons, the kill).
        stop: set to kill the attempt.
        force: set (with ``stop``) to delete the pod at once, with no grace.
        silence: seconds a watch may stay silent before it is replaced (without ``watch``).
        watch: the node's shared watch of its pods (None: the follower watches its pod
            alone).
        waiting: why the pod waits, told once per new reason (``""``: it waits no more).
        adopted: the pod, found running by a restarted node: it is followed, not created.
        skip: bytes of the task's log already sent (an adopted pod's): not sent again.
        on_end: gets the verdict once the pod's task ended, before it is handed on and the
            pod deleted; returns the verdict to hand on.
    """

    def __init__(self, kube: Kube, pod: Obj, secret: Obj | None, *, out: IO[bytes],
                 note: Callable[[str], None], stop: threading.Event,
                 force: threading.Event | None = None, silence: int = SILENCE,
                 waiting: Callable[[str], None] = lambda _reason: None,
                 adopted: Obj | None = None, skip: int = 0,
                 on_end: Callable[[Verdict], Verdict] | None = None,
                 watch: PodWatch | None = None) -> None:
        self.kube, self.pod, self.secret = kube, pod, secret
        self.namespace = str(pod["metadata"]["namespace"])
        self.name = str(pod["metadata"]["name"])
        self.out, self.note, self.stop, self.waiting = out, note, stop, waiting
        self.force = force or threading.Event()
        self._watch = watch or PodWatch(kube, self.namespace, silence=silence,
                                        fields=f"metadata.name={self.name}")
        self._events: queue.Queue[Item] = queue.Queue()
        self._log_thread: threading.Thread | None = None
        self._deleting_at: float | None = None
        self._forced = False
        self.image_id: str | None = None
        self._adopted, self._skip = adopted, skip
        self._on_end = on_end

    def run(self, ended: Callable[[Verdict], None] | None = None) -> Verdict:
        """Create, follow and delete the pod; what became of the attempt.

        ``ended`` gets the verdict as soon as the task's log is complete, before the pod is
        deleted (the deletion is not the attempt's to wait for).

        Raises:
            KubeError: the pod could not be created (nothing is left then).
        """
        self._events = self._watch.follow(self.name)  # before the pod exists: nothing missed
        try:
            if self._adopted is not None:
                self._events.put((ABSENT, None))  # read again: it changed since it was found
                return self._follow_adopted(self._adopted, ended)
            return self._create_and_follow(ended)
        finally:
            self._watch.forget(self.name)

    def _create_and_follow(self, ended: Callable[[Verdict], None] | None) -> Verdict:
        """Steps 1 to 5 (the module docstring)."""
        first = self.secret is not None and "ownerReferences" not in self.secret["metadata"]
        if first:  # a pull Secret: the kubelet needs it before it pulls
            assert self.secret is not None
            self.kube.create("secret", self.namespace, self.secret)
        try:
            created = self.kube.create("pod", self.namespace, self.pod)
        except BaseException:
            self._delete_secret(first)
            raise
        try:
            if self.secret is not None and not first:
                owned = copy.deepcopy(self.secret)
                owned["metadata"]["ownerReferences"][0]["uid"] = created["metadata"]["uid"]
                self.kube.create("secret", self.namespace, owned)
            found = self._follow(created)
        except BaseException:
            self._delete(grace=0)
            self._delete_secret(first)
            raise
        self._finish_logs(found)
        if self._on_end is not None:
            found = self._on_end(found)
        if ended is not None:
            ended(found)
        self._delete(grace=0)
        self._delete_secret(first)
        return found

    def _follow_adopted(self, pod: Obj, ended: Callable[[Verdict], None] | None) -> Verdict:
        """Steps 2 to 5 for a pod a previous life of the node created."""
        try:
            found = self._follow(pod)
        except BaseException:
            self._delete(grace=0)
            raise
        self._finish_logs(found)
        if self._on_end is not None:  # an adopted pod with its own data: its collection
            found = self._on_end(found)
        if ended is not None:
            ended(found)
        self._delete(grace=0)
        return found

    def _delete_secret(self, unowned: bool) -> None:
        """A pull Secret has no owner: it is deleted after its pod."""
        if not unowned:
            return
        try:
            self.kube.delete("secret", self.namespace, self.name)
        except KubeError as exc:
            self.note(f"secret {self.name}: cannot delete it: {exc}")

    # ------------------------------------------------------------ following

    def _follow(self, created: Obj) -> Verdict:
        last = verdict(created)
        shown = ""
        while True:
            if self.stop.is_set():
                self._kill()
            try:
                item = self._events.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise item
            kind, obj = item
            if kind == ABSENT:  # a list lacked it: gone, or created after that list?
                obj = self.kube.read_pod(self.namespace, self.name)
                kind = "DELETED" if obj is None else "MODIFIED"
            last = verdict(None if kind == "DELETED" and not _ended(obj) else obj)
            if self._deleting_at is not None and last.outcome is Outcome.LOST:
                code = _exit_code(obj)  # none: gone before its container said (SIGKILL if forced)
                killed = 137 if self._forced else 143
                return Verdict(Outcome.EXITED, "killed", killed if code is None else code)
            if (last.outcome is Outcome.WAITING and last.message != shown
                    and last.message not in _ORDINARY and not self._own_secret(last)):
                shown = last.message
                self.waiting(last.message)
                self.note(f"pod {self.name}: waiting: {last.message}")
            if last.outcome is not Outcome.WAITING and shown:
                shown = ""
                self.waiting("")  # waits no more: osmo query shows no reason
            if last.outcome in (Outcome.RUNNING, Outcome.EXITED) and self._log_thread is None:
                self._image(obj)
                self._start_logs()
            if last.final:
                if last.outcome is Outcome.EXITED and self._deleting_at is not None:
                    return Verdict(Outcome.EXITED, last.message, last.exit_code or 143)
                return last

    def _own_secret(self, found: Verdict) -> bool:
        """The pod waits for its own Secret, created just after it: nothing to say."""
        return self.secret is not None and f'"{self.name}"' in found.message

    # ------------------------------------------------------------ kill and delete

    def _kill(self) -> None:
        now = time.monotonic()
        if self._deleting_at is None and self.force.is_set():
            self._deleting_at, self._forced = now, True
            self.note(f"pod {self.name}: deleting at once")
            self._delete(grace=0)
        elif self._deleting_at is None:
            self._deleting_at = now
            self.note(f"pod {self.name}: deleting with a 3 s grace")
            self._delete(grace=3)
        elif not self._forced and (self.force.is_set()
                                   or now - self._deleting_at > FORCE_AFTER):
            self._forced = True
            self.note(f"pod {self.name}: still there after the grace: deleting at once")
            self._delete(grace=0)
        elif self._forced and now - self._deleting_at > GIVE_UP_AFTER:
            raise KubeError(f"pod {self.name} is still there {GIVE_UP_AFTER:g} s after its "
                            "deletion; the node's next start deletes it")

    def _delete(self, grace: int) -> None:
        try:
            self.kube.delete("pod", self.namespace, self.name, grace=grace)
        except KubeError as exc:
            self.note(f"pod {self.name}: cannot delete it: {exc}")

    # ------------------------------------------------------------ logs

    def _image(self, obj: Obj | None) -> None:
        for entry in ((obj or {}).get("status") or {}).get("containerStatuses") or []:
            if entry.get("name") == CONTAINER and entry.get("imageID"):
                self.image_id = str(entry["imageID"])

    def _start_logs(self) -> None:
        self._log_thread = threading.Thread(target=self._logs, daemon=True, name="osmo-pod-log")
        self._log_thread.start()

    def _logs(self) -> None:
        for _ in range(20):
            skip = self._skip  # the stream starts at the log's start each time
            try:
                for chunk in self.kube.logs(self.namespace, self.name, CONTAINER):
                    cut = min(skip, len(chunk))
                    skip -= cut
                    if cut < len(chunk):
                        self.out.write(chunk[cut:])
                return
            except OSError:
                return  # nobody reads the log any more (the attempt was let go)
            except KubeError as exc:
                if exc.status != 400:  # 400: not started yet
                    self.note(f"pod {self.name}: its log cannot be read: {exc}")
                    return
            time.sleep(0.25)

    def _finish_logs(self, found: Verdict) -> None:
        if self._log_thread is None and found.outcome is Outcome.EXITED:
            self._start_logs()
        if self._log_thread is not None:
            self._log_thread.join(_LOG_WAIT)


def _ended(obj: Obj | None) -> bool:
    return _exit_code(obj) is not None


def _exit_code(obj: Obj | None) -> int | None:
    for entry in ((obj or {}).get("status") or {}).get("containerStatuses") or []:
        if entry.get("name") == CONTAINER:
            ended = (entry.get("state") or {}).get("terminated")
            if ended:
                return int(ended.get("exitCode", 1))
    return None
