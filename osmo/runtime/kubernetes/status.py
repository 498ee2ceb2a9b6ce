"""The one table from a pod's status to what osmo makes of its attempt (pure data).

:data:`TABLE` is read top to bottom; the first row whose test holds gives the
:class:`Verdict` (:func:`verdict`). ``osmo.runtime.kubernetes.follow`` asks it for every
version of the pod it sees, and for a pod that went away (``None``).

====================  ========================================  ============================
row                   the pod shows                             osmo
====================  ========================================  ============================
``gone``              it was deleted before its task ended      lost (rescheduled, not a
                                                                retry)
``node-lost``         phase Unknown or reason NodeLost          lost
``evicted``           reason Evicted (the kubelet's)            lost
``disrupted``         DisruptionTarget True (preemption, taint  lost
                      manager, eviction API)
``init-failed``       an init container ended with an error     FAILED_START_ERROR with its
                      (osmo's fetch: an input that did not      reason
                      match its digest)
``pull-failed``       the task container waits: ErrImagePull,   FAILED_START_ERROR with the
                      ImagePullBackOff, InvalidImageName, ...   registry's message
``config-failed``     waits: CreateContainerError,              FAILED_START_ERROR
                      RunContainerError
``oom-killed``        terminated, reason OOMKilled              exit 137, "OOMKilled"
``terminated``        terminated with an exit code              that exit code
``running``           the container runs                        running
``unschedulable``     PodScheduled False (Unschedulable)        waiting: the scheduler's
                                                                message
``pending``           anything else (ContainerCreating, a       waiting: the reason
                      Secret still missing)
====================  ========================================  ============================
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

from osmo.runtime.kubernetes.manifest import CONTAINER

__all__ = ["TABLE", "Outcome", "Row", "Verdict", "verdict"]

Pod = Mapping[str, Any]

PULL_FAILURES = frozenset({"ErrImagePull", "ImagePullBackOff", "InvalidImageName",
                           "ErrImageNeverPull", "RegistryUnavailable"})
CREATE_FAILURES = frozenset({"CreateContainerError", "RunContainerError",
                             "PreCreateHookError", "PostStartHookError"})


class Outcome(Enum):
    """What an attempt's pod means for the attempt."""

    WAITING = "waiting"
    RUNNING = "running"
    EXITED = "exited"
    START_FAILED = "start_failed"
    LOST = "lost"


@dataclass(frozen=True)
class Verdict:
    """A row's answer: the outcome, an exit code (EXITED) and the reason to show."""

    outcome: Outcome
    message: str = ""
    exit_code: int | None = None
    row: str = ""

    @property
    def final(self) -> bool:
        """Whether the attempt ended (nothing the pod does later changes it)."""
        return self.outcome in (Outcome.EXITED, Outcome.START_FAILED, Outcome.LOST)


@dataclass(frozen=True)
class Row:
    """One row: its name, when it holds, and what it says."""

    name: str
    holds: Callable[[Pod | None], bool]
    says: Callable[[Pod | None], Verdict]


def _status(pod: Pod | None) -> Mapping[str, Any]:
    return (pod or {}).get("status") or {}


def _state(pod: Pod | None) -> tuple[str, Mapping[str, Any]]:
    """The task container's state: ``(waiting|running|terminated|"", details)``."""
    for entry in _status(pod).get("containerStatuses") or []:
        if entry.get("name") == CONTAINER:
            for kind, info in (entry.get("state") or {}).items():
                if info:
                    return kind, info
    return "", {}


def _condition(pod: Pod | None, kind: str) -> Mapping[str, Any] | None:
    for entry in _status(pod).get("conditions") or []:
        if entry.get("type") == kind:
            return entry  # type: ignore[no-any-return]
    return None


def _disrupted(pod: Pod | None) -> bool:
    found = _condition(pod, "DisruptionTarget")
    return found is not None and found.get("status") == "True"


def _unschedulable(pod: Pod | None) -> bool:
    found = _condition(pod, "PodScheduled")
    return found is not None and found.get("status") == "False"


def _failed_init(pod: Pod | None) -> Mapping[str, Any] | None:
    """The first init container that ended with an error: its status entry (None: none)."""
    for entry in _status(pod).get("initContainerStatuses") or []:
        ended = (entry.get("state") or {}).get("terminated")
        if ended and int(ended.get("exitCode", 0)) != 0:
            return entry  # type: ignore[no-any-return]
    return None


def _init_failed(pod: Pod | None) -> Verdict:
    entry = _failed_init(pod) or {}
    info = (entry.get("state") or {}).get("terminated") or {}
    return Verdict(Outcome.START_FAILED, f"init container {entry.get('name')} failed (exit "
                   f"{info.get('exitCode')}): " + _why(info, "Error"))


def _why(info: Mapping[str, Any], fallback: str = "") -> str:
    reason, message = info.get("reason") or fallback, info.get("message") or ""
    return f"{reason}: {message}" if reason and message else reason or message


def _lost(message: str) -> Callable[[Pod | None], Verdict]:
    def says(pod: Pod | None) -> Verdict:
        status = _status(pod)
        detail = status.get("message") or (_condition(pod, "DisruptionTarget") or {}).get(
            "message") or ""
        return Verdict(Outcome.LOST, f"{message}: {detail}" if detail else message)
    return says


def _terminated(pod: Pod | None) -> Verdict:
    info = _state(pod)[1]
    code = int(info.get("exitCode", 1))
    return Verdict(Outcome.EXITED, _why(info), code)


TABLE: tuple[Row, ...] = (
    Row("gone", lambda pod: pod is None,
        lambda pod: Verdict(Outcome.LOST, "the pod was deleted before its task ended")),
    Row("node-lost", lambda pod: _status(pod).get("phase") == "Unknown"
        or _status(pod).get("reason") == "NodeLost", _lost("the pod's node was lost")),
    Row("evicted", lambda pod: _status(pod).get("reason") == "Evicted",
        _lost("the pod was evicted")),
    Row("disrupted", _disrupted,
        lambda pod: Verdict(Outcome.LOST, "the pod was disrupted: " + _why(
            _condition(pod, "DisruptionTarget") or {}))),
    Row("init-failed", lambda pod: _failed_init(pod) is not None, _init_failed),
    Row("pull-failed", lambda pod: _state(pod)[0] == "waiting"
        and _state(pod)[1].get("reason") in PULL_FAILURES,
        lambda pod: Verdict(Outcome.START_FAILED, "image pull failed: " + _why(_state(pod)[1]))),
    Row("config-failed", lambda pod: _state(pod)[0] == "waiting"
        and _state(pod)[1].get("reason") in CREATE_FAILURES,
        lambda pod: Verdict(Outcome.START_FAILED, "the container could not be created: "
                            + _why(_state(pod)[1]))),
    Row("oom-killed", lambda pod: _state(pod)[0] == "terminated"
        and _state(pod)[1].get("reason") == "OOMKilled",
        lambda pod: Verdict(Outcome.EXITED, "OOMKilled: the task used more memory than its "
                            "limit", 137)),
    Row("terminated", lambda pod: _state(pod)[0] == "terminated", _terminated),
    Row("running", lambda pod: _state(pod)[0] == "running",
        lambda pod: Verdict(Outcome.RUNNING)),
    Row("unschedulable", _unschedulable,
        lambda pod: Verdict(Outcome.WAITING, "unschedulable: " + str(
            (_condition(pod, "PodScheduled") or {}).get("message") or "no node fits"))),
    Row("pending", lambda pod: True,
        lambda pod: Verdict(Outcome.WAITING, _why(_state(pod)[1], "pending"))),
)
"""The rows, in the order they are tried (see the module docstring)."""


def verdict(pod: Pod | None) -> Verdict:
    """What ``pod`` (None: deleted) means for its attempt: the first row that holds."""
    for row in TABLE:
        if row.holds(pod):
            found = row.says(pod)
            return Verdict(found.outcome, found.message, found.exit_code, row.name)
    raise AssertionError("the last row always holds")
