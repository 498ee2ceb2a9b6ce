"""Engine throughput: 1,000 `true` tasks end to end through a real server with durable state.

Shapes: fan-out/join (1 source → 998 parallel → 1 join) and a 1,000-task chain. Each is
submitted through the SDK to a fresh server (own OSMO_HOME, SQLite WAL) and timed from
submit to the workflow's COMPLETED. Prints the median of N runs (min/max), tasks/s and
per-task overhead, plus the "limit": spawning `true` as many times with the same
parallelism and no orchestrator.

Usage: python bench/bench_engine.py [--runs 3] [--tasks 1000] [--base DIR] [--json out.json]

The numbers depend heavily on the filesystem under the homes (each attempt makes folders
and renames its output): the script prints the median mkdir cost there. Compare with
``--base /dev/shm`` (tmpfs) to see the engine without the disk.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import osmo  # noqa: E402
from osmo.sdk.connect import start_server, stop_server  # noqa: E402


def fan_out(n: int) -> osmo.Workflow:
    wf = osmo.Workflow("bench-fanout")
    wf.task("source", ["true"])
    middle = [f"m{i}" for i in range(n - 2)]
    for name in middle:
        wf.task(name, ["true"], inputs=["source"])
    wf.task("join", ["true"], inputs=middle)
    return wf


def chain(n: int) -> osmo.Workflow:
    wf = osmo.Workflow("bench-chain")
    wf.task("t0", ["true"])
    for i in range(1, n):
        wf.task(f"t{i}", ["true"], inputs=[f"t{i - 1}"])
    return wf


def run_once(spec: osmo.WorkflowSpec, base: str | None) -> float:
    with tempfile.TemporaryDirectory(prefix="osmo-bench-", dir=base) as home:
        start_server(home)
        try:
            with osmo.Client(home=home) as client:
                t0 = time.perf_counter()
                result = client.wait(client.submit(spec))
                elapsed = time.perf_counter() - t0
                if not result.ok:
                    raise SystemExit(f"benchmark workflow ended {result.status.name}")
        finally:
            stop_server(home)
    os.sync()  # flush this run's writeback now, not during the next run
    return elapsed


def spawn_limit(n: int, parallel: int) -> float:
    t0 = time.perf_counter()
    with ThreadPoolExecutor(parallel) as pool:
        list(pool.map(lambda _i: subprocess.run(["true"], check=True), range(n)))
    return time.perf_counter() - t0


def mkdir_us(base: str | None, n: int = 500) -> float:
    """Median cost of one mkdir where the homes live: attempt folders are mostly this."""
    with tempfile.TemporaryDirectory(dir=base) as d:
        times = []
        for i in range(n):
            t0 = time.perf_counter()
            os.mkdir(f"{d}/{i}")
            times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def machine() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{platform.system()} {platform.release()}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=1000)
    parser.add_argument("--json")
    parser.add_argument("--base", help="folder for the OSMO_HOMEs (default: system temp)")
    args = parser.parse_args()
    print(f"machine: {machine()}")
    print(f"homes under {args.base or tempfile.gettempdir()}: mkdir {mkdir_us(args.base):.0f} µs")
    cores = os.cpu_count() or 1
    results = {}
    limit = [spawn_limit(args.tasks, cores) for _ in range(args.runs)]
    shapes = {"fan-out/join": fan_out(args.tasks).build(), "chain": chain(args.tasks).build()}
    for name, spec in shapes.items():
        times = [run_once(spec, args.base) for _ in range(args.runs)]
        med = statistics.median(times)
        results[name] = {"median_s": med, "min_s": min(times), "max_s": max(times),
                         "tasks_per_s": args.tasks / med, "per_task_ms": 1000 * med / args.tasks}
        print(f"{name:14s} {args.tasks} tasks: median {med:.2f}s (min {min(times):.2f}, "
              f"max {max(times):.2f}) → {args.tasks / med:.0f} tasks/s, "
              f"{1000 * med / args.tasks:.2f} ms/task")
    lim = statistics.median(limit)
    results["spawn-limit"] = {"median_s": lim, "tasks_per_s": args.tasks / lim}
    print(f"{'limit':14s} spawn `true` x{args.tasks}, {cores} parallel, no orchestrator: "
          f"{lim:.2f}s → {args.tasks / lim:.0f}/s")
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"machine": machine(), "base": args.base, **results}, indent=2))


if __name__ == "__main__":
    main()
