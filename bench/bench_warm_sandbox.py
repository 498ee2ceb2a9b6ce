"""One ``sim.rollout`` start in the sandbox: warm (a fork of a sandboxed runner) against cold.

Through the sandboxed process runtime alone (``osmo.runtime.process.sandboxed``), as root:
each attempt is prepared as the pool prepares it, then timed from ``start`` to its exit
(a one-episode, 20-step InvertedPendulum rollout: the import is most of a cold start).
Warm and cold attempts alternate; the first warm one (the runner's import) is not counted.

Usage (as root, from the repository): python bench/bench_warm_sandbox.py [--runs 8]
"""

from __future__ import annotations

import argparse
import os
import selectors
import statistics
import sys
import tempfile
import time
from pathlib import Path

from osmo.layout import AttemptDirs
from osmo.runtime.api import Attempt, Launch
from osmo.runtime.process.sandbox import choose, node_network
from osmo.runtime.process.sandboxed import SandboxRuntime
from osmo.runtime.process.warm import WarmRunners, WarmStart
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import ResolvedType, TaskSpec
from osmo.worker.taskenv import base_env
from osmo.worker.workdir import prepare


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
    parser.add_argument("--runs", type=int, default=8)
    args = parser.parse_args()
    if os.geteuid() != 0:
        sys.exit("run it as root: a non-root osmo's sandboxed attempts start cold")
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
    for warm in (True, False):
        print(f"sandboxed {'warm' if warm else 'cold'}: median "
              f"{statistics.median(times[warm]) * 1000:.0f} ms of {args.runs} "
              f"(min {min(times[warm]) * 1000:.0f}, max {max(times[warm]) * 1000:.0f})")


if __name__ == "__main__":
    main()
