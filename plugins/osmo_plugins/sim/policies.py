"""Policies that drive a gymnasium env: ``random``, ``expert`` and ``checkpoint``.

A policy is anything with ``reset(seed)`` and ``act(observation) -> action`` (numpy). The
experts read the env's true MuJoCo state. For the inverted pendulums, LQR: it linearises the
env's own model about its upright rest pose (central differences of ``mj_step``), folds in
the env's frame skip and solves the discrete-time LQR, so it works on any pendulum XML passed
to the env, not only the stock one. For Reacher-v5, inverse kinematics plus joint velocity
control (:mod:`osmo_plugins.sim.reacher`); for osmo/ReachVision-v1, the inverse-kinematics
pose as a position command (:mod:`osmo_plugins.sim.reach_vision`). A ``checkpoint`` policy is
a LeRobot policy saved by ``lerobot.train`` (loaded lazily: importing this module needs numpy
only; gymnasium/mujoco/torch are imported when used).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np

__all__ = ["EXPERT_ENVS", "ExpertPolicy", "Policy", "RandomPolicy", "has_expert", "linearize",
           "lqr_gain", "make_policy"]

EXPERT_ENVS = ("InvertedPendulum", "InvertedDoublePendulum", "Reacher", "osmo/ReachVision")
"""Env families (id without the ``-vN`` suffix) that have an expert."""


class Policy(Protocol):
    """What a rollout needs from a policy."""

    name: str

    def reset(self, seed: int) -> None:
        """Start an episode (reseed any randomness)."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The action for this observation."""


class RandomPolicy:
    """Uniform samples from the env's action space, seeded per episode."""

    name = "random"

    def __init__(self, env: Any) -> None:
        self._space = env.action_space

    def reset(self, seed: int) -> None:
        """Reseed the action space."""
        self._space.seed(seed)

    def act(self, observation: np.ndarray) -> np.ndarray:
        """A random action."""
        return np.asarray(self._space.sample(), dtype=np.float32)


def lqr_gain(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray,
             iterations: int = 5000) -> np.ndarray:
    """The discrete-time LQR gain K (u = -K x) by iterating the Riccati equation."""
    p = q.copy()
    for _ in range(iterations):
        k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
        p_next = q + a.T @ p @ (a - b @ k)
        if np.allclose(p_next, p, rtol=1e-10, atol=1e-10):
            p = p_next
            break
        p = p_next
    return np.asarray(np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a))


def linearize(model: Any, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """One ``mj_step`` linearised about the rest pose by central differences.

    The rest pose is qpos0 with zero velocity and control. It works with any integrator
    (``mjd_transitionFD`` rejects RK4).
    """
    import mujoco

    data = mujoco.MjData(model)
    nq, nv, nu = model.nq, model.nv, model.nu
    if nq != nv:
        raise ValueError("the LQR expert needs a model without free or ball joints")

    def step(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        mujoco.mj_resetData(model, data)
        data.qpos[:] = model.qpos0 + x[:nq]
        data.qvel[:] = x[nq:]
        data.ctrl[:] = u
        mujoco.mj_step(model, data)
        return np.concatenate([data.qpos - model.qpos0, data.qvel])

    x0, u0 = np.zeros(nq + nv), np.zeros(nu)
    a = np.stack([(step(x0 + e, u0) - step(x0 - e, u0)) / (2 * eps)
                  for e in np.eye(nq + nv) * eps], axis=1)
    b = np.stack([(step(x0, u0 + e) - step(x0, u0 - e)) / (2 * eps)
                  for e in np.eye(nu) * eps], axis=1)
    return a, b


class ExpertPolicy:
    """LQR about the upright pose, from the env's MuJoCo model; reads the true state.

    Args:
        env: a gymnasium MuJoCo env of an :data:`EXPERT_ENVS` family.
        noise: std of Gaussian noise added to each action (as a fraction of the action
            range), to spread demonstrations over more states.
    """

    name = "expert"

    def __init__(self, env: Any, noise: float = 0.0) -> None:
        base = env.unwrapped
        a, b = linearize(base.model)
        skip = int(getattr(base, "frame_skip", 1))
        a_env, b_env = np.eye(a.shape[0]), np.zeros(b.shape)
        for _ in range(skip):  # zero-order hold over the env's frame skip
            a_env, b_env = a @ a_env, a @ b_env + b
        nx, nv = a.shape[0], base.model.nv
        q = np.eye(nx)
        q[:nv, :nv] *= 10.0  # positions (angles) matter most
        self._k = lqr_gain(a_env, b_env, q, np.eye(b.shape[1]) * 0.1)
        self._base = base
        self._low = np.asarray(env.action_space.low, dtype=np.float64)
        self._high = np.asarray(env.action_space.high, dtype=np.float64)
        self._noise = float(noise)
        self._rng = np.random.default_rng(0)
        self._qpos0 = base.model.qpos0.copy()

    def reset(self, seed: int) -> None:
        """Reseed the exploration noise."""
        self._rng = np.random.default_rng(seed)

    def act(self, observation: np.ndarray) -> np.ndarray:
        """``-K x`` (plus noise), clipped to the action range."""
        d = self._base.data
        x = np.concatenate([d.qpos - self._qpos0, d.qvel])
        u = -self._k @ x
        if self._noise > 0:
            u = u + self._rng.normal(0.0, self._noise, size=u.shape) * (self._high - self._low) / 2
        return np.clip(u, self._low, self._high).astype(np.float32)


def make_policy(kind: str, env: Any, *, env_id: str, checkpoint: Path | None = None,
                noise: float = 0.0) -> Policy:
    """Build a policy by name for ``env``.

    Raises:
        ValueError: ``expert`` for an env with no expert, or ``checkpoint`` without a folder.
    """
    if kind == "random":
        return RandomPolicy(env)
    if kind == "expert":
        if env_id.split("-")[0] not in EXPERT_ENVS:
            raise ValueError(f"no expert policy for {env_id}; experts exist for "
                             f"{', '.join(EXPERT_ENVS)} (use policy: random or checkpoint)")
        if env_id.startswith("osmo/ReachVision"):
            from osmo_plugins.sim.reach_vision import ReachVisionExpert

            return ReachVisionExpert(env, noise=noise)
        if "Reacher" in env_id:
            from osmo_plugins.sim.reacher import ReacherExpert

            return ReacherExpert(env, noise=noise)
        return ExpertPolicy(env, noise=noise)
    if kind == "checkpoint":
        if checkpoint is None:
            raise ValueError("policy: checkpoint needs a trained checkpoint folder as an input "
                             "(the output of a lerobot.train task)")
        from osmo_plugins.lerobot.policy_io import CheckpointPolicy

        return CheckpointPolicy(checkpoint, env)
    raise ValueError(f"unknown policy {kind!r}: use random, expert or checkpoint")


def has_expert(env_id: str) -> bool:
    """True when :func:`make_policy` can build an expert for ``env_id``."""
    return env_id.split("-")[0] in EXPERT_ENVS
