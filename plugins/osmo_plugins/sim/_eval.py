"""The work of ``sim.eval`` (params and metric definitions in :mod:`osmo_plugins.sim.eval`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from osmo.tasktypes.api import TaskContext
from osmo_plugins.episodes import EpisodeWriter
from osmo_plugins.lerobot.policy_io import POLICY_MARKER, frame_size
from osmo_plugins.sim.envs import EpisodeResult, make_env, run_episodes
from osmo_plugins.sim.metrics import add_normalized, choose_criterion, parse_success, summarize
from osmo_plugins.sim.policies import has_expert, make_policy

__all__ = ["run"]


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
    default, per_env = parse_success(p["success"], p["envs"])
    if p["threads"]:
        try:
            import torch

            torch.set_num_threads(p["threads"])
        except ImportError:
            pass
    plan, seeds = _plan(ctx), [p["seed"] + i for i in range(p["episodes"])]
    rows: list[dict[str, Any]] = []
    criteria: dict[str, Any] = {}
    recorded: list[tuple[str, Path]] = []
    progress = _Progress(ctx, len(plan) * len(p["envs"]) * len(seeds))
    for env_id in p["envs"]:
        ran: list[tuple[str, str, list[EpisodeResult]]] = []
        for label, kind, ckpt in plan:
            if kind == "expert" and not has_expert(env_id):
                ctx.log.info("no expert for %s: skipped", env_id)
                progress.skip(len(seeds))
                continue
            ran.append((label, kind, _evaluate(ctx, env_id, label, kind, ckpt, seeds,
                                               progress, recorded)))
        criterion = choose_criterion(env_id, [r for *_, rs in ran for r in rs],
                                     max_steps=p["max_steps"], default=default,
                                     per_env=per_env)
        criteria[env_id] = criterion.to_json()
        rows.extend(summarize(label, kind, env_id, results, criterion)
                    for label, kind, results in ran)
    add_normalized(rows)
    for row in rows:
        _log_row(ctx, row)
    metrics = {"suite": {"envs": list(p["envs"]), "seeds": seeds, "max_steps": p["max_steps"],
                         "success": criteria},
               "results": rows}
    (Path(ctx.output) / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    if p["rrd"] and recorded:
        _write_rrd(ctx, recorded)


class _Progress:
    """Progress over every episode of the suite."""

    def __init__(self, ctx: TaskContext, total: int) -> None:
        self.ctx, self.total, self.done = ctx, total, 0

    def skip(self, n: int) -> None:
        self.done += n

    def tick(self, who: str, r: EpisodeResult) -> None:
        self.done += 1
        self.ctx.progress(self.done, self.total, f"{who}: {r.total_reward:.0f}")


def _evaluate(ctx: TaskContext, env_id: str, label: str, kind: str, ckpt: Path | None,
              seeds: list[int], progress: _Progress,
              recorded: list[tuple[str, Path]]) -> list[EpisodeResult]:
    """One policy on one env over the suite's seeds (recorded as MCAP when asked)."""
    p = ctx.params
    size = frame_size(ckpt)
    env = make_env(env_id, max_steps=p["max_steps"], render=size is not None, size=size or 64)
    policy = make_policy(kind, env, env_id=env_id, checkpoint=ckpt)

    def tick(index: int, r: EpisodeResult) -> None:
        progress.tick(f"{label} on {env_id}", r)

    if p["record"]:
        name = f"rollouts/{label}--{env_id}.mcap"
        meta = {"env": env_id, "policy": label, "kind": kind, "seed": str(p["seed"]),
                "episodes": str(len(seeds)), "max_steps": str(p["max_steps"]),
                "fps": str(round(1.0 / env.unwrapped.dt, 6))}
        with EpisodeWriter.for_task(ctx, name, meta, dt=env.unwrapped.dt) as writer:
            results = run_episodes(env, policy, seeds, writer=writer, on_episode=tick,
                                   cancelled=ctx.cancelled)
        recorded.append((f"{label}/{env_id}", Path(ctx.output) / name))
    else:
        results = run_episodes(env, policy, seeds, on_episode=tick, cancelled=ctx.cancelled)
    ctx.check_cancelled()
    env.close()
    return results


def _log_row(ctx: TaskContext, row: dict[str, Any]) -> None:
    rate = row["success_rate"]
    norm = row["normalized_score"]
    ctx.log.info("%-12s %-24s success %s  return %.1f [%.1f, %.1f]  normalised %s  length %.0f",
                 row["policy"], row["env"], "n/a" if rate is None else f"{100 * rate:.0f}%",
                 row["mean_return"], *row["return_ci95"],
                 "n/a" if norm is None else f"{norm:.2f}", row["mean_length"])


def _write_rrd(ctx: TaskContext, recorded: list[tuple[str, Path]]) -> None:
    try:
        from osmo_plugins.viz._rerun import episodes_to_rrd

        episodes_to_rrd(recorded, Path(ctx.output) / "eval.rrd", app_id=ctx.workflow_id)
    except ImportError as exc:  # the viz extra is optional for evaluation
        ctx.log.warning("eval.rrd not written: %s", exc)
