"""The work of ``sim.rollout`` (see :mod:`osmo_plugins.sim.rollout` for its params)."""

from __future__ import annotations

import json
from pathlib import Path

from osmo.tasktypes.api import TaskContext
from osmo_plugins._base import find_folder_with
from osmo_plugins.episodes import EpisodeWriter
from osmo_plugins.lerobot.policy_io import POLICY_MARKER, frame_size
from osmo_plugins.sim.envs import EpisodeResult, make_env, run_episodes
from osmo_plugins.sim.policies import make_policy

__all__ = ["resolve_xml", "run", "shard_seeds"]


def shard_seeds(seed: int, shard: int, episodes: int) -> list[int]:
    """The episode seeds of one shard: disjoint across shards of the same size."""
    return [seed + shard * episodes + i for i in range(episodes)]


def resolve_xml(xml: str, ctx: TaskContext) -> Path | None:
    """The MuJoCo XML to load: absolute as given, relative to the first input that has it."""
    if not xml:
        return None
    path = Path(xml)
    if path.is_absolute():
        return path
    for folder in ctx.inputs:
        if (Path(folder) / path).is_file():
            return Path(folder) / path
    return path.resolve()


def run(ctx: TaskContext) -> None:
    """Roll out ``episodes`` episodes of this shard and write them to MCAP."""
    p = ctx.params
    if p["shard"] >= p["shards"]:
        raise ValueError(f"shard {p['shard']} is out of range for shards={p['shards']}")
    checkpoint = find_folder_with(ctx.inputs, POLICY_MARKER) if p["policy"] == "checkpoint" \
        else None
    seen = frame_size(checkpoint)  # a policy that sees frames needs a rendering env
    env = make_env(p["env"], xml_file=resolve_xml(p["xml"], ctx),
                   render=p["render"] or seen is not None, size=seen or p["size"],
                   max_steps=p["max_steps"] or None)
    policy = make_policy(p["policy"], env, env_id=p["env"], checkpoint=checkpoint,
                         noise=p["noise"])
    seeds = shard_seeds(p["seed"], p["shard"], p["episodes"])
    meta = {"env": p["env"], "xml": p["xml"], "policy": p["policy"], "noise": str(p["noise"]),
            "seed": str(p["seed"]), "shard": str(p["shard"]), "shards": str(p["shards"]),
            "episodes": str(p["episodes"]), "max_steps": str(p["max_steps"]),
            "obs_dim": str(env.observation_space.shape[0]),
            "action_dim": str(env.action_space.shape[0]),
            "fps": str(round(1.0 / env.unwrapped.dt, 6))}
    name = f"episodes-shard{p['shard']:03d}.mcap"
    ctx.log.info("shard %d/%d: %d %s episodes of %s (seeds %d..%d)", p["shard"] + 1,
                 p["shards"], len(seeds), p["policy"], p["env"], seeds[0], seeds[-1])

    def done(index: int, r: EpisodeResult) -> None:
        ctx.progress(index + 1, len(seeds), f"return {r.total_reward:.1f} in {r.length} steps")

    with EpisodeWriter.for_task(ctx, name, meta, dt=env.unwrapped.dt,
                                with_frames=p["render"]) as writer:
        results = run_episodes(env, policy, seeds, writer=writer, render=p["render"],
                               on_episode=done, cancelled=ctx.cancelled)
        ctx.check_cancelled()
    env.close()
    summary = {"meta": meta, "episodes": [r.__dict__ for r in results]}
    (Path(ctx.output) / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    mean = sum(r.total_reward for r in results) / len(results)
    ctx.log.info("wrote %s: %d episodes, mean return %.1f", name, len(results), mean)
