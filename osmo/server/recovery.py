"""Rebuilding the scheduler from the store, and quarantining what crashed the server.

The store is the truth: every batch the engine applies is committed before any of its
commands runs. So a scheduler built from the store (:func:`restore`) is exactly the state the
workers were last told about. The server does this when it starts; the engine does it when
applying a batch raised (``osmo.server.engine``), to drop the half-applied batch from memory.

Quarantine: the engine applies the final reports (exits and start failures: the reports
that carry a task's outputs and messages into the server) that arrived together in one
transaction, writing their ids to ``OSMO_HOME/applying.json`` (:class:`InFlight`) before and
emptying the file once it is committed. A file still holding ids when a server starts means
the previous server died while applying those reports: a crash no exception handler saw (a
segfault, the kernel's OOM killer), or a ``kill -9`` from outside at that very instant, which
nothing tells apart. The first time, the task is given the benefit of the doubt: its attempt
is recovered like any other lost one (run again as a new retry) and the crash is counted in
``OSMO_HOME/crashes.json`` (:meth:`InFlight.strike`). From then on a report of that task is
applied in a transaction of its own (:meth:`InFlight.suspect`), so that a second crash names
it alone. If a server dies again while applying a report of the same task, that attempt is
failed with :data:`QUARANTINED` instead of being run again, so one task cannot crash a server
over and over; ``osmo restart`` runs it again once its cause is fixed. The files are written
without fsync: a process crash leaves the page cache intact, and a power cut is no attempt's
fault.

Must not run tasks or talk to workers; it only reads the store and that one file.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from osmo.layout import Home
from osmo.runtime.process.proctable import kill_stale
from osmo.scheduler import Scheduler, TaskState, WorkflowState
from osmo.scheduler.types import AttemptExited, AttemptStartFailed, Event
from osmo.spec.model import WorkflowSpec
from osmo.status import TaskStatus
from osmo.store.sqlite import AttemptRow, Store

__all__ = ["QUARANTINED", "InFlight", "Restored", "attempt_row", "kill_leftovers",
           "quarantine", "restore", "split_lost"]

log = logging.getLogger("osmo.server")

QUARANTINED = ("quarantined: the server stopped while applying this attempt's report (its "
               "outputs or message may be what crashed it), so it is not run again; check "
               "its outputs, then `osmo restart` the workflow")
"""The message of an attempt failed by :func:`quarantine`."""


@dataclass
class Restored:
    """A scheduler rebuilt from the store.

    Attributes:
        scheduler: holds every unfinished workflow; active attempts keep their reservations.
        specs: workflow id → spec of each unfinished workflow.
        reuse: id → True for those submitted with ``--reuse``, False with ``--no-cache``.
        active: tasks whose attempt was placed or running when the state was committed.
    """

    scheduler: Scheduler
    specs: dict[str, WorkflowSpec] = field(default_factory=dict)
    reuse: dict[str, bool] = field(default_factory=dict)
    active: list[TaskState] = field(default_factory=list)


def restore(store: Store) -> Restored:
    """Build a scheduler holding the store's unfinished workflows.

    Raises:
        InfrastructureError: the store cannot be read.
    """
    out = Restored(Scheduler())  # its default cap: for states saved without one
    workflows, tasks = [], []
    for listed in store.workflows(active_only=True):
        row = store.workflow(listed.id)
        if row is None:
            continue
        if row.options.reuses is not None:
            out.reuse[row.id] = row.options.reuses
        out.specs[row.id] = row.spec.load()
        workflows.append(WorkflowState.from_dict(row.state))
        tasks += [TaskState.from_dict(t) for t in store.tasks(row.id)]
    out.scheduler.restore(out.specs, workflows, tasks)
    out.active = [t for t in tasks if t.status.active and t.attempt_id]
    return out


def split_lost(active: list[TaskState]) -> tuple[list[TaskState], set[str]]:
    """Split restored active attempts into the local pool's and remote nodes.

    The local pool's were lost with the old server; the workers of remote ones keep running and are
    expected back.
    """
    local = [t for t in active if (t.node_id or "local") == "local"]
    remote = {t.node_id for t in active if t.node_id and t.node_id != "local"}
    return local, remote


def kill_leftovers(store: Store, lost: list[TaskState]) -> None:
    """Kill what still runs of the old server's local attempts (checked by pid start time)."""
    for task in lost:
        for row in store.attempts(task.workflow_id, task.name):
            if row.id == task.attempt_id and row.pid and row.pid_start is not None:
                kill_stale(row.pid, row.pid_start)


def attempt_row(home: Home, attempt_id: str, node_id: str | None) -> AttemptRow:
    """The store's row of a placed attempt: where it runs and, locally, its folder.

    Its process id is written when the attempt starts (``Batch.pids``).
    """
    dirs = home.attempt_of(attempt_id)
    wf, task, retry = attempt_id.rsplit(":", 2)
    return AttemptRow(attempt_id, wf, task, int(retry), node_id,
                      str(dirs.root) if dirs else None, None, None)


def quarantine(active: list[TaskState], suspects: set[str]) -> tuple[list[TaskState],
                                                                    list[Event]]:
    """Split restored active attempts into those to recover and failures for the suspects.

    Returns:
        the tasks whose attempt was not being applied, and one final report per suspect
        (an ``AttemptExited`` with no output for a running attempt: FAILED, exit code 3005;
        ``AttemptStartFailed`` for one still starting), each carrying :data:`QUARANTINED`.
    """
    keep: list[TaskState] = []
    failures: list[Event] = []
    for task in active:
        aid = task.attempt_id
        if aid is None or aid not in suspects:
            keep.append(task)
            continue
        log.error("attempt %s: %s", aid, QUARANTINED)
        if task.status is TaskStatus.RUNNING:
            failures.append(AttemptExited(aid, 0, None, QUARANTINED))
        else:
            failures.append(AttemptStartFailed(aid, QUARANTINED))
    return keep, failures


class InFlight:
    """``OSMO_HOME/applying.json``: ids of the attempts whose reports are being applied.

    Args:
        path: the file; created if missing. What an earlier server left in it is kept in
            :attr:`left` before the file is emptied.
        crashes: the file counting, per task, the servers that died applying its reports
            (default: ``crashes.json`` beside ``path``).
    """

    def __init__(self, path: Path, crashes: Path | None = None) -> None:
        self.path = Path(path)
        self.crashes = Path(crashes) if crashes else self.path.with_name("crashes.json")
        self.left: set[str] = _read_ids(self.path)
        self._struck = set(_read_counts(self.crashes))  # tasks a server already died on
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        self._dirty = True
        self.clear()

    def strike(self, attempt_ids: set[str]) -> set[str]:
        """Count a crash against each attempt's task; the attempts to quarantine.

        Returns:
            the attempts whose task a server had already died on once before (their second
            strike); the others are to be recovered as lost attempts.
        """
        counts = _read_counts(self.crashes)
        repeat = set()
        for aid in sorted(attempt_ids):
            task = aid.rsplit(":", 1)[0]  # workflow:task, the same for every retry
            counts[task] = counts.get(task, 0) + 1
            if counts[task] > 1:
                repeat.add(aid)
            else:
                log.warning("attempt %s: a server died while applying its report; it runs "
                            "again (a second such crash quarantines the task)", aid)
        self._struck |= set(counts)
        if attempt_ids:
            tmp = self.crashes.with_suffix(".tmp")
            tmp.write_text(json.dumps(counts))
            os.chmod(tmp, 0o600)
            tmp.replace(self.crashes)
        return repeat

    def suspect(self, attempt_id: str) -> bool:
        """Whether a server already died applying a report of ``attempt_id``'s task.

        The engine applies such a report on its own, so that a second crash is this task's
        alone (the first one may have hit a batch of many tasks' reports).
        """
        return attempt_id.rsplit(":", 1)[0] in self._struck

    def mark(self, attempt_ids: list[str]) -> None:
        """Note the attempts about to be applied (replaces what was there)."""
        self.clear()  # first: a crash between the two calls leaves an empty file, not a torn one
        os.pwrite(self._fd, json.dumps(attempt_ids).encode(), 0)
        self._dirty = True

    def clear(self) -> None:
        """Nothing is being applied any more."""
        if self._dirty:
            os.ftruncate(self._fd, 0)
            self._dirty = False

    def close(self) -> None:
        """Close the file (it stays, empty)."""
        os.close(self._fd)


def _read_counts(path: Path) -> dict[str, int]:
    try:
        data = json.loads(path.read_bytes() or b"{}")
    except FileNotFoundError:
        return {}
    except ValueError:  # torn: start counting again
        return {}
    if not isinstance(data, dict):
        return {}
    return {str(k): int(v) for k, v in data.items() if isinstance(v, int)}


def _read_ids(path: Path) -> set[str]:
    try:
        data = json.loads(path.read_bytes() or b"[]")
    except FileNotFoundError:
        return set()
    except ValueError:  # torn by a crash mid-write: nothing trustworthy in it
        log.warning("%s is unreadable; no attempt is quarantined", path)
        return set()
    return {str(a) for a in data} if isinstance(data, list) else set()
