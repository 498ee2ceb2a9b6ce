"""A real osmo server with one fault injected, for the engine's fault-isolation tests.

Run as ``python -m tests.hostile.faulty_server --home HOME`` with ``OSMO_FAULT`` set:

- ``commit:TASK``   the state store refuses (raises) every commit that records TASK's outputs
- ``apply:TASK``    building TASK's lineage raises (a bug in the engine's own code path)
- ``crash:TASK``    the process kills itself (SIGKILL) while committing TASK's outputs
- ``store:FILE``    once FILE exists, every store transaction fails (the database is gone)
- ``batch:PHASE:N:MARKER``  the process kills itself (SIGKILL) the first time a commit records
  the outputs of N or more tasks at once: ``before`` the transaction, ``during`` it (after its
  first lineage row) or ``after`` its commit (before any command of the batch leaves). MARKER
  is created first, so that only one server of a test is killed. To make reports arrive
  together, the engine waits 1 s after the first final report it takes before it takes the
  rest.
- ``spawn:WORD:MARKER``  the process kills itself (SIGKILL) right after its pool spawned a
  command whose argv holds WORD, before the start is reported (MARKER as above: once per
  test).

Everything else is the real server (``osmo.server.app.main``).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

from osmo.errors import InfrastructureError
from osmo.scheduler.types import AttemptExited
from osmo.server import app, inbox, provenance
from osmo.store import sqlite
from osmo.worker import starts


def _inject(kind: str, arg: str) -> None:
    if kind in ("commit", "crash"):
        commit = sqlite.Store.commit

        def faulty_commit(self: sqlite.Store, changes: Any, **kw: Any) -> None:
            if any(row.task == arg for row in kw.get("lineage") or ()):
                if kind == "crash":
                    os.kill(os.getpid(), signal.SIGKILL)
                raise InfrastructureError(f"injected: the store refuses {arg}'s outputs")
            commit(self, changes, **kw)

        sqlite.Store.commit = faulty_commit  # type: ignore[method-assign]
    elif kind == "apply":
        exited = provenance.Provenance.exited

        def faulty_exited(self: provenance.Provenance, event: Any, task: Any,
                          **kw: Any) -> Any:
            if task.name == arg:
                raise RuntimeError(f"injected: lineage of {arg} cannot be built")
            return exited(self, event, task, **kw)

        provenance.Provenance.exited = faulty_exited  # type: ignore[method-assign]
    elif kind == "batch":
        _batch_kill(*arg.split(":", 2))
    elif kind == "spawn":
        word, marker = arg.split(":", 1)
        spawn = starts.Starting.spawn

        def dying_spawn(self: starts.Starting, runtime: Any, launch: Any) -> Any:
            handle = spawn(self, runtime, launch)
            if any(word in str(item) for item in launch.argv):
                _die_once(marker)
            return handle

        starts.Starting.spawn = dying_spawn  # type: ignore[method-assign]
    elif kind == "store":
        tx, read = sqlite.Store._tx, sqlite.Store._read

        def gone(self: sqlite.Store) -> None:
            if Path(arg).exists():
                raise InfrastructureError(f"state store {self.path}: disk I/O error (injected)")

        def faulty_tx(self: sqlite.Store) -> Any:
            gone(self)
            return tx(self)

        def faulty_read(self: sqlite.Store, sql: str, args: tuple[Any, ...] = ()) -> Any:
            gone(self)
            return read(self, sql, args)

        sqlite.Store._tx = faulty_tx  # type: ignore[method-assign]
        sqlite.Store._read = faulty_read  # type: ignore[method-assign]


def _die_once(marker: str) -> None:
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return  # an earlier server of this test was killed already
    os.kill(os.getpid(), signal.SIGKILL)


def _batch_kill(phase: str, least: str, marker: str) -> None:
    assert phase in ("before", "during", "after"), phase
    commit, take, write_lineage = sqlite.Store.commit, inbox.Inbox.take, sqlite.write_lineage
    armed: list[bool] = []

    def faulty_commit(self: sqlite.Store, changes: Any, **kw: Any) -> None:
        big = len(kw.get("lineage") or ()) >= int(least)
        if big and phase == "before":
            _die_once(marker)
        armed[:] = [big and phase == "during"]
        commit(self, changes, **kw)
        if big and phase == "after":
            _die_once(marker)

    def faulty_write_lineage(db: Any, row: Any) -> None:
        write_lineage(db, row)
        if armed and armed[0]:
            _die_once(marker)  # mid-transaction: one lineage row written, not committed

    def gathering_take(self: inbox.Inbox, timeout: float | None) -> list[Any]:
        items = take(self, timeout)
        if any(isinstance(i, AttemptExited) for i in items):
            time.sleep(1.0)  # let the other exits arrive: they are applied together
            items += take(self, 0)
        return items

    sqlite.Store.commit = faulty_commit  # type: ignore[method-assign]
    sqlite.write_lineage = faulty_write_lineage  # type: ignore[assignment]
    inbox.Inbox.take = gathering_take  # type: ignore[method-assign]


if __name__ == "__main__":
    fault_kind, _, fault_arg = os.environ["OSMO_FAULT"].partition(":")
    _inject(fault_kind, fault_arg)
    app.main()
