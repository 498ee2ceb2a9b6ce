"""Ray running the realistic workloads of ``bench/bench_sim.py``; run by the peer venv's python.

The plan (a JSON file written by bench_sim.py) lists workloads, each a DAG of tasks: name,
shipped task type, params (as the spec rendered them), and inputs (an upstream task of the same
workload, or a folder made before the clock, such as the evaluated checkpoint), and the cpus
it requests. Each task is a Ray task with as many ``num_cpus`` as osmo reserves for it that calls
``osmo_bench_timed.call``: the shipped plugin function, timed inside the task exactly as under
osmo, writing its outputs (the MCAPs, the checkpoint) under ``--out``. Upstream results are
object-ref arguments, so Ray runs a task when its inputs are done.

``ray.init(num_cpus=2)``, private ``--temp-dir``, no dashboard, usage stats off; a 2-task
no-op warm-up starts 2 worker processes (its time from process start is ``startup_s``); the
workers import the plugins' stacks in their first real task and keep them, as Ray does. Each
workload is timed from its first ``.remote`` to the ``ray.get`` of all its tasks.

``osmo`` and ``osmo_plugins`` come from ``PYTHONPATH`` (the checkout under test; workers
inherit it), torch, mujoco, gymnasium and lerobot from osmo's own site-packages, appended
after the peer venv's by a ``.pth`` file (``compare.ensure_sim_path``).

Usage: python ray_sim.py --plan PLAN.json --out DIR --temp-dir D --json OUT
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

T_START = time.perf_counter()
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import ray  # noqa: E402


@ray.remote(num_cpus=1)
def run_task(kind: str, params: dict[str, Any], name: str, output: str,
             *inputs: dict[str, Any]) -> dict[str, Any]:
    """One task: the shipped type ``kind``, timed, on its inputs' folders; output, seconds."""
    import osmo_bench_timed

    pairs = [(i["name"], i["output"]) for i in inputs]
    seconds = osmo_bench_timed.call(kind, params, pairs, output, name)
    return {"name": name, "output": output, "compute_s": seconds, "pid": os.getpid()}


@ray.remote(num_cpus=1)
def noop() -> None:
    """Warm-up: starts a worker process."""


def run_workload(tasks: list[dict[str, Any]], out: str) -> dict[str, Any]:
    """Submit every task of one DAG (upstream first), wait for all; makespan and seconds."""
    refs: dict[str, Any] = {}
    t0 = time.perf_counter()
    for t in tasks:  # the plan lists upstream tasks first
        args = [refs[i["task"]] if "task" in i else {"name": i["name"], "output": i["path"]}
                for i in t["inputs"]]
        refs[t["name"]] = run_task.options(num_cpus=t.get("cpu", 1)).remote(
            t["kind"], t["params"], t["name"], os.path.join(out, t["name"]), *args)
    done = ray.get(list(refs.values()))
    makespan = time.perf_counter() - t0
    return {"makespan_s": makespan, "compute_s": {d["name"]: d["compute_s"] for d in done},
            "workers": len({d["pid"] for d in done})}


def main() -> None:
    """Start Ray, warm up, run every workload of the plan once, shut down; write JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--plan", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--temp-dir", required=True)
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    with open(args.plan) as f:
        plan = json.load(f)
    ray.init(num_cpus=2, include_dashboard=False, _temp_dir=args.temp_dir,
             logging_level="WARNING", log_to_driver=False)
    try:
        ray.get([noop.remote() for _ in range(2)])
        out: dict[str, Any] = {"peer": "ray", "version": ray.__version__,
                               "startup_s": time.perf_counter() - T_START, "results": {}}
        for name, tasks in plan.items():
            folder = os.path.join(args.out, name)
            os.makedirs(folder, exist_ok=True)
            out["results"][name] = run_workload(tasks, folder)
    finally:
        ray.shutdown()
    with open(args.json, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
