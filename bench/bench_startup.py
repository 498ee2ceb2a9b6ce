"""Start-up latency: submit → first task running, and an auto-started server's first answer.

Rows, each the median of N runs (min/max):

- **submit → first task running (SDK)** — a connected ``osmo.Client`` submits a 1-task
  workflow to a server that is already up. The task's command is ``date +%s.%N`` into its
  output, so the end point is the moment the task's own process runs, read from the same
  clock as the start point (CLOCK_REALTIME: ``time.time()`` in this process, ``date`` in the
  task; both on this host). Includes validating the spec, the request over zenoh, the
  commit, placement, the attempt folder and the spawn. Target ≤ 100 ms.
- **submit → first task running (CLI)** — the same, starting just before ``osmo submit
  FILE`` is spawned as a new process: adds the interpreter, osmo's imports and opening a
  zenoh session.
- **auto-started server ready (CLI)** — ``osmo list`` with no server running for a fresh
  OSMO_HOME, from spawn until the process exits with the answer: the CLI starts the server
  in the background and waits until it answers. Target ≤ 1.5 s.
- Breakdown rows: ``osmo --help`` (a CLI process that calls no server) and
  ``start_server`` from the SDK (server process until ready).

Each measured run uses a distinct workflow and ``--no-cache``; one warm-up submission per
server is not counted.

Usage: python bench/bench_startup.py [--runs 7] [--base DIR] [--json out.json]
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import quick, row, write_rows  # noqa: E402

import osmo  # noqa: E402
from osmo.sdk.connect import start_server, stop_server  # noqa: E402

STAMP = ["sh", "-c", "date +%s.%N > {{output}}/started"]


def cli() -> list[str]:
    """The ``osmo`` console script of this interpreter's environment (else ``-m osmo``)."""
    script = Path(sys.executable).with_name("osmo")
    return [str(script)] if script.exists() else [sys.executable, "-m", "osmo"]


def cli_env(home: str) -> dict[str, str]:
    """This environment, pointed at ``home``, with no server override."""
    env = dict(os.environ, OSMO_HOME=home)
    env.pop("OSMO_SERVER", None)
    return env


def one_task(i: int) -> osmo.Workflow:
    """A 1-task workflow that records when its process ran."""
    wf = osmo.Workflow(f"startup-{i}")
    wf.task("stamp", STAMP)
    return wf


def task_started(client: osmo.Client, wf_id: str) -> tuple[float, float]:
    """Wait for the workflow; (task's own timestamp, server's RUNNING time)."""
    info = client.wait(wf_id, min_interval=0.01)
    task = info.task("stamp")
    if not info.ok or task.output is None:
        raise SystemExit(f"start-up workflow {wf_id} ended {info.status.name}: {task.message}")
    stamp = float((Path(task.output) / "started").read_text())
    return stamp, task.started_at or float("nan")


def submit_latency(home: str, runs: int) -> tuple[list[float], list[float], list[float]]:
    """(SDK submit → task ran, server's view of the same, CLI submit → task ran), ms."""
    sdk, server_view, via_cli = [], [], []
    with osmo.Client(home=home) as client:
        task_started(client, client.submit(one_task(-1), no_cache=True))  # warm-up
        with tempfile.NamedTemporaryFile("w", suffix=".yaml", dir=home, delete=False) as f:
            f.write("workflow:\n  name: startup-cli\n  tasks:\n  - name: stamp\n"
                    f"    command: {json.dumps(STAMP)}\n")
        for i in range(runs):
            spec = one_task(i)
            t0 = time.time()
            wf_id = client.submit(spec, no_cache=True)
            stamp, started = task_started(client, wf_id)
            sdk.append((stamp - t0) * 1000)
            server_view.append((started - t0) * 1000)
            t0 = time.time()
            proc = subprocess.run([*cli(), "submit", f.name, "--no-cache", "--format", "json"],
                                  env=cli_env(home), capture_output=True, text=True, check=True)
            stamp, _ = task_started(client, json.loads(proc.stdout)["workflow_id"])
            via_cli.append((stamp - t0) * 1000)
    return sdk, server_view, via_cli


def autostart(base: str | None) -> tuple[float, float]:
    """Seconds for `osmo list` to answer with no server (it starts one), and for start_server."""
    with tempfile.TemporaryDirectory(prefix="osmo-bench-", dir=base) as home:
        t0 = time.perf_counter()
        subprocess.run([*cli(), "list", "--format", "json"], env=cli_env(home),
                       capture_output=True, check=True)
        ready = time.perf_counter() - t0
        stop_server(home)
    with tempfile.TemporaryDirectory(prefix="osmo-bench-", dir=base) as home:
        t0 = time.perf_counter()
        start_server(home)
        sdk = time.perf_counter() - t0
        stop_server(home)
    return ready, sdk


def main() -> None:
    """Measure every start-up row and write them."""
    small = quick()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2 if small else 7)
    ap.add_argument("--base", help="folder for the OSMO_HOMEs (default: system temp)")
    ap.add_argument("--json")
    args = ap.parse_args()
    helps, readies, starts = [], [], []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        subprocess.run([*cli(), "--help"], capture_output=True, check=True)
        helps.append(time.perf_counter() - t0)
        ready, start = autostart(args.base)
        readies.append(ready)
        starts.append(start)
    with tempfile.TemporaryDirectory(prefix="osmo-bench-", dir=args.base) as home:
        start_server(home)
        try:
            sdk, server_view, via_cli = submit_latency(home, args.runs)
        finally:
            stop_server(home)
    rows = [
        row("startup: submit → first task running (SDK)", "ms", sdk, higher_is_better=False,
            target=100.0, notes="task's own `date` vs time.time() before submit; "
            f"server-recorded RUNNING: median {sorted(server_view)[len(server_view) // 2]:.1f} ms"),
        row("startup: submit → first task running (CLI `osmo submit`)", "ms", via_cli,
            higher_is_better=False, target=100.0,
            notes="new `osmo submit` process; includes interpreter, imports, zenoh session"),
        row("startup: auto-started server ready (CLI, no server running)", "s", readies,
            higher_is_better=False, target=1.5,
            notes="`osmo list` on a fresh OSMO_HOME: spawn → answered, server started by it"),
        row("startup: breakdown: `osmo --help` process (no server call)", "s", helps,
            higher_is_better=False),
        row("startup: breakdown: SDK start_server until ready", "s", starts,
            higher_is_better=False),
    ]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
