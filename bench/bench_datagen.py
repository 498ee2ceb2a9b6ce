"""Simulation data generation: env steps per second recorded to MCAP, 1 and 2 workers.

The workload is the pipeline's own: the LQR expert (with action noise) balancing MuJoCo
InvertedPendulum-v5 for 1,000-step episodes, written through ``osmo.record`` in the episode
format of ``osmo_plugins.episodes`` (one MCAP per worker, like one rollout shard per task).

Cases, each timed from a start signal after every worker has built its env (process start
and imports are not counted):

- bare: the same rollout loop with no recording (1 process);
- recorded, 1 worker / 2 workers: separate processes, each writing its own MCAP; throughput
  is all steps over the wall time.

Reports the median of several runs with min/max, the 2-vs-1 worker ratio (target ≥ 1.7×) and
the recording overhead, recorded vs bare time per step (target ≤ 15%). Needs the sim extra.

Usage: python bench/bench_datagen.py [--runs 5] [--steps 20000] [--env InvertedPendulum-v5]
                                     [--json out.json]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "plugins"), str(ROOT / "bench")]

from benchlib import quick, row, write_rows  # noqa: E402


def _worker(env_id: str, steps: int, record: bool, folder: str, index: int,
            ready: Any, go: Any, done: Any) -> None:
    from osmo_plugins.episodes import EpisodeWriter
    from osmo_plugins.sim.envs import make_env, run_episodes
    from osmo_plugins.sim.policies import has_expert, make_policy

    from osmo.record import LineageMcapWriter

    env = make_env(env_id, max_steps=1000)
    policy = make_policy("expert" if has_expert(env_id) else "random", env, env_id=env_id,
                         noise=0.3)
    run_episodes(env, policy, [999])  # warm up
    ready.release()
    go.wait()
    count, seed = 0, index * 1_000_000
    writer = LineageMcapWriter(Path(folder) / f"w{index}.mcap", None) if record else None
    episodes = EpisodeWriter(writer, {"env": env_id}, dt=env.unwrapped.dt) if writer else None
    while count < steps:
        (result,) = run_episodes(env, policy, [seed], writer=episodes, first_index=seed)
        count += result.length
        seed += 1
    if writer is not None:
        writer.close()
    done.put(count)


def one_run(env_id: str, workers: int, steps: int, record: bool) -> float:
    """Env steps per second over all workers, from the start signal to the last close."""
    ctx = mp.get_context("spawn")
    ready, go, done = ctx.Semaphore(0), ctx.Event(), ctx.Queue()
    with tempfile.TemporaryDirectory() as folder:
        procs = [ctx.Process(target=_worker, args=(env_id, steps, record, folder, i, ready, go,
                                                   done)) for i in range(workers)]
        for p in procs:
            p.start()
        for _ in procs:
            ready.acquire()
        start = time.perf_counter()
        go.set()
        total = sum(done.get() for _ in procs)
        elapsed = time.perf_counter() - start
        for p in procs:
            p.join()
            if p.exitcode != 0:
                raise RuntimeError(f"a worker exited {p.exitcode}")
    return total / elapsed


def machine() -> str:
    """One line about where the numbers came from."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{platform.system()} {platform.release()}, load before {load:.2f}")


def main() -> None:
    """Run every case ``--runs`` times, interleaved, and print/record the medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20_000, help="env steps per worker")
    parser.add_argument("--env", default="InvertedPendulum-v5")
    parser.add_argument("--json")
    args = parser.parse_args()
    import importlib.util

    missing = [m for m in ("gymnasium", "mujoco") if importlib.util.find_spec(m) is None]
    if missing:  # a core-only install: nothing to measure, not a failure
        print(f"skipped: needs {', '.join(missing)} (pip install \"osmo[sim]\")")
        write_rows(args.json, [])
        return
    if quick():
        args.runs, args.steps = 1, 2_000
    print(f"machine: {machine()}")
    cases = {"bare, 1 process": (1, False), "recorded, 1 worker": (1, True),
             "recorded, 2 workers": (2, True)}
    samples: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.runs):  # interleaved, so background load hits every case alike
        for name, (workers, record) in cases.items():
            samples[name].append(one_run(args.env, workers, args.steps, record))
    rows = [row(f"datagen: {args.env} {name}", "steps/s", v, higher_is_better=True)
            for name, v in samples.items()]
    bare, one, two = (samples[n] for n in cases)
    ratio = [b / a for a, b in zip(one, two, strict=True)]
    overhead = [100 * (b / r - 1) for b, r in zip(bare, one, strict=True)]
    rows.append(row("datagen: 2 workers / 1 worker", "x", ratio, higher_is_better=True,
                    target=1.7))
    rows.append(row("datagen: recording overhead (recorded vs bare time per step)", "%",
                    overhead, higher_is_better=False, target=15.0))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
