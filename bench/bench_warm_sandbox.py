"""One ``sim.rollout`` start in the sandbox: warm (a fork of a sandboxed runner) against cold.

Through the sandboxed process runtime alone (``osmo.runtime.process.sandboxed``), as root:
each attempt is prepared as the pool prepares it, then timed from ``start`` to its exit
(a one-episode, 20-step InvertedPendulum rollout: the import is most of a cold start).
Warm and cold attempts alternate; the first warm one (the runner's import) is not counted.

Rows: the warm and the cold start, medians of ``--runs`` (8; 1 with ``OSMO_BENCH_QUICK=1``),
and cold ÷ warm. A non-root run writes no rows (its sandboxed attempts start cold).

Usage (as root, from the repository): python bench/bench_warm_sandbox.py [--runs 8] [--json F]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import selectors
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchlib import quick, row, write_rows  # noqa: E402

from osmo.layout import AttemptDirs  # noqa: E402
from osmo.runtime.api import Attempt, Launch  # noqa: E402
from osmo.runtime.process.sandbox import choose, node_network  # noqa: E402
from osmo.runtime.process.sandboxed import SandboxRuntime  # noqa: E402
from osmo.runtime.process.warm import WarmRunners, WarmStart  # noqa: E402
from osmo.scheduler.types import PrepareAttempt  # noqa: E402
from osmo.spec.model import ResolvedType, TaskSpec  # noqa: E402
from osmo.worker.taskenv import base_env  # noqa: E402
from osmo.worker.workdir import prepare  # noqa: E402


def _launch(runtime: SandboxRuntime, home: Path, name: str, warm: bool) -> Launch:
    task = TaskSpec(name, type="sim.rollout", params={"episodes": 1, "max_steps": 20},
                    warm=None if warm else False, resolved=ResolvedType("2"))
    cmd = PrepareAttempt(f"wf:{name}:0", "wf", name, 0, "bench", {}, {})
    dirs = AttemptDirs(home / "wf" / name / "0")
    made = prepare(dirs, cmd, task, base_env(os.environ), {}, paths=runtime.paths(cmd))
    return runtime.prepare(made, Attempt(cmd, task, dirs), progress=lambda _: None)


def _run(runtime: SandboxRuntime, launch: Launch) -> float:
    began = time.perf_counter()
    handle = runtime.start(launch)
    with selectors.DefaultSelector() as sel:
        sel.register(handle.exit_fd, selectors.EVENT_READ)
        for fd in (handle.stdout_fd, handle.stderr_fd):
            sel.register(fd, selectors.EVENT_READ)
        done = False
        while not done:
            for key, _ in sel.select(60):
                if key.fd == handle.exit_fd:
                    done = True
                else:
                    try:
                        if not os.read(key.fd, 65536):
                            sel.unregister(key.fd)
                    except BlockingIOError:
                        pass
    took = time.perf_counter() - began
    code = runtime.reap(handle)
    runtime.release(handle)
    if code != 0:
        sys.exit(f"{launch.argv}: exit code {code}")
    return took


def main() -> None:
    """Run the measurement (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if quick() else 8)
    parser.add_argument("--json")
    args = parser.parse_args()
    if os.geteuid() != 0 or importlib.util.find_spec("mujoco") is None:
        print("skipped: needs root (a non-root osmo's sandboxed attempts start cold) and "
              "osmo[sim]")
        write_rows(args.json, [])
        return
    sandbox = choose("on")
    assert sandbox is not None
    network = node_network(outbound=False)
    home = Path(tempfile.mkdtemp(prefix="osmo-bench-", dir="/var/tmp"))
    runtime = SandboxRuntime(sandbox.joined(network), network, hidden=(home,),
                             warm=WarmRunners(base_env(os.environ), idle=600))
    times: dict[bool, list[float]] = {True: [], False: []}
    try:
        first = _launch(runtime, home, "first", True)
        assert isinstance(first.run, WarmStart), "sim.rollout did not start warm"
        _run(runtime, first)
        for i in range(args.runs):
            for warm in (True, False):
                launch = _launch(runtime, home, f"{'warm' if warm else 'cold'}-{i}", warm)
                times[warm].append(_run(runtime, launch))
    finally:
        runtime.close()
    rows = [row(f"warm sandbox: one sim.rollout start, {'warm' if warm else 'cold'}", "ms",
                [t * 1000 for t in times[warm]], higher_is_better=False,
                notes="start → exit, 1 episode of 20 steps; the runner's first start not counted"
                if warm else "start → exit, the same task with warm: false")
            for warm in (True, False)]
    rows.append(row("warm sandbox: cold ÷ warm start", "×",
                    [c / w for c, w in zip(times[False], times[True], strict=True)],
                    higher_is_better=True))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
