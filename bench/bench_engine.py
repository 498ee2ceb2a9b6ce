"""Engine throughput: `true` tasks end to end through a real server with durable state.

Shapes: fan-out/join (1 source → N-2 parallel → 1 join) of 1,000 and of 10,000 tasks, and a
1,000-task chain. Each run submits through the SDK to a fresh server (own OSMO_HOME, SQLite
WAL; the server is started before the clock starts) and times from ``submit`` to the
workflow's COMPLETED. The rounds alternate the shapes, so a noisy minute hits all of them.
Every task requests 1 cpu, so on 2 cores 2 run at once. Submitted with ``no_cache``: the
``true`` tasks of a shape have identical definitions and inputs, so with caching on all but
the first few would complete as cache hits without running. The limit these rows are compared
with is bench_limits.py's spawn row (spawning ``true`` with the same parallelism and no
orchestrator). Each shape also gets a row of the server process's own CPU time per task
(utime + stime from ``/proc/<pid>/stat``, from submit to COMPLETED; the tasks' processes are
its children and not counted): on a shared machine a steadier figure than tasks/s.

Usage: python bench/bench_engine.py [--runs 3] [--tasks 1000] [--big 10000] [--base DIR]
       [--json out.json]

The numbers depend on the filesystem under the homes (each attempt makes folders and renames
its output): a row gives the median mkdir cost there. ``--base /dev/shm`` (tmpfs) shows the
engine without the disk.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import quick, row, write_rows  # noqa: E402

import osmo  # noqa: E402
from osmo.options import ServerOptions  # noqa: E402
from osmo.sdk.connect import start_server, stop_server  # noqa: E402

SPAWN_LIMIT = "limit: spawn `true`, 2 parallel, no orchestrator"


def fan_out(n: int) -> osmo.Workflow:
    """1 source task, n-2 parallel tasks that read it, 1 join task that reads them all."""
    wf = osmo.Workflow("bench-fanout")
    wf.task("source", ["true"])
    middle = [f"m{i}" for i in range(n - 2)]
    for name in middle:
        wf.task(name, ["true"], inputs=["source"])
    wf.task("join", ["true"], inputs=middle)
    return wf


def chain(n: int) -> osmo.Workflow:
    """n tasks, each reading the previous one's output."""
    wf = osmo.Workflow("bench-chain")
    wf.task("t0", ["true"])
    for i in range(1, n):
        wf.task(f"t{i}", ["true"], inputs=[f"t{i - 1}"])
    return wf


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system) process ``pid`` used so far, its children not counted."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_once(spec: osmo.WorkflowSpec, base: str | None,
             options: ServerOptions | None = None) -> float:
    """Seconds from submit to COMPLETED on a fresh server (started before the clock)."""
    return run_measured(spec, base, options)[0]


def run_measured(spec: osmo.WorkflowSpec, base: str | None,
                 options: ServerOptions | None = None) -> tuple[float, float]:
    """:func:`run_once`'s seconds, and the server's CPU seconds over that time."""
    with tempfile.TemporaryDirectory(prefix="osmo-bench-", dir=base) as home:
        pid = start_server(home, options).pid
        try:
            with osmo.Client(home=home) as client:
                cpu0, t0 = cpu_seconds(pid), time.perf_counter()
                result = client.wait(client.submit(spec, no_cache=True))
                elapsed, cpu = time.perf_counter() - t0, cpu_seconds(pid) - cpu0
                if not result.ok:
                    raise SystemExit(f"benchmark workflow ended {result.status.name}")
        finally:
            stop_server(home)
    os.sync()  # flush this run's writeback now, not during the next run
    return elapsed, cpu


def mkdir_us(base: str | None, n: int = 500) -> list[float]:
    """Cost of each mkdir where the homes live (attempt folders are mostly this), in µs."""
    with tempfile.TemporaryDirectory(dir=base) as d:
        times = []
        for i in range(n):
            t0 = time.perf_counter()
            os.mkdir(f"{d}/{i}")
            times.append((time.perf_counter() - t0) * 1e6)
    return times


def main() -> None:
    """Run every shape ``--runs`` times (alternating) and write the rows."""
    small = quick()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if small else 3)
    parser.add_argument("--tasks", type=int, default=20 if small else 1000)
    parser.add_argument("--big", type=int, default=60 if small else 10_000)
    parser.add_argument("--json")
    parser.add_argument("--base", help="folder for the OSMO_HOMEs (default: system temp)")
    args = parser.parse_args()
    where = args.base or tempfile.gettempdir()
    shapes = {  # name -> (spec, tasks); a --big equal to --tasks is the same shape, once
        f"osmo fan-out/join {args.tasks:,} `true` tasks": (fan_out(args.tasks).build(), args.tasks),
        f"osmo chain {args.tasks:,} `true` tasks": (chain(args.tasks).build(), args.tasks),
        f"osmo fan-out/join {args.big:,} `true` tasks": (fan_out(args.big).build(), args.big),
    }
    times: dict[str, list[float]] = {name: [] for name in shapes}
    cpus: dict[str, list[float]] = {name: [] for name in shapes}
    mkdirs: list[float] = []
    for _ in range(args.runs):
        mkdirs.append(statistics.median(mkdir_us(args.base)))
        for name, (spec, _) in shapes.items():
            elapsed, cpu = run_measured(spec, args.base)
            times[name].append(elapsed)
            cpus[name].append(cpu)
    rows = [row(f"filesystem: mkdir under {where}", "µs", mkdirs, higher_is_better=False,
                notes="attempt folders cost mostly this; a slow disk moment shows here")]
    for name, runs in times.items():
        n = shapes[name][1]
        rows.append(row(name, "tasks/s", [n / t for t in runs], higher_is_better=True,
                        limit_of=SPAWN_LIMIT,
                        notes=f"submit→COMPLETED median {statistics.median(runs):.2f} s, "
                              f"{1000 * statistics.median(runs) / n:.2f} ms/task"))
        rows.append(row(f"{name}: server CPU", "ms/task", [1000 * c / n for c in cpus[name]],
                        higher_is_better=False,
                        notes="the server process's user+system time, submit→COMPLETED"))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
