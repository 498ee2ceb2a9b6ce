"""Making gymnasium MuJoCo envs for the sim plugins, and running episodes into MCAP.

Imports gymnasium and mujoco only inside functions, so the task-type objects that import this
module stay importable without the ``sim`` extra. Offscreen rendering uses ``MUJOCO_GL=egl``
unless the environment already says otherwise; when EGL cannot render, osmesa is tried and
then a clear error names both.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from osmo.errors import MissingExtra
from osmo_plugins.episodes import EpisodeWriter

__all__ = ["OSMO_ENVS", "SUCCESS_KEYS", "EpisodeResult", "MissingExtra", "make_env", "require",
           "run_episodes"]

OSMO_ENVS = ("osmo/ReachVision-v1",)
"""Env ids osmo itself provides (registered with gymnasium when first made)."""

SUCCESS_KEYS = ("is_success", "success")
"""``info`` keys an env may use for its own success signal, in order of preference."""


def require(module: str, extra: str) -> Any:
    """Import ``module`` or raise :class:`MissingExtra` naming ``pip install "osmo[extra]"``."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(f"this task type needs {module!r}, which is not installed: "
                           f'pip install "osmo[{extra}]" ({exc})') from exc


@dataclass(frozen=True)
class EpisodeResult:
    """What one episode came to.

    ``signal`` names the env's own success key (``is_success`` or ``success`` in ``info``)
    when the env reported one; ``success`` is then true when any step reported success.
    """

    seed: int
    total_reward: float
    length: int
    terminated: bool
    truncated: bool
    success: bool | None = None
    signal: str | None = None


def make_env(env_id: str, *, xml_file: str | Path | None = None, render: bool = False,
             size: int = 64, max_steps: int | None = None) -> Any:
    """``gymnasium.make`` an env, optionally from a MuJoCo XML and with offscreen frames."""
    if render:
        os.environ.setdefault("MUJOCO_GL", "egl")
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    gym = require("gymnasium", "sim")
    require("mujoco", "sim")
    if env_id in OSMO_ENVS:
        from osmo_plugins.sim import reach_vision

        reach_vision.register()
    kwargs: dict[str, Any] = {}
    if xml_file:
        path = Path(xml_file).resolve()
        if not path.is_file():
            raise FileNotFoundError(f"MuJoCo XML {path} does not exist")
        kwargs["xml_file"] = str(path)
    if render:
        kwargs.update(render_mode="rgb_array", width=size, height=size)
    if max_steps:
        kwargs["max_episode_steps"] = int(max_steps)
    try:
        env = gym.make(env_id, **kwargs)
    except gym.error.Error as exc:
        raise ValueError(f"cannot make env {env_id!r}: {exc}") from exc
    if render:
        _check_render(env)
    return env


def _check_render(env: Any) -> None:
    env.reset(seed=0)
    try:
        frame = env.render()
    except Exception as exc:  # noqa: BLE001 - GL backends fail with many types
        raise RuntimeError(
            f"offscreen rendering failed with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: {exc}. "
            "Install EGL (apt-get install libegl1) or OSMesa (apt-get install libosmesa6 and "
            "set MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa), or run with render: false"
        ) from exc
    if frame is None or np.asarray(frame).ndim != 3:
        raise RuntimeError("the env rendered no RGB frame; run with render: false")


def run_episodes(env: Any, policy: Any, seeds: Sequence[int], *,
                 writer: EpisodeWriter | None = None, render: bool = False,
                 first_index: int = 0,
                 on_episode: Callable[[int, EpisodeResult], None] | None = None,
                 cancelled: Callable[[], bool] = lambda: False) -> list[EpisodeResult]:
    """Run one episode per seed with ``policy``, recording each step when ``writer`` is set.

    Episodes end at termination or at the env's time limit (truncation). ``on_episode`` is
    called after each one; ``cancelled`` is polled between episodes.
    """
    results: list[EpisodeResult] = []
    for n, seed in enumerate(seeds):
        if cancelled():
            break
        index = first_index + n
        obs, _ = env.reset(seed=int(seed))
        policy.reset(int(seed))
        total, t, terminated, truncated = 0.0, 0, False, False
        key: str | None = None
        success: bool | None = None
        while not (terminated or truncated):
            action = policy.act(obs)
            frame = env.render() if render else None
            next_obs, reward, terminated, truncated, info = env.step(action)
            if t == 0:  # an env that has a success signal reports it from the first step
                key = next((k for k in SUCCESS_KEYS if k in info), None)
            if key is not None:
                success = bool(success) or bool(info.get(key))
            if writer is not None:
                writer.step(index, t, obs, action, float(reward), terminated, truncated, frame)
            total += float(reward)
            t += 1
            obs = next_obs
        result = EpisodeResult(int(seed), total, t, bool(terminated), bool(truncated),
                               success, key)
        if writer is not None:
            writer.end(index, int(seed), total, t, terminated, truncated)
        results.append(result)
        if on_episode is not None:
            on_episode(index, result)
    return results
