"""Slurm's own cost: `sbatch --wait` of `true` with no orchestrator (the Slurm executor's limit).

Runs on the tests' private cluster (``tests/slurm/cluster.py``: munged, slurmctld and two
slurmd nodes n1 and n2 on loopback, 2 CPUs each, on this machine's cores), started once per
configuration and stopped at the end. Rows:

- **limit: `sbatch --wait` of `true`, 1 job** — ``sbatch --parsable --wait --wrap true``
  until it exits, one job at a time. sbatch polls the controller 2 s after submitting, then
  every 8 s, so this figure is quantised: it is what a caller of ``sbatch --wait`` waits.
- **100 × `sbatch --wait` of `true`, in parallel** — 100 such commands started together,
  wall time until the last one exits (and the same per job).
- **submit → RUNNING / COMPLETED, 1 job** — ``sbatch --parsable`` then ``scontrol show job``
  every 20 ms: Slurm's own latency without sbatch's polling (the scheduler's cycle is the
  submit → RUNNING part).
- **100 jobs submitted back to back → all COMPLETED** — polled with ``squeue`` every 50 ms.
- **osmo through Slurm** (the executor, ``osmo worker --runtime slurm``): a server and a
  Slurm worker on the same cluster; ``osmo submit --wait`` of a workflow of 1 task and of
  N independent tasks of ``true``, wall time until it returns (the CLI's start included),
  against the ``sbatch --wait`` rows (target: at most 20% over), and the engine's own
  figure (the workflow's submit time → its last task's end, from ``osmo query``).

Each is measured with the cluster's ``SchedulerParameters`` (:data:`CHOSEN`) and the
submit → RUNNING row also with Slurm's defaults (``batch_sched_delay=3``: batch jobs wait up
to 3 s for the scheduler). The first job after a start is a warm-up and is not counted.
Needs root and Slurm (``slurm-wlm munge``): otherwise the script writes no rows.

Usage: python bench/bench_slurm.py [--runs 5] [--jobs 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import Row, quick, row, write_rows  # noqa: E402

from tests.conftest import write  # noqa: E402
from tests.e2e.cluster import Cluster  # noqa: E402
from tests.slurm.cluster import (  # noqa: E402
    DEFAULT_SCHEDULER_PARAMETERS,
    SlurmCluster,
    missing_programs,
)

CHOSEN = DEFAULT_SCHEDULER_PARAMETERS
LIMIT = "limit: slurm `sbatch --wait` of `true`, 1 job"
LIMIT_MANY = "slurm: `sbatch --wait` of `true`, N in parallel, all exited"


def sbatch_wait(cluster: SlurmCluster) -> float:
    """Seconds of one ``sbatch --wait`` of ``true``."""
    t0 = time.perf_counter()
    cluster.run("sbatch", "--parsable", "--wait", "--output=/dev/null", "--wrap", "true",
                timeout=120)
    return time.perf_counter() - t0


def sbatch_wait_many(cluster: SlurmCluster, jobs: int) -> float:
    """Seconds until ``jobs`` concurrent ``sbatch --wait`` of ``true`` have all exited."""
    t0 = time.perf_counter()
    with ThreadPoolExecutor(jobs) as pool:
        list(pool.map(lambda _: cluster.run(
            "sbatch", "--parsable", "--wait", "--output=/dev/null", "--wrap", "true",
            timeout=600), range(jobs)))
    return time.perf_counter() - t0


def submit_to_states(cluster: SlurmCluster) -> tuple[float, float]:
    """Seconds from submitting ``true`` to RUNNING (or later) and to COMPLETED."""
    t0 = time.perf_counter()
    job_id = cluster.sbatch("true", "--output=/dev/null")
    started: float | None = None
    while True:
        state = cluster.job(job_id)["JobState"]
        now = time.perf_counter() - t0
        if started is None and state != "PENDING":
            started = now
        if state == "COMPLETED":
            return (now if started is None else started), now
        if state not in ("PENDING", "RUNNING", "COMPLETING", "CONFIGURING"):
            raise SystemExit(f"job {job_id} ended {state}")
        time.sleep(0.02)


def burst(cluster: SlurmCluster, jobs: int) -> float:
    """Seconds from submitting ``jobs`` jobs of ``true`` back to back to all COMPLETED."""
    t0 = time.perf_counter()
    ids = [cluster.sbatch("true", "--output=/dev/null") for _ in range(jobs)]
    while cluster.run("squeue", "-h", "-o", "%i").stdout.strip():
        time.sleep(0.05)
    states = cluster.run("sacct", "-c", "-P", "-n", "-o", "JobID,State").stdout.splitlines()
    done = {line.split("|")[0] for line in states if line.endswith("|COMPLETED")}
    if not set(ids) <= done:
        raise SystemExit(f"jobs not COMPLETED: {sorted(set(ids) - done)[:5]}...")
    return time.perf_counter() - t0


def measure(runs: int, jobs: int) -> list[Row]:
    """Every row, on a cluster with :data:`CHOSEN` and one with Slurm's defaults."""
    cluster = SlurmCluster(scheduler_parameters=CHOSEN).start()
    try:
        submit_to_states(cluster)  # warm-up: the first job after a start is slower
        single = [sbatch_wait(cluster) * 1000 for _ in range(runs)]
        states = [submit_to_states(cluster) for _ in range(runs)]
        many = [sbatch_wait_many(cluster, jobs) * 1000]
        burst_ms = [burst(cluster, jobs) * 1000]
    finally:
        cluster.stop()
    cluster = SlurmCluster(scheduler_parameters=None).start()
    try:
        submit_to_states(cluster)
        default_start = [submit_to_states(cluster)[0] * 1000 for _ in range(runs)]
    finally:
        cluster.stop()
    setup = (f"2 nodes x 2 CPUs on {os.cpu_count()} cores, SchedulerParameters="
             f"{CHOSEN or '(defaults)'}")
    return [
        row(LIMIT, "ms", single, higher_is_better=False,
            notes=f"sbatch polls 2 s after submit, then every 8 s; {setup}"),
        row(LIMIT_MANY, "ms", many,
            higher_is_better=False, notes=f"N={jobs}; {setup}"),
        row("slurm: `sbatch --wait` of `true`, N in parallel, per job", "ms",
            [m / jobs for m in many], higher_is_better=False, notes=f"N={jobs}; {setup}"),
        row("slurm: submit → RUNNING, 1 job (the scheduler's cycle)", "ms",
            [s * 1000 for s, _ in states], higher_is_better=False,
            notes=f"scontrol polled every 20 ms; {setup}"),
        row("slurm: submit → RUNNING, 1 job, Slurm's default SchedulerParameters", "ms",
            default_start, higher_is_better=False,
            notes="batch_sched_delay=3 (the default); scontrol polled every 20 ms"),
        row("slurm: submit → COMPLETED, 1 job (polled)", "ms",
            [c * 1000 for _, c in states], higher_is_better=False,
            notes=f"scontrol polled every 20 ms; {setup}"),
        row("slurm: N jobs submitted back to back → all COMPLETED, per job", "ms",
            [b / jobs for b in burst_ms], higher_is_better=False,
            notes=f"N={jobs}; squeue polled every 50 ms; {setup}"),
    ]


def workflow(folder: Path, tasks: int) -> Path:
    """A workflow of ``tasks`` independent tasks of ``true``, never reused from the cache
    (each workflow's tasks carry a fresh value in their environment)."""
    nonce = uuid.uuid4().hex
    body = "".join(f"  - name: t{i}\n    command: [\"true\"]\n"
                   f"    environment: {{RUN: \"{nonce}\"}}\n" for i in range(tasks))
    return write(folder / f"wf-{tasks}.yaml", f"workflow:\n  name: b{tasks}\n  tasks:\n{body}")


def osmo_through_slurm(grid: Cluster, spec: Path) -> tuple[float, float]:
    """Seconds of ``osmo submit --wait`` of ``spec``, and the engine's submit → last end."""
    t0 = time.perf_counter()
    done = grid.osmo("submit", str(spec), "--wait", timeout=900)
    wall = time.perf_counter() - t0
    if done.code != 0:
        raise SystemExit(f"osmo submit failed: {done.out}{done.err}")
    wf_id = done.out.splitlines()[0].split(" - ", 1)[1].strip()
    info = grid.osmo.query(wf_id)
    if any(t.get("reused") for t in info["tasks"]):
        raise SystemExit(f"{wf_id}: a task was reused from the cache, not run")
    ended = max(float(t["ended_at"]) for t in info["tasks"])
    return wall, ended - float(info["submitted_at"])


def measure_osmo(runs: int, jobs: int, limits: dict[str, float]) -> list[Row]:
    """osmo's rows: a server and an ``osmo worker --runtime slurm`` on a fresh cluster."""
    import tempfile

    cluster = SlurmCluster(scheduler_parameters=CHOSEN).start()
    folder = Path(tempfile.mkdtemp(prefix="osmo-bench-slurm-"))
    folder.chmod(0o755)
    grid = Cluster(folder, env={"SLURM_CONF": str(cluster.conf), "PATH": cluster.env["PATH"],
                                "OSMO_BENCH_RUN": os.environ.get("OSMO_BENCH_RUN", "")})
    try:
        grid.start_server()
        grid.start_worker("login", "--runtime", "slurm", "--sandbox", "off")
        osmo_through_slurm(grid, workflow(folder, 1))  # warm-up
        one = [osmo_through_slurm(grid, workflow(folder, 1)) for _ in range(runs)]
        many = [osmo_through_slurm(grid, workflow(folder, jobs))]
    finally:
        grid.stop()
        cluster.stop()
        shutil.rmtree(folder, ignore_errors=True)  # every run left one in the temp folder
    setup = f"2 nodes x 2 CPUs on {os.cpu_count()} cores, 1 Slurm worker, tasks `true`"
    return [
        row("osmo through slurm: submit --wait → COMPLETED, 1 task", "ms",
            [w * 1000 for w, _ in one], higher_is_better=False, limit_of=LIMIT,
            target=limits[LIMIT] * 1.2, notes=f"the CLI's start included; {setup}"),
        row("osmo through slurm: submit → last task ended (engine), 1 task", "ms",
            [e * 1000 for _, e in one], higher_is_better=False, limit_of=LIMIT,
            notes=f"osmo query's submitted_at → ended_at; {setup}"),
        row("osmo through slurm: submit --wait → COMPLETED, N tasks", "ms",
            [w * 1000 for w, _ in many], higher_is_better=False, limit_of=LIMIT_MANY,
            target=limits[LIMIT_MANY] * 1.2, notes=f"N={jobs} independent tasks; {setup}"),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=100)
    parser.add_argument("--json")
    args = parser.parse_args()
    missing = missing_programs()
    if missing or os.geteuid() != 0:
        print(f"no Slurm rows: {'missing ' + ', '.join(missing) if missing else 'needs root'}")
        write_rows(args.json, [])
        return
    runs = 1 if quick() else args.runs
    jobs = 4 if quick() else args.jobs
    try:
        rows = measure(runs, jobs)
        limits = {r["name"]: float(r["median"]) for r in rows}
        rows += measure_osmo(runs, jobs, limits)
    except subprocess.CalledProcessError as exc:
        raise SystemExit(f"slurm command failed: {exc}") from exc
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
