"""A real osmo server with one fault injected, for the engine's fault-isolation tests.

Run as ``python -m tests.hostile.faulty_server --home HOME`` with ``OSMO_FAULT`` set:

- ``commit:TASK``   the state store refuses (raises) every commit that records TASK's outputs
- ``apply:TASK``    building TASK's lineage raises (a bug in the engine's own code path)
- ``crash:TASK``    the process kills itself (SIGKILL) while committing TASK's outputs
- ``store:FILE``    once FILE exists, every store transaction fails (the database is gone)

Everything else is the real server (``osmo.server.app.main``).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

from osmo.errors import InfrastructureError
from osmo.server import app, provenance
from osmo.store import sqlite


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


if __name__ == "__main__":
    fault_kind, _, fault_arg = os.environ["OSMO_FAULT"].partition(":")
    _inject(fault_kind, fault_arg)
    app.main()
