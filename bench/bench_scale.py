"""Scale: a 100,000-task fan-out through a real server, and reads on a store of many workflows.

Rows (median of ``--runs`` fresh servers; issue 16's targets in brackets):

- **submit of an N-task fan-out** [≤ 10 s for 100,000]: ``Client.submit`` of a spec built
  beforehand (the SDK builder's own time is its own row), until the server has committed the
  workflow and answered.
- **server CPU for the submit**: user + system seconds the server process spent from the
  request to the answer (from /proc), which the machine's other load changes little.
- **SDK builder for an N-task fan-out**: ``osmo.Workflow(...).build()``, on the client.
- **query of the running N-task workflow** [≤ 1 s]: what ``osmo query`` asks (``Client.get``
  with ``limit=1000``: the first 1,000 tasks and the count per status), right after the
  submit, while it runs; and ``osmo query`` itself (a new CLI process, its start included).
- **every task of the running N-task workflow**: ``Client.get`` with no limit (the SDK can
  still fetch them all; ~30 MB of JSON for 100,000).
- **server RSS with the N-task workflow** [≤ 1 GiB]: after the submit, from /proc.
- **list / query with M finished workflows in the store** [≤ 200 ms]: ``Client.list``
  (20 rows) and ``Client.get`` of one of them, after M one-task workflows completed.

The fan-out is cancelled once measured (running 100,000 ``true`` tasks is bench_engine's
job). Usage: python bench/bench_scale.py [--runs 3] [--tasks 100000] [--finished 10000]
[--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_engine import fan_out  # noqa: E402
from benchlib import quick, row, write_rows  # noqa: E402

import osmo  # noqa: E402
from osmo.cli.render import QUERY_LIMIT  # noqa: E402
from osmo.layout import Home  # noqa: E402
from osmo.sdk.connect import start_server, stop_server  # noqa: E402


def _server_pid(home: str) -> int:
    return int(json.loads(Home(Path(home)).server_info.read_text())["pid"])


def _rss_mib(home: str) -> float:
    status = Path(f"/proc/{_server_pid(home)}/status").read_text()
    return int(status.split("VmRSS:")[1].split()[0]) / 1024


def _cpu_s(home: str) -> float:
    """User + system CPU seconds of the server process so far."""
    fields = Path(f"/proc/{_server_pid(home)}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def big_fan_out(n: int) -> dict[str, list[float]]:
    """One run: build, submit, query and RSS of an n-task fan-out on a fresh server."""
    out: dict[str, list[float]] = {}
    t0 = time.perf_counter()
    spec = fan_out(n).build()
    out["build"] = [time.perf_counter() - t0]
    with tempfile.TemporaryDirectory(prefix="osmo-bench-") as home:
        start_server(home)
        try:
            with osmo.Client(home=home) as client:
                cpu, t0 = _cpu_s(home), time.perf_counter()
                wf = client.submit(spec, no_cache=True)
                out["submit"] = [time.perf_counter() - t0]
                out["server_cpu"] = [_cpu_s(home) - cpu]
                out["rss"] = [_rss_mib(home)]
                t0 = time.perf_counter()
                client.get(wf, limit=QUERY_LIMIT)
                out["query"] = [time.perf_counter() - t0]
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "osmo", "query", wf], check=True,
                               env=dict(os.environ, OSMO_HOME=home), stdout=subprocess.DEVNULL)
                out["cli"] = [time.perf_counter() - t0]
                t0 = time.perf_counter()
                client.get(wf)
                out["query_all"] = [time.perf_counter() - t0]
                client.cancel(wf)
        finally:
            stop_server(home)
    return out


def many_finished(m: int) -> dict[str, list[float]]:
    """List and query latency with m finished one-task workflows in the store."""
    one = osmo.Workflow("done")
    one.task("t", ["true"])
    spec = one.build()
    with tempfile.TemporaryDirectory(prefix="osmo-bench-") as home:
        start_server(home)
        try:
            with osmo.Client(home=home) as client:
                ids = [client.submit(spec, no_cache=True) for _ in range(m)]
                client.wait(ids[-1])
                for wf in ids[:-1]:
                    client.wait(wf)
                lists, gets = [], []
                for i in range(7):
                    t0 = time.perf_counter()
                    client.list(limit=20)
                    lists.append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    client.get(ids[(i * 997) % m])
                    gets.append(time.perf_counter() - t0)
        finally:
            stop_server(home)
    return {"list": lists, "get": gets}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=100_000)
    parser.add_argument("--finished", type=int, default=10_000)
    parser.add_argument("--json")
    args = parser.parse_args()
    if quick():
        args.runs, args.tasks, args.finished = 1, 2_000, 50
    runs: dict[str, list[float]] = {}
    for _ in range(args.runs):
        for key, values in big_fan_out(args.tasks).items():
            runs.setdefault(key, []).extend(values)
    n = f"{args.tasks:,}"
    rows = [
        row(f"SDK builder: {n}-task fan-out", "s", runs["build"], higher_is_better=False),
        row(f"submit: {n}-task fan-out", "s", runs["submit"], higher_is_better=False,
            target=10.0 if args.tasks >= 100_000 else None),
        row(f"server CPU for the submit: {n}-task fan-out", "s", runs["server_cpu"],
            higher_is_better=False, notes="user + system seconds of the server process"),
        row(f"query: running {n}-task workflow", "s", runs["query"], higher_is_better=False,
            target=1.0 if args.tasks >= 100_000 else None,
            notes=f"Client.get(limit={QUERY_LIMIT:,}), what `osmo query` asks"),
        row(f"osmo query (CLI process): running {n}-task workflow", "s", runs["cli"],
            higher_is_better=False, notes="a new CLI process: interpreter start included"),
        row(f"query, every task: running {n}-task workflow", "s", runs["query_all"],
            higher_is_better=False, notes="Client.get() with no limit"),
        row(f"server RSS: {n}-task workflow", "MiB", runs["rss"], higher_is_better=False,
            target=1024.0 if args.tasks >= 100_000 else None),
    ]
    finished = many_finished(args.finished)
    m = f"{args.finished:,}"
    rows += [
        row(f"list (20 rows): {m} finished workflows", "ms",
            [v * 1000 for v in finished["list"]], higher_is_better=False,
            target=200.0 if args.finished >= 10_000 else None),
        row(f"query: one of {m} finished workflows", "ms",
            [v * 1000 for v in finished["get"]], higher_is_better=False,
            target=200.0 if args.finished >= 10_000 else None),
    ]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
