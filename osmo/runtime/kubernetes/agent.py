"""``python -m osmo.runtime.kubernetes.agent PLAN``: the local process standing for one pod.

The Kubernetes runtime starts one per attempt (``osmo.runtime.kubernetes.runtime``): it is
what the worker pool's reactor watches (its stdout is the task's log, its exit code the
task's), what a kill signals (SIGTERM: the pod is deleted with its grace) and what a
restarted worker's clean-up finds by pid. It reads its plan (a 0600 JSON file holding the
manifests and the Secret's values) and deletes it at once, follows the pod
(``osmo.runtime.kubernetes.follow``), writes its verdict to the plan's ``verdict`` file for the
runtime, and exits with:

- the task container's exit code (EXITED);
- :data:`START_FAILED` (125): the pod never ran its task (an image that cannot be pulled);
- :data:`LOST` (3): the pod was lost (evicted, preempted, its node lost, deleted by someone).

When its worker dies (even of SIGKILL) it is sent SIGTERM (``PR_SET_PDEATHSIG``), so it
deletes its pod, as a kill does; whatever is still left (the agent killed too) the node's
next start deletes by label.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["LOST", "START_FAILED", "main"]

START_FAILED = 125
LOST = 3


def main(argv: list[str]) -> int:
    """Follow the pod of the plan file ``argv[0]``; the exit code (module docstring)."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    plan_file = Path(argv[0])
    plan = json.loads(plan_file.read_text())
    plan_file.unlink(missing_ok=True)
    _term_with_parent(int(plan.get("parent") or 0), stop)
    verdict_file = Path(plan["verdict"])

    def note(line: str) -> None:
        sys.stderr.write(f"osmo: {line}\n")
        sys.stderr.flush()

    from osmo.runtime.kubernetes.follow import PodFollower
    from osmo.runtime.kubernetes.kube import KubeError, connect
    from osmo.runtime.kubernetes.status import Outcome

    try:
        kube = connect(plan.get("kubeconfig"), plan.get("context"))
        follower = PodFollower(kube, plan["pod"], plan.get("secret"), out=sys.stdout.buffer,
                               note=note, stop=stop)
        found = follower.run()
    except KubeError as exc:
        _write(verdict_file, {"outcome": "start_failed", "message": str(exc)})
        note(str(exc))
        return START_FAILED
    _write(verdict_file, {"outcome": found.outcome.value, "message": found.message,
                          "exit_code": found.exit_code, "image_id": follower.image_id})
    if found.message and found.outcome is not Outcome.EXITED:
        note(found.message)
    elif found.message and found.exit_code:
        note(f"the task's container ended: {found.message}")
    if found.outcome is Outcome.START_FAILED:
        return START_FAILED
    if found.outcome is Outcome.LOST:
        return LOST
    return found.exit_code if found.exit_code is not None else 1


def _term_with_parent(parent: int, stop: threading.Event) -> None:
    """SIGTERM this process when its worker dies (its pod is then deleted, as on a kill)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    if parent and os.getppid() != parent:  # it died before the line above
        stop.set()


def _write(path: Path, verdict: dict[str, object]) -> None:
    temp = path.with_name(path.name + ".tmp")
    temp.write_text(json.dumps(verdict))
    os.replace(temp, path)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
