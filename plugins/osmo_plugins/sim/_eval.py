"""The work of ``sim.eval`` (params and metric definitions in :mod:`osmo_plugins.sim.eval`)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from osmo.tasktypes.api import TaskContext
from osmo_plugins.episodes import EpisodeWriter
from osmo_plugins.lerobot.policy_io import POLICY_MARKER, frame_size
from osmo_plugins.sim.envs import EpisodeResult, make_env, run_episodes
from osmo_plugins.sim.policies import has_expert, make_policy

__all__ = ["ci95", "run", "summarize"]

# Two-sided 95% Student t quantiles for 1..30 degrees of freedom; normal beyond.
_T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
        2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
        2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


def ci95(values: Sequence[float]) -> tuple[float, float]:
    """The 95% confidence interval of the mean (Student t; a point for one value)."""
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, mean
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    half = (_T95[n - 2] if n - 1 <= len(_T95) else 1.96) * sd / math.sqrt(n)
    return mean - half, mean + half


def summarize(policy: str, kind: str, env_id: str, results: Sequence[EpisodeResult],
              max_steps: int) -> dict[str, Any]:
    """One row of ``metrics.json``."""
    returns = [r.total_reward for r in results]
    lo, hi = ci95(returns)
    return {
        "policy": policy, "kind": kind, "env": env_id, "episodes": len(results),
        "success_rate": sum(1 for r in results if not r.terminated and r.length >= max_steps)
        / len(results),
        "mean_return": sum(returns) / len(returns), "return_ci95": [lo, hi],
        "mean_length": sum(r.length for r in results) / len(results),
        "returns": returns, "seeds": [r.seed for r in results]}


def _checkpoints(ctx: TaskContext) -> list[tuple[str, Path]]:
    named = {Path(folder).resolve(): name for name, folder in ctx.input_named.items()}
    found = []
    for n, folder in enumerate(ctx.inputs):
        for marker in sorted(Path(folder).rglob(POLICY_MARKER)):
            label = named.get(Path(folder).resolve(), f"checkpoint{n}")
            found.append((label, marker.parent))
    return found


def _plan(ctx: TaskContext) -> list[tuple[str, str, Path | None]]:
    """(label, kind, checkpoint) for every policy asked for."""
    plan: list[tuple[str, str, Path | None]] = []
    for kind in ctx.params["policies"]:
        if kind == "checkpoint":
            found = _checkpoints(ctx)
            if not found:
                raise ValueError(f"policies lists checkpoint but no input holds {POLICY_MARKER} "
                                 "(add a lerobot.train task to inputs)")
            plan.extend((label, kind, path) for label, path in found)
        elif kind in ("random", "expert"):
            plan.append((kind, kind, None))
        else:
            raise ValueError(f"unknown policy {kind!r}: use checkpoint, random or expert")
    return plan


def run(ctx: TaskContext) -> None:
    """Run every policy on every env over the same seeds; write metrics, MCAP, .rrd."""
    p = ctx.params
    if p["threads"]:
        try:
            import torch

            torch.set_num_threads(p["threads"])
        except ImportError:
            pass
    plan, seeds = _plan(ctx), [p["seed"] + i for i in range(p["episodes"])]
    out = Path(ctx.output)
    rows, recorded = [], []
    total, done = len(plan) * len(p["envs"]) * len(seeds), 0
    for env_id in p["envs"]:
        for label, kind, ckpt in plan:
            if kind == "expert" and not has_expert(env_id):
                ctx.log.info("no expert for %s: skipped", env_id)
                done += len(seeds)
                continue
            size = frame_size(ckpt)
            env = make_env(env_id, max_steps=p["max_steps"], render=size is not None,
                           size=size or 64)
            policy = make_policy(kind, env, env_id=env_id, checkpoint=ckpt)
            name = f"rollouts/{label}--{env_id}.mcap"

            def tick(index: int, r: EpisodeResult, base: int = done,
                     who: str = f"{label} on {env_id}") -> None:
                ctx.progress(base + index + 1, total, f"{who}: {r.total_reward:.0f}")

            meta = {"env": env_id, "policy": label, "kind": kind, "seed": str(p["seed"]),
                    "episodes": str(len(seeds)), "max_steps": str(p["max_steps"]),
                    "fps": str(round(1.0 / env.unwrapped.dt, 6))}
            if p["record"]:
                with ctx.mcap_writer(name) as mcap:
                    writer = EpisodeWriter(mcap, meta, dt=env.unwrapped.dt)
                    results = run_episodes(env, policy, seeds, writer=writer, on_episode=tick,
                                           cancelled=ctx.cancelled)
                recorded.append((f"{label}/{env_id}", out / name))
            else:
                results = run_episodes(env, policy, seeds, on_episode=tick,
                                       cancelled=ctx.cancelled)
            ctx.check_cancelled()
            env.close()
            done += len(seeds)
            row = summarize(label, kind, env_id, results, p["max_steps"])
            rows.append(row)
            ctx.log.info("%-12s %-24s success %.0f%%  return %.1f [%.1f, %.1f]  length %.0f",
                         label, env_id, 100 * row["success_rate"], row["mean_return"],
                         *row["return_ci95"], row["mean_length"])
    metrics = {"suite": {"envs": list(p["envs"]), "seeds": seeds, "max_steps": p["max_steps"],
                         "success": "ran max_steps steps without terminating"},
               "results": rows}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    if p["rrd"] and recorded:
        _write_rrd(ctx, recorded)


def _write_rrd(ctx: TaskContext, recorded: list[tuple[str, Path]]) -> None:
    try:
        from osmo_plugins.viz._rerun import episodes_to_rrd

        episodes_to_rrd(recorded, Path(ctx.output) / "eval.rrd", app_id=ctx.workflow_id)
    except ImportError as exc:  # the viz extra is optional for evaluation
        ctx.log.warning("eval.rrd not written: %s", exc)
