"""Status scripts: a pod's life played from a list of steps instead of podman.

A test registers a :class:`Script` for a pod name (``Kubelet.script``) before creating the
pod; the kubelet then publishes each step's status through the API, one after the other,
and never starts a container. Each step builds the status the real kubelet and control plane
publish in that situation, so an executor's status table can be tested row by row:

==========================  ===========================================================
step                        what the API shows
==========================  ===========================================================
``unschedulable()``         Pending; PodScheduled False, reason Unschedulable
``scheduled()``             bound to the node; containers waiting (ContainerCreating)
``running()``               Running; containers running, Ready, a pod IP
``succeeded()``             Succeeded; containers terminated, exit 0, Completed
``failed(code)``            Failed; containers terminated with ``code``, reason Error
``image_pull_error()``      Pending; waiting, reason ErrImagePull, the registry's message
``image_pull_backoff()``    Pending; waiting, reason ImagePullBackOff
``oom_killed()``            Failed; terminated, exit 137, reason OOMKilled
``evicted()``               Failed, reason Evicted; DisruptionTarget TerminationByKubelet
``preempted()``             DisruptionTarget PreemptionByScheduler (then ``deleted()``)
``node_lost()``             phase Unknown, reason NodeLost; Ready False
``deleted(reason)``         the pod is removed (DELETED), with ``reason`` in its last status
``stall_watches()``         the watches open now go silent (no events, connection open)
``wait(event)``             nothing until the test sets ``event``
==========================  ===========================================================

:data:`SCRIPTS` names the sequences the executor's table needs. Deleting a scripted pod
ends its script; its containers end with exit 137.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from tests.k8s.store import now

__all__ = ["SCRIPTS", "Script", "ScriptPod", "Step", "deleted", "evicted", "failed",
           "image_pull_backoff", "image_pull_error", "node_lost", "oom_killed", "preempted",
           "running", "scheduled", "stall_watches", "succeeded", "unschedulable", "wait"]

Obj = dict[str, Any]


class ScriptPod(Protocol):
    """What a step may do to its pod (the kubelet implements it)."""

    node: str

    def change(self, change: Callable[[Obj], None]) -> None:
        """Apply ``change`` to the stored pod (its status, its node)."""

    def remove(self) -> None:
        """Take the pod out of the API (DELETED)."""

    def stall_watches(self) -> None:
        """Silence the watches open now."""

    def wait(self, event: threading.Event) -> None:
        """Block until ``event`` is set (or the node closes)."""


@dataclass(frozen=True)
class Step:
    """One scripted change: a name (for messages) and what it does."""

    name: str
    act: Callable[[ScriptPod], None]


@dataclass(frozen=True)
class Script:
    """Steps played in order, ``pause`` seconds apart; ``logs`` is what pods/log returns."""

    steps: tuple[Step, ...]
    logs: str = ""
    pause: float = 0.05


def _containers(pod: Obj, state: Obj, ready: bool = False) -> list[Obj]:
    return [{"name": c["name"], "image": c.get("image", ""), "imageID": "",
             "ready": ready, "restartCount": 0, "started": "running" in state, "state": state}
            for c in pod["spec"]["containers"]]


def _set(phase: str, *, state: Obj, ready: bool = False, **extra: Any) -> Callable[[Obj], None]:
    def change(pod: Obj) -> None:
        status = pod.setdefault("status", {})
        status.update(phase=phase, containerStatuses=_containers(pod, state, ready), **extra)
        _condition(status, "Ready", ready, "" if ready else "ContainersNotReady")
        _condition(status, "ContainersReady", ready, "" if ready else "ContainersNotReady")
    return change


def _condition(status: Obj, kind: str, value: bool, reason: str = "", message: str = "") -> None:
    conditions = [c for c in status.get("conditions") or [] if c["type"] != kind]
    entry = {"type": kind, "status": "True" if value else "False",
             "lastTransitionTime": now()}
    if reason:
        entry["reason"] = reason
    if message:
        entry["message"] = message
    status["conditions"] = [*conditions, entry]


def unschedulable(message: str = "0/1 nodes are available: 1 Insufficient nvidia.com/gpu.") -> Step:
    """Pending, not placed: PodScheduled False, reason Unschedulable."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            status = obj.setdefault("status", {})
            status["phase"] = "Pending"
            _condition(status, "PodScheduled", False, "Unschedulable", message)
        pod.change(change)
    return Step("unschedulable", act)


def scheduled() -> Step:
    """Bound to the node; containers waiting (ContainerCreating)."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            obj["spec"]["nodeName"] = pod.node
            _set("Pending", state={"waiting": {"reason": "ContainerCreating"}},
                 hostIP="127.0.0.1", startTime=now())(obj)
            _condition(obj["status"], "PodScheduled", True)
        pod.change(change)
    return Step("scheduled", act)


def running() -> Step:
    """Running: containers running and ready, with a pod IP."""
    def act(pod: ScriptPod) -> None:
        pod.change(_set("Running", state={"running": {"startedAt": now()}}, ready=True,
                        podIP="10.244.0.10", podIPs=[{"ip": "10.244.0.10"}]))
    return Step("running", act)


def _terminated(code: int, reason: str) -> Obj:
    return {"terminated": {"exitCode": code, "reason": reason, "startedAt": now(),
                           "finishedAt": now(), "containerID": "scripted://"}}


def succeeded() -> Step:
    """Succeeded: every container exited 0 (Completed)."""
    def act(pod: ScriptPod) -> None:
        pod.change(_set("Succeeded", state=_terminated(0, "Completed")))
    return Step("succeeded", act)


def failed(code: int = 1) -> Step:
    """Failed: every container exited with ``code`` (Error)."""
    def act(pod: ScriptPod) -> None:
        pod.change(_set("Failed", state=_terminated(code, "Error")))
    return Step(f"failed({code})", act)


def image_pull_error(message: str = 'rpc error: code = NotFound desc = failed to pull and '
                     'unpack image "nvcr.io/nvidia/nosuch:1.0": not found') -> Step:
    """Pending: waiting, reason ErrImagePull, with the registry's message."""
    def act(pod: ScriptPod) -> None:
        pod.change(_set("Pending", state={"waiting": {"reason": "ErrImagePull",
                                                      "message": message}}))
    return Step("image_pull_error", act)


def image_pull_backoff() -> Step:
    """Pending: waiting, reason ImagePullBackOff."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            image = obj["spec"]["containers"][0].get("image", "")
            _set("Pending", state={"waiting": {"reason": "ImagePullBackOff",
                                               "message": f'Back-off pulling image "{image}"'}})(
                obj)
        pod.change(change)
    return Step("image_pull_backoff", act)


def oom_killed() -> Step:
    """Failed: killed for memory, exit 137, reason OOMKilled."""
    def act(pod: ScriptPod) -> None:
        pod.change(_set("Failed", state=_terminated(137, "OOMKilled")))
    return Step("oom_killed", act)


def evicted(message: str = "The node was low on resource: memory. Threshold quantity: "
            "100Mi, available: 52Mi.") -> Step:
    """Failed, reason Evicted: the kubelet evicted the pod."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            _set("Failed", state=_terminated(137, "Error"), reason="Evicted",
                 message=message)(obj)
            _condition(obj["status"], "DisruptionTarget", True, "TerminationByKubelet", message)
        pod.change(change)
    return Step("evicted", act)


def preempted() -> Step:
    """DisruptionTarget True, reason PreemptionByScheduler (a deletion follows)."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            _condition(obj.setdefault("status", {}), "DisruptionTarget", True,
                       "PreemptionByScheduler", "default-scheduler: preempting to "
                       "accommodate a higher priority pod")
        pod.change(change)
    return Step("preempted", act)


def node_lost() -> Step:
    """Phase Unknown, reason NodeLost: the node stopped reporting."""
    def act(pod: ScriptPod) -> None:
        def change(obj: Obj) -> None:
            status = obj.setdefault("status", {})
            name = obj["metadata"]["name"]
            status.update(phase="Unknown", reason="NodeLost",
                          message=f"Node {pod.node} which was running pod {name} is "
                          "unresponsive")
            _condition(status, "Ready", False, "NodeLost")
        pod.change(change)
    return Step("node_lost", act)


def deleted(reason: str = "") -> Step:
    """The pod is removed from the API; ``reason`` goes into its last status first."""
    def act(pod: ScriptPod) -> None:
        if reason:
            def change(obj: Obj) -> None:
                status = obj.setdefault("status", {})
                status["reason"] = reason
                _condition(status, "DisruptionTarget", True, "DeletionByTaintManager"
                           if reason == "NodeLost" else reason)
            pod.change(change)
        pod.remove()
    return Step(f"deleted({reason})", act)


def stall_watches() -> Step:
    """The watches open now deliver nothing more (their connections stay open)."""
    return Step("stall_watches", lambda pod: pod.stall_watches())


def wait(event: threading.Event) -> Step:
    """Nothing happens until the test sets ``event``."""
    return Step("wait", lambda pod: pod.wait(event))


SCRIPTS: dict[str, Script] = {
    "unschedulable-running-succeeded": Script((unschedulable(), scheduled(), running(),
                                               succeeded()), logs="hello from a script\n"),
    "image-pull-error": Script((scheduled(), image_pull_error(), image_pull_backoff())),
    "oom-killed": Script((scheduled(), running(), oom_killed())),
    "evicted": Script((scheduled(), running(), evicted())),
    "preempted": Script((scheduled(), running(), preempted(), deleted())),
    "node-lost": Script((scheduled(), running(), node_lost(), deleted("NodeLost"))),
    "watch-stalls": Script((scheduled(), running(), stall_watches(), succeeded())),
}
"""The scripted lives the executor's status table is tested against, by name."""
