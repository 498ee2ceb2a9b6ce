"""Ray running osmo's benchmark shapes; run by the peer virtualenv's python.

Local mode: ``ray.init(num_cpus=2)`` starts a private local cluster (GCS, raylet and worker
processes, session files under a private ``--temp-dir``), no dashboard, usage stats off;
``ray.shutdown()`` stops all of it before exit. Each task asks for 1 cpu, so 2 run at once,
matching osmo's 2 cpu slots.

Shapes (dependencies as object-ref arguments, like osmo's ``inputs``): a chain of N tasks, and a
fan-out/join (1 source → N-2 → 1 join that takes all N-2 refs). Task bodies: ``shell`` runs
``subprocess.run(["true"])`` (osmo's tasks are processes, so this is the like-for-like body);
``noop`` returns at once.

``startup_s`` is the time from process start to a finished 2-task warm-up (``ray.init``
plus worker start). Each measured shape is timed from the first ``.remote`` to ``ray.get``
of the last task.

Usage: python ray_dag.py --tasks 1000 --shapes chain,fanout --bodies shell,noop --temp-dir D
       --json OUT
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time

T_START = time.perf_counter()
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import ray  # noqa: E402


@ray.remote(num_cpus=1)
def shell(*_deps: object) -> None:
    """Spawn `true` and wait for it."""
    subprocess.run(["true"], check=True)


@ray.remote(num_cpus=1)
def noop(*_deps: object) -> None:
    """Do nothing."""


BODIES = {"shell": shell, "noop": noop}


def chain(n: int, body: str) -> None:
    """n tasks, each taking the previous one's result."""
    t = BODIES[body]
    ref = t.remote()
    for _ in range(n - 1):
        ref = t.remote(ref)
    ray.get(ref)


def fanout(n: int, body: str) -> None:
    """1 source, n-2 tasks taking its result, 1 join taking all of theirs."""
    t = BODIES[body]
    src = t.remote()
    middle = [t.remote(src) for _ in range(n - 2)]
    ray.get(t.remote(*middle))


def main() -> None:
    """Start Ray, warm up, time every shape × body once, shut down; write JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--tasks", type=int, default=1000)
    ap.add_argument("--shapes", default="chain,fanout")
    ap.add_argument("--bodies", default="shell,noop")
    ap.add_argument("--temp-dir", required=True)
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    ray.init(num_cpus=2, include_dashboard=False, _temp_dir=args.temp_dir,
             logging_level="WARNING", log_to_driver=False)
    try:
        chain(2, "noop")
        out: dict[str, object] = {"peer": "ray", "version": ray.__version__,
                                  "startup_s": time.perf_counter() - T_START, "results": []}
        flows = {"chain": chain, "fanout": fanout}
        for body in args.bodies.split(","):  # the `true` body first: it is compared
            for shape in args.shapes.split(","):
                t0 = time.perf_counter()
                flows[shape](args.tasks, body)
                out["results"].append({"shape": shape, "body": body, "tasks": args.tasks,  # type: ignore[attr-defined]
                                       "seconds": time.perf_counter() - t0})
    finally:
        ray.shutdown()
    with open(args.json, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
