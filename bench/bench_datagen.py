"""Simulation data generation: env steps per second recorded to MCAP, 1 and 2 workers.

The workload is the pipeline's own: the LQR expert (with action noise) balancing MuJoCo
InvertedPendulum-v5 for 1,000-step episodes, written in the Foxglove-native episode format of
``osmo_plugins.episodes`` (one message per step; one MCAP per worker, like one rollout shard
per task).

Cases (process start, imports and a warm-up episode are never counted):

- bare vs recorded, 1 process: one process alternates a bare segment (the rollout loop with
  no recording) and a recorded one (opening, writing and closing its MCAP), ``--steps``
  steps each, so both meet the same background load; the recording overhead is recorded vs
  bare time per step of each pair (target ≤ 15%);
- the same with 64×64 frames (``--frame-steps`` steps): offscreen rendering every step
  (``MUJOCO_GL=egl``), frames written as ``foxglove.RawImage`` (overhead reported, no target);
- recorded, 2 workers: two processes, each writing its own MCAP, timed from one start signal
  to the last close; against the 1-process recorded throughput (target ≥ 1.7×).

Reports the median of several runs with min/max. Needs the sim extra.

Usage: python bench/bench_datagen.py [--runs 5] [--steps 20000] [--frame-steps 2000]
                                     [--env InvertedPendulum-v5] [--json out.json]
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


def _setup(env_id: str, frames: bool, folder: str, index: int) -> Any:
    """Build the env and policy and warm both up, recording too (imports and schema building
    are one-off costs); returns ``segment(steps, record) -> seconds``."""
    from osmo_plugins.episodes import EpisodeWriter
    from osmo_plugins.sim.envs import make_env, run_episodes
    from osmo_plugins.sim.policies import has_expert, make_policy

    env = make_env(env_id, max_steps=1000, render=frames, size=64)
    policy = make_policy("expert" if has_expert(env_id) else "random", env, env_id=env_id,
                         noise=0.3)
    seeds = iter(range(index * 1_000_000, (index + 1) * 1_000_000))

    def segment(steps: int, record: bool) -> float:
        start, count = time.perf_counter(), 0
        episodes = EpisodeWriter(Path(folder) / f"w{index}.mcap", {"env": env_id},
                                 dt=env.unwrapped.dt, with_frames=frames) if record else None
        while count < steps:
            seed = next(seeds)
            (result,) = run_episodes(env, policy, [seed], writer=episodes, first_index=seed,
                                     render=frames)
            count += result.length
        if episodes is not None:
            episodes.close()
        return count / (time.perf_counter() - start)

    segment(1, True)
    return segment


def _paired(env_id: str, steps: int, frames: bool, folder: str, ready: Any, go: Any,
            done: Any) -> None:
    segment = _setup(env_id, frames, folder, 0)
    ready.release()
    go.wait()
    bare = segment(steps, False)
    done.put((bare, segment(steps, True)))


def _worker(env_id: str, steps: int, folder: str, index: int, ready: Any, go: Any,
            done: Any) -> None:
    segment = _setup(env_id, False, folder, index)
    ready.release()
    go.wait()
    segment(steps, True)
    done.put(steps)


def _spawn(target: Any, args_of: Any, workers: int) -> tuple[float, list[Any]]:
    """Run ``workers`` processes; the seconds from the start signal to the last result."""
    ctx = mp.get_context("spawn")
    ready, go, done = ctx.Semaphore(0), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=target, args=args_of(i, ready, go, done))
             for i in range(workers)]
    for p in procs:
        p.start()
    for _ in procs:
        ready.acquire()
    start = time.perf_counter()
    go.set()
    results = [done.get() for _ in procs]
    elapsed = time.perf_counter() - start
    for p in procs:
        p.join()
        if p.exitcode != 0:
            raise RuntimeError(f"a worker exited {p.exitcode}")
    return elapsed, results


def paired_run(env_id: str, steps: int, frames: bool) -> tuple[float, float]:
    """(bare, recorded) steps per second in one process, back to back."""
    with tempfile.TemporaryDirectory() as folder:
        _, (result,) = _spawn(
            _paired, lambda i, ready, go, done: (env_id, steps, frames, folder, ready, go, done),
            1)
    return result  # type: ignore[no-any-return]


def parallel_run(env_id: str, workers: int, steps: int) -> float:
    """Recorded env steps per second over all workers, from the start signal to the last
    close."""
    with tempfile.TemporaryDirectory() as folder:
        elapsed, counts = _spawn(
            _worker, lambda i, ready, go, done: (env_id, steps, folder, i, ready, go, done),
            workers)
    return sum(counts) / elapsed


def machine() -> str:
    """One line about where the numbers came from."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{platform.system()} {platform.release()}, load before {load:.2f}")


def main() -> None:
    """Run every case ``--runs`` times, interleaved, and print/record the medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20_000, help="env steps per segment")
    parser.add_argument("--frame-steps", type=int, default=2_000,
                        help="env steps per segment of the cases with 64x64 frames")
    parser.add_argument("--env", default="InvertedPendulum-v5")
    parser.add_argument("--json")
    args = parser.parse_args()
    import importlib.util

    missing = [m for m in ("gymnasium", "mujoco", "foxglove")
               if importlib.util.find_spec(m) is None]
    if missing:  # a core-only install: nothing to measure, not a failure
        print(f"skipped: needs {', '.join(missing)} (pip install \"osmo[sim]\")")
        write_rows(args.json, [])
        return
    if quick():
        args.runs, args.steps, args.frame_steps = 1, 2_000, 200
    print(f"machine: {machine()}")
    plain: list[tuple[float, float]] = []
    framed: list[tuple[float, float]] = []
    two: list[float] = []
    for _ in range(args.runs):  # interleaved, so background load hits every case alike
        plain.append(paired_run(args.env, args.steps, False))
        two.append(parallel_run(args.env, 2, args.steps))
        framed.append(paired_run(args.env, args.frame_steps, True))
    name = f"datagen: {args.env}"
    rows = [row(f"{name} bare, 1 process", "steps/s", [b for b, _ in plain],
                higher_is_better=True),
            row(f"{name} recorded, 1 process", "steps/s", [r for _, r in plain],
                higher_is_better=True),
            row(f"{name} recorded, 2 workers", "steps/s", two, higher_is_better=True),
            row(f"{name} bare with 64x64 frames", "steps/s", [b for b, _ in framed],
                higher_is_better=True),
            row(f"{name} recorded with 64x64 frames", "steps/s", [r for _, r in framed],
                higher_is_better=True),
            row("datagen: 2 workers / 1 worker", "x",
                [t / r for t, (_, r) in zip(two, plain, strict=True)], higher_is_better=True,
                target=1.7),
            row("datagen: recording overhead (recorded vs bare time per step)", "%",
                [100 * (b / r - 1) for b, r in plain], higher_is_better=False, target=15.0),
            row("datagen: recording overhead with 64x64 frames", "%",
                [100 * (b / r - 1) for b, r in framed], higher_is_better=False)]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
