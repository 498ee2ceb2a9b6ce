"""Realistic workloads, osmo against Ray: a rollout sweep, an evaluation sweep, the demo pipeline.

Each workload is the same Python code under both systems: the shipped plugin types
(``plugins/osmo_plugins``), timed inside the task the same way under both
(``bench/workloads/osmo_bench_timed.py``: ``perf_counter`` around the type's ``run``, after what
it imports; under osmo, by osmo's runner with ``OSMO_TASK_TIMING=1`` in the task's environment):

- **rollout sweep**: ``--rollouts`` ``sim.rollout`` tasks (default 200), each one expert
  episode of InvertedPendulum-v5, 50 steps, written as its MCAP (shard i of N: distinct seeds);
- **evaluation sweep**: ``--evals`` ``sim.eval`` tasks (default 40) of one small trained ACT
  policy (torch), 5 episodes each of 50 steps, distinct seeds, recorded as MCAP (no ``.rrd``).
  The checkpoint is made before any clock, here, by the shipped rollout → dataset → train
  functions (20 expert episodes, 100 training steps; nothing downloaded); both systems
  evaluate that same folder (osmo as an uploaded dataset);
- **the demo pipeline**: ``workflows/reach-vision.yaml`` with its defaults (4 rollout shards
  → a dataset per shard → train on the 4 → eval), each task given ``OSMO_TASK_TIMING=1``.

**osmo**: a fresh ``osmo server start`` (local pool, one slot per core, the default sandbox;
and again with ``--sandbox off``: ``--osmo-sandbox``; the shipped types start from warm
runners in both, in the sandbox where osmo runs as root) per workload and round, then one
``osmo submit FILE --wait`` through the real CLI, timed from the CLI's start to its exit; each
task's compute is read back from its log. **Ray** (``--peers``, or ``bench/run --peers``): the same
rendered tasks and params as a DAG of Ray tasks (``peers/ray_sim.py``), ``ray.init(num_cpus=2)``,
in the peer venv (``peers/compare.py``), one process per round.

**Overhead per task** = (makespan − ideal) × slots ÷ tasks, where ideal is the makespan with
no overhead at all: the sum over the DAG's levels (tasks at the same depth) of
max(the level's compute ÷ slots, its longest task), slots = 2. For a sweep (one level) that is
makespan × 2 ÷ tasks − the mean compute. Compute is always measured inside the task.

Each workload runs under both systems back to back, and which goes first alternates round by
round (the pipeline: ``--pipeline-rounds``); ratios are per round (osmo ÷ Ray, the same
round). Rows carry the targets of issue 30: makespan ≤ Ray's (the rollout sweep's
stretch: 0.8×), the pipeline's osmo workflow time ≤ 120 s.

Usage: python bench/bench_sim.py [--rounds 2] [--pipeline-rounds 1] [--rollouts 200]
       [--evals 40] [--peers] [--no-pipeline] [--json out.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
WORKLOADS = HERE / "workloads"
sys.path[:0] = [str(ROOT), str(HERE), str(HERE / "peers"), str(WORKLOADS), str(ROOT / "plugins")]

from bench_pipeline import osmo_cli, submit_wait  # noqa: E402
from benchlib import Row, quick, row, write_rows  # noqa: E402

SLOTS = 2
TIMED = '    environment: {OSMO_TASK_TIMING: "1"}\n'  # osmo's runner prints the compute
ENV = "InvertedPendulum-v5"
POLICY = "bench-policy"
TARGETS = {"rollout": 1.0, "eval": 1.0, "pipeline": 1.0}


def rollout_yaml(n: int) -> str:
    """n sim.rollout tasks, one 50-step expert episode each, shard i of n (distinct seeds)."""
    tasks = "".join(f"""
  - name: rollout-{i}
    type: sim.rollout
{TIMED}    params: {{env: {ENV}, policy: expert, episodes: 1, max_steps: 50, shard: {i},
              shards: {n}}}
""" for i in range(n))
    return f"version: 2\nworkflow:\n  name: bench-rollout-sweep\n  tasks:{tasks}"


def eval_yaml(n: int, episodes: int) -> str:
    """n sim.eval tasks of the checkpoint dataset, ``episodes`` 50-step episodes each."""
    tasks = "".join(f"""
  - name: eval-{i}
    type: sim.eval
{TIMED}    params: {{envs: [{ENV}], policies: [checkpoint], episodes: {episodes}, max_steps: 50,
              seed: {10_000 + i * episodes}, rrd: false}}
    inputs:
    - dataset: {{name: {POLICY}}}
""" for i in range(n))
    return f"version: 2\nworkflow:\n  name: bench-eval-sweep\n  tasks:{tasks}"


def pipeline_yaml() -> str:
    """workflows/reach-vision.yaml with each task's compute timed by osmo's runner."""
    lines = (ROOT / "workflows" / "reach-vision.yaml").read_text().splitlines(keepends=True)
    return "".join(line + TIMED if line.startswith("    type: ") else line for line in lines)


def build_checkpoint(folder: Path, episodes: int = 20, steps: int = 100) -> Path:
    """A small trained ACT policy for InvertedPendulum, made here by the shipped functions."""
    from osmo_bench_timed import call

    call("sim.rollout", {"env": ENV, "policy": "expert", "episodes": episodes, "max_steps": 50},
         [], str(folder / "rollout"), "rollout")
    call("lerobot.dataset", {"images": False}, [("rollout", str(folder / "rollout"))],
         str(folder / "dataset"), "dataset")
    call("lerobot.train", {"steps": steps, "batch_size": 32},
         [("dataset", str(folder / "dataset"))],
         str(folder / "checkpoint"), "train")
    return folder / "checkpoint"


def plan_of(spec_path: Path, checkpoint: Path) -> list[dict[str, Any]]:
    """The rendered spec's tasks as Ray's plan: shipped type, params, inputs, cpus; upstream
    first."""
    from osmo.spec import load_spec

    tasks = []
    spec = load_spec(spec_path)
    for t in spec.all_tasks():
        assert t.type is not None and t.environment.get("OSMO_TASK_TIMING") == "1", t.name
        inputs: list[dict[str, str]] = []
        for i in t.inputs:
            if i.task:
                inputs.append({"task": i.task})
            elif i.dataset:
                inputs.append({"name": i.dataset, "path": str(checkpoint)})
        tasks.append({"name": t.name, "kind": t.type, "params": dict(t.params),
                      "inputs": inputs, "cpu": spec.resource_for(t).cpu or 1})
    return tasks


def ideal(plan: list[dict[str, Any]], compute: dict[str, float]) -> float:
    """The makespan with no overhead: Σ over DAG levels of max(Σ compute ÷ slots, longest)."""
    depth: dict[str, int] = {}
    for t in plan:  # upstream first
        depth[t["name"]] = 1 + max((depth[i["task"]] for i in t["inputs"] if "task" in i),
                                   default=-1)
    levels: dict[int, list[float]] = {}
    for name, d in depth.items():
        levels.setdefault(d, []).append(compute[name])
    return sum(max(sum(v) / SLOTS, max(v)) for v in levels.values())


@contextmanager
def server(checkpoint: Path | None, sandbox: str = "auto") -> Iterator[Path]:
    """A fresh osmo home with a started server (and the checkpoint uploaded as a dataset)."""
    import osmo

    with tempfile.TemporaryDirectory(prefix="osmo-bench-sim-") as tmp:
        home = Path(tmp)
        try:  # a start that timed out may still have left its server running
            osmo_cli(home, "server", "start", "--sandbox", sandbox)
            if checkpoint is not None:
                with osmo.Client(home=home) as client:
                    client.upload_dataset(POLICY, checkpoint)
            yield home
        finally:
            osmo_cli(home, "server", "stop")


def run_osmo(spec: Path, plan: list[dict[str, Any]], checkpoint: Path | None,
             sandbox: str = "auto") -> dict[str, Any]:
    """One workload through the CLI on a fresh server: makespan and each task's compute."""
    from osmo_bench_timed import compute_of

    import osmo

    with server(checkpoint, sandbox) as home:
        makespan, wf = submit_wait(home, spec, [])
        with osmo.Client(home=home) as client:
            lines: dict[str, list[str]] = {}
            for record in client.logs(wf):
                lines.setdefault(record.task or "", []).append(record.text)
            info = client.get(wf, waiting=False)
    compute = {}
    for t in plan:
        seconds = compute_of(lines.get(t["name"], []))
        if seconds is None:
            raise SystemExit(f"task {t['name']} printed no compute line")
        compute[t["name"]] = seconds
    workflow_s = (info.ended_at or 0) - info.submitted_at
    return {"makespan_s": makespan, "compute_s": compute, "workflow_s": workflow_s}


def run_ray(plans: dict[str, list[dict[str, Any]]], log: Path) -> dict[str, Any]:
    """Every workload of ``plans`` in one Ray process (peers/ray_sim.py)."""
    from compare import ensure_sim_path, ensure_venv, run_peer_script

    ensure_venv()
    ensure_sim_path()
    plan_file = Path(tempfile.mkstemp(prefix="osmo-bench-plan-", suffix=".json")[1])
    try:
        plan_file.write_text(json.dumps(plans))
        path = os.pathsep.join([str(ROOT), str(ROOT / "plugins"), str(WORKLOADS)])
        return run_peer_script("ray_sim.py", ["--plan", str(plan_file)], log, ray=True,
                               out_dir=True, env={"PYTHONPATH": path}, timeout=1800)
    finally:
        plan_file.unlink(missing_ok=True)


def overhead(plan: list[dict[str, Any]], makespan: float, compute: dict[str, float]) -> float:
    """(makespan − ideal) × slots ÷ tasks, in seconds per task."""
    return (makespan - ideal(plan, compute)) * SLOTS / len(plan)


def main() -> None:
    """Build the checkpoint, run every workload under osmo (and Ray), write the rows."""
    small = quick()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=1 if small else 2)
    ap.add_argument("--pipeline-rounds", type=int, default=1)
    ap.add_argument("--rollouts", type=int, default=4 if small else 200)
    ap.add_argument("--evals", type=int, default=2 if small else 40)
    ap.add_argument("--episodes", type=int, default=1 if small else 5)
    ap.add_argument("--peers", action="store_true",
                    default=os.environ.get("OSMO_BENCH_PEERS") == "1",
                    help="also run Ray (bench/run --peers sets this)")
    ap.add_argument("--no-pipeline", action="store_true", default=small,
                    help="skip the demo pipeline (the quick run skips it: bench_pipeline runs it)")
    ap.add_argument("--osmo-sandbox", default="auto" if small else "auto,off",
                    help="osmo's sandbox modes to run, comma-separated (a system each: 'osmo' "
                         "is the default sandbox, 'osmo --sandbox off' none; the shipped types "
                         "start from warm runners in both where osmo runs as root)")
    ap.add_argument("--json")
    args = ap.parse_args()
    missing = [m for m in ("gymnasium", "mujoco", "lerobot", "torch")
               if importlib.util.find_spec(m) is None]
    if missing:
        print(f"skipped: needs {', '.join(missing)} (pip install \"osmo[all]\")")
        write_rows(args.json, [])
        return
    with tempfile.TemporaryDirectory(prefix="osmo-bench-sim-") as tmp:
        project = Path(tmp) / "project"
        project.mkdir()
        specs = {"rollout": rollout_yaml(args.rollouts), "eval": eval_yaml(args.evals,
                                                                           args.episodes)}
        if not args.no_pipeline:
            specs["pipeline"] = pipeline_yaml()
        for name, text in specs.items():
            (project / f"{name}.yaml").write_text(text)
        print("building the evaluated checkpoint (not timed)", flush=True)
        checkpoint = build_checkpoint(Path(tmp) / "policy", *((2, 5) if small else (20, 100)))
        plans = {name: plan_of(project / f"{name}.yaml", checkpoint) for name in specs}
        results = measure(args, project, plans, checkpoint)
    write_rows(args.json, rows_of(args, plans, results))


def measure(args: argparse.Namespace, project: Path, plans: dict[str, list[dict[str, Any]]],
            checkpoint: Path) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Run the rounds; results[system][workload], one entry per round.

    Each workload runs under both systems back to back (so a pair sees the same load); which
    system goes first alternates round by round. Ray runs each workload in its own process.
    """
    osmos = {_system(mode): mode for mode in args.osmo_sandbox.split(",") if mode}
    results: dict[str, dict[str, list[dict[str, Any]]]] = {s: {} for s in (*osmos, "ray")}
    log = Path(tempfile.gettempdir()) / "osmo-bench-sim-ray.log"
    log.write_text("")
    for r in range(max(args.rounds, args.pipeline_rounds)):
        names = [n for n in plans if r < (args.pipeline_rounds if n == "pipeline"
                                           else args.rounds)]
        order = [*osmos, "ray"] if r % 2 == 0 else ["ray", *reversed(osmos)]
        for n in names:
            for system in order:
                if system == "ray" and args.peers:
                    ray = run_ray({n: plans[n]}, log)
                    res = dict(ray["results"][n], startup_s=ray["startup_s"])
                elif system in osmos:
                    res = run_osmo(project / f"{n}.yaml", plans[n],
                                   checkpoint if n == "eval" else None, osmos[system])
                else:
                    continue
                results[system].setdefault(n, []).append(res)
                each = " ".join(f"{t} {c:.2f}" for t, c in res["compute_s"].items())
                print(f"round {r + 1}: {system} {n} {res['makespan_s']:.1f} s "
                      f"(load {os.getloadavg()[0]:.1f})"
                      + (f"; compute inside: {each}" if len(res["compute_s"]) <= 10 else ""),
                      flush=True)
    return results


def _system(sandbox: str) -> str:
    """The name of osmo's system in the rows for one sandbox mode."""
    return "osmo" if sandbox == "auto" else f"osmo --sandbox {sandbox}"


LABELS = {"rollout": "rollout sweep", "eval": "evaluation sweep",
          "pipeline": "reach-vision pipeline"}


def rows_of(args: argparse.Namespace, plans: dict[str, list[dict[str, Any]]],
            results: dict[str, dict[str, list[dict[str, Any]]]]) -> list[Row]:
    """The rows: per workload and system makespan, compute and overhead; osmo ÷ Ray."""
    rows: list[Row] = []
    for name, plan in plans.items():
        label = f"sim: {LABELS[name]} ({len(plan)} tasks)"
        for system, runs in ((s, results[s].get(name, [])) for s in results):
            if not runs:
                continue
            computes = [statistics.mean(r["compute_s"].values()) for r in runs]
            rows.append(row(f"{label}, {system} makespan", "s",
                            [r["makespan_s"] for r in runs], higher_is_better=False,
                            notes=f"mean compute per task, measured inside it: "
                                  f"{statistics.median(computes):.3f} s"))
            rows.append(row(f"{label}, {system} overhead per task", "s",
                            [overhead(plan, r["makespan_s"], r["compute_s"]) for r in runs],
                            higher_is_better=False,
                            notes="(makespan − ideal) × 2 slots ÷ tasks; ideal: the compute "
                                  "alone, packed on 2 slots level by level"))
        ray_runs = results["ray"].get(name, [])
        for system in (s for s in results if s != "ray"):
            osmo_runs = results[system].get(name, [])
            if not (osmo_runs and ray_runs):
                continue
            rows.append(row(f"{label}, {system} ÷ Ray makespan", "×",
                            [o["makespan_s"] / r["makespan_s"]
                             for o, r in zip(osmo_runs, ray_runs, strict=False)],
                            higher_is_better=False, target=TARGETS[name],
                            notes="per round; Ray's start-up (ray.init + 2 workers) "
                                  f"{statistics.median(r['startup_s'] for r in ray_runs):.1f} s "
                                  "not counted" + ("; stretch target 0.8×"
                                                   if name == "rollout" else "")))
        for system in (s for s in results if s != "ray"):
            osmo_runs = results[system].get(name, [])
            if name == "pipeline" and osmo_runs:
                rows.append(row(f"sim: reach-vision pipeline, {system} workflow time", "s",
                                [o["workflow_s"] for o in osmo_runs], higher_is_better=False,
                                target=120.0, notes="submitted → COMPLETED as the server "
                                                    "records it, the workflow's defaults"))
            elif osmo_runs:  # the makespan less the CLI's own start, submit and exit
                rows.append(row(f"{label}, {system} workflow time", "s",
                                [o["workflow_s"] for o in osmo_runs], higher_is_better=False,
                                notes="submitted → COMPLETED as the server records it (no "
                                      "target: the makespan above is the CLI's)"))
    return rows


if __name__ == "__main__":
    main()
