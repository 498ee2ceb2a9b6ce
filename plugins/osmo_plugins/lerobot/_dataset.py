"""The work of ``lerobot.dataset`` (params in :mod:`osmo_plugins.lerobot.dataset`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from osmo.tasktypes.api import TaskContext
from osmo_plugins._base import offline
from osmo_plugins.episodes import Episode, episode_files, read_episodes
from osmo_plugins.sim.envs import require

__all__ = ["DATASET_MARKER", "dataset_root", "features_for", "pad", "run"]

DATASET_MARKER = "osmo_dataset.json"
STATE, ENV_STATE, ACTION, CAMERA = ("observation.state", "observation.environment_state",
                                    "action", "observation.images.camera")


def pad(values: np.ndarray, width: int) -> np.ndarray:
    """Zero-pad the last axis of ``values`` to ``width``."""
    extra = width - values.shape[-1]
    if extra <= 0:
        return values
    return np.concatenate([values, np.zeros((*values.shape[:-1], extra), values.dtype)], -1)


def features_for(obs_dim: int, act_dim: int, frame_shape: tuple[int, ...] | None,
                 min_dims: int) -> dict[str, Any]:
    """LeRobot feature specs.

    The state is stored twice: ACT needs an image or an ``environment_state`` input, and
    state-only datasets have no image.
    """
    o, a = max(obs_dim, min_dims), max(act_dim, min_dims)
    feats: dict[str, Any] = {
        STATE: {"dtype": "float32", "shape": (o,), "names": [f"s{i}" for i in range(o)]},
        ENV_STATE: {"dtype": "float32", "shape": (o,), "names": [f"s{i}" for i in range(o)]},
        ACTION: {"dtype": "float32", "shape": (a,), "names": [f"a{i}" for i in range(a)]},
    }
    if frame_shape is not None:
        feats[CAMERA] = {"dtype": "image", "shape": frame_shape,
                         "names": ["height", "width", "channels"]}
    return feats


def _load(ctx: TaskContext) -> list[Episode]:
    files = episode_files(list(ctx.inputs))
    if not files:
        raise ValueError("no .mcap episode files in the inputs (expected sim.rollout outputs)")
    episodes = [ep for f in files for ep in read_episodes(f)]
    envs = {ep.meta.get("env", "?") for ep in episodes}
    if len(envs) > 1:
        raise ValueError(f"episodes from several envs cannot share a dataset: {sorted(envs)}")
    return episodes


def dataset_root(source: Path, info: dict[str, Any]) -> Path:
    """The LeRobotDataset folder an ``osmo_dataset.json`` in ``source`` names: inside it only."""
    root = info.get("root")
    if not isinstance(root, str) or not root or root in (".", "..") or "/" in root \
            or "\\" in root or not (source / root).is_dir():
        raise ValueError(f"{source / DATASET_MARKER}: 'root' must name a folder beside it, "
                         f"not {root!r}")
    return source / root


def run(ctx: TaskContext) -> None:
    """Convert every episode of every input into one LeRobotDataset."""
    offline()
    require("lerobot", "learn")
    from lerobot.datasets import LeRobotDataset

    p = ctx.params
    episodes = _load(ctx)
    first = episodes[0]
    obs_dim, act_dim = first.observations.shape[1], first.actions.shape[1]
    use_images = p["images"] and all(ep.frames is not None for ep in episodes)
    frame_shape = tuple(first.frames.shape[1:]) if use_images and first.frames is not None \
        else None
    fps = int(round(float(first.meta.get("fps", "25"))))
    feats = features_for(obs_dim, act_dim, frame_shape, p["min_dims"])
    root = Path(ctx.output) / "dataset"
    # PNG writing in threads roughly doubles the frames per second with images.
    ds = LeRobotDataset.create(repo_id=p["repo_id"], fps=fps, features=feats, root=root,
                               robot_type="mujoco", use_videos=False, video_backend="pyav",
                               image_writer_threads=p["image_threads"] if frame_shape else 0)
    frames = 0
    for n, ep in enumerate(episodes):
        ctx.check_cancelled()
        obs = pad(ep.observations, feats[STATE]["shape"][0])
        act = pad(ep.actions, feats[ACTION]["shape"][0])
        for t in range(ep.length):
            frame: dict[str, Any] = {STATE: obs[t], ENV_STATE: obs[t], ACTION: act[t],
                                     "task": p["task"]}
            if frame_shape is not None and ep.frames is not None:
                frame[CAMERA] = ep.frames[t]
            ds.add_frame(frame)
        ds.save_episode()
        frames += ep.length
        ctx.progress(n + 1, len(episodes), f"{frames} frames")
    ds.finalize()
    info = {"env": first.meta.get("env"), "obs_dim": obs_dim, "action_dim": act_dim,
            "padded_action_dim": feats[ACTION]["shape"][0], "fps": fps,
            "episodes": len(episodes), "frames": frames, "images": frame_shape is not None,
            "image_size": int(frame_shape[0]) if frame_shape else None,
            "repo_id": p["repo_id"], "root": "dataset",
            "mean_return": float(np.mean([ep.total_reward for ep in episodes]))}
    (Path(ctx.output) / DATASET_MARKER).write_text(json.dumps(info, indent=1) + "\n")
    ctx.log.info("LeRobotDataset with %d episodes, %d frames%s", len(episodes), frames,
                 " and images" if frame_shape else "")
