"""Slurm's job states in osmo's terms: the one table (:data:`STATES`), and nothing else.

=====================================================  ===========================================
Slurm state                                            for osmo
=====================================================  ===========================================
PENDING, REQUEUED, REQUEUE_HOLD, REQUEUE_FED,          **waiting**: its reason (``Resources``,
RESV_DEL_HOLD, CONFIGURING                             ``Priority``, ``QOSMaxJobsPerUserLimit``...)
                                                       is the attempt's waiting reason in ``osmo
                                                       query`` and ``osmo events``
                                                       (:func:`waiting_reason`) and goes to its log
RUNNING, COMPLETING, SIGNALING, STAGE_OUT, RESIZING,   **running**
SUSPENDED, STOPPED
COMPLETED, FAILED, SPECIAL_EXIT                        **ended**: the agent's exit code (1 when
                                                       the job ended before its agent could say)
CANCELLED                                              **ended**: the agent's code, else 137
OUT_OF_MEMORY                                          **ended**: 137, "over its --mem"
TIMEOUT, DEADLINE                                      **ended**: the agent's code (143: the
                                                       task got SIGTERM), else 137; osmo's own
                                                       ``exec_timeout`` is kept beside it; the
                                                       runtime reports a TIMEOUT osmo did not
                                                       cause as ``ExitCode.EXEC_TIMEOUT``: the
                                                       task is FAILED_EXEC_TIMEOUT
NODE_FAIL, PREEMPTED, BOOT_FAIL                        **lost**: submitted again, the same
                                                       attempt, not counted against its retries
=====================================================  ===========================================

A state missing from the table (a newer Slurm's) counts as running while the job is in
``squeue`` (the node asks again) and as ended with code 1 once it has gone.

:data:`REASONS` says in a few words what the commonest of squeue's pending reasons (``%r``)
mean; any other is shown as Slurm words it.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["REASONS", "STATES", "Phase", "Verdict", "verdict", "waiting_reason"]


class Phase(enum.Enum):
    """Where a job is, for osmo."""

    WAITING = "waiting"
    RUNNING = "running"
    ENDED = "ended"
    LOST = "lost"


@dataclass(frozen=True)
class Verdict:
    """What a Slurm state means for the attempt.

    Attributes:
        phase: waiting, running, ended or lost.
        code: the exit code when the agent gave none (None: not ended).
        override: this code wins over the agent's (OUT_OF_MEMORY's 137).
        reason: the osmo log line that says why (None: nothing to say).
    """

    phase: Phase
    code: int | None = None
    override: bool = False
    reason: str | None = None


_W, _R = Verdict(Phase.WAITING), Verdict(Phase.RUNNING)

STATES: dict[str, Verdict] = {
    **dict.fromkeys(("PENDING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESV_DEL_HOLD",
                     "CONFIGURING"), _W),
    **dict.fromkeys(("RUNNING", "COMPLETING", "SIGNALING", "STAGE_OUT", "RESIZING",
                     "SUSPENDED", "STOPPED"), _R),
    "COMPLETED": Verdict(Phase.ENDED, 0),
    "FAILED": Verdict(Phase.ENDED, 1, reason="Slurm: the job FAILED"),
    "SPECIAL_EXIT": Verdict(Phase.ENDED, 1, reason="Slurm: the job ended SPECIAL_EXIT"),
    "CANCELLED": Verdict(Phase.ENDED, 137, reason="Slurm: the job was CANCELLED"),
    "OUT_OF_MEMORY": Verdict(Phase.ENDED, 137, override=True,
                             reason="Slurm: OUT_OF_MEMORY: the task went over its memory "
                                    "(--mem); exit code 137"),
    "TIMEOUT": Verdict(Phase.ENDED, 137, reason="Slurm: TIMEOUT: the job reached its time "
                                                "limit (--time)"),
    "DEADLINE": Verdict(Phase.ENDED, 137, reason="Slurm: DEADLINE: the job reached its "
                                                 "deadline"),
    **{state: Verdict(Phase.LOST, reason=f"Slurm: {state}: the attempt is lost, not failed")
       for state in ("NODE_FAIL", "PREEMPTED", "BOOT_FAIL")},
}
"""Slurm's job state → what it means for the attempt (see the module docstring)."""


def verdict(state: str, *, listed: bool = True) -> Verdict:
    """What ``state`` means (``listed``: the job is still in ``squeue``).

    ``squeue`` may add a suffix (``CANCELLED by 0``): the first word counts.
    """
    word = state.split()[0] if state.strip() else ""
    known = STATES.get(word)
    if known is not None:
        return known
    if listed:
        return _R
    return Verdict(Phase.ENDED, 1, reason=f"Slurm: the job ended in state {state!r}")


REASONS: dict[str, str] = {
    "Resources": "the nodes it needs are busy",
    "Priority": "jobs of a higher priority are queued before it",
    "Dependency": "it waits for another job",
    "JobHeldUser": "held by a user (scontrol release)",
    "JobHeldAdmin": "held by an administrator",
    "BeginTime": "its start time has not come",
    "ReqNodeNotAvail": "a node it needs is down, drained or reserved",
    "PartitionTimeLimit": "it asks for more time than its partition allows",
    "QOSMaxJobsPerUserLimit": "its QOS's limit of jobs per user is reached",
    "AssocGrpCpuLimit": "its account's CPU limit is reached",
    "AssocMaxJobsLimit": "its account's job limit is reached",
}
"""squeue's commonest pending reasons, in a few words (:func:`waiting_reason`)."""


def waiting_reason(job_id: str, state: str, reason: str) -> str:
    """Why a waiting job waits, for ``osmo query``: ``Slurm job 12 PENDING: Resources (...)``."""
    word = reason.strip() or "None"
    meaning = REASONS.get(word)
    return f"Slurm job {job_id} {state}: {word}" + (f" ({meaning})" if meaning else "")
