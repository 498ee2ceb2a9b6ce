"""``osmo/ReacherVision-v0``: reaching that can only be learnt from pixels, and its expert.

gymnasium's Reacher-v5 (a 2-link arm in the plane, a target drawn at random within 0.2 of its
base, 50 steps of 0.02 s) with three changes, so that a policy must look at the camera:

- the observation is the arm's proprioception only — cos and sin of both joint angles and
  their velocities (6 numbers); the target's position appears only in the camera image;
- the camera looks straight down on the arena, and the target is drawn larger and pure red
  on a dark floor (``assets/reacher_vision.xml``), so it covers ~50 pixels at 64×64;
- ``info["is_success"]`` turns true once the fingertip has touched the target (centres within
  3 cm: the two spheres' radii) for 10 consecutive steps (0.2 s): reached and held, which
  random flailing does not do.

The reward is Reacher-v5's (minus the distance, minus the squared action). The env is
registered with gymnasium when :func:`osmo_plugins.sim.envs.make_env` first needs it; this
module imports gymnasium, so only code that runs a task imports it.

:class:`ReacherExpert` solves any Reacher-like model from its true state: inverse kinematics
of the two links (lengths read from the model) for the target, then joint velocity control.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.envs.mujoco.reacher_v5 import ReacherEnv
from gymnasium.spaces import Box

__all__ = ["ENV_ID", "HOLD_STEPS", "SUCCESS_RADIUS", "ReacherExpert", "ReacherVisionEnv",
           "register"]

ENV_ID = "osmo/ReacherVision-v0"
SUCCESS_RADIUS = 0.03
HOLD_STEPS = 10
XML = Path(__file__).parent / "assets" / "reacher_vision.xml"
TOP_DOWN = {"distance": 0.55, "elevation": -90.0, "azimuth": 90.0, "lookat": (0.0, 0.0, 0.0)}


def register() -> None:
    """Register :data:`ENV_ID` with gymnasium (once per process)."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="osmo_plugins.sim.reacher:ReacherVisionEnv",
                           max_episode_steps=50)


class ReacherVisionEnv(ReacherEnv):  # type: ignore[misc]
    """Reacher-v5 seen from above, observing only the arm (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("xml_file", str(XML))
        kwargs.setdefault("default_camera_config",
                          {**TOP_DOWN, "lookat": np.array(TOP_DOWN["lookat"])})
        super().__init__(**kwargs)
        self.observation_space = Box(-np.inf, np.inf, (6,), np.float64)
        self._held = 0

    def _get_obs(self) -> np.ndarray:
        theta = self.data.qpos[:2]
        return np.concatenate([np.cos(theta), np.sin(theta), self.data.qvel[:2]])

    def reset_model(self) -> np.ndarray:
        """Reacher-v5's reset (arm near straight, target anywhere within 0.2)."""
        self._held = 0
        return super().reset_model()

    def step(self, action: Any) -> Any:
        """Reacher-v5's step, plus ``info["is_success"]`` (reached and held)."""
        obs, reward, terminated, truncated, info = super().step(action)
        self._held = self._held + 1 if -info["reward_dist"] < SUCCESS_RADIUS else 0
        info["is_success"] = self._held >= HOLD_STEPS
        return obs, reward, terminated, truncated, info


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


class ReacherExpert:
    """Inverse kinematics to the target, then joint velocity control.

    It reads the true state, including the target, which the policy being taught never gets
    as a number.

    The joints are driven at a velocity proportional to their angle error, capped, rather
    than by a stiff PD: a PD's actions are one saturated jolt and then near zero, which
    leaves a demonstration almost nothing to learn the approach from; these spread the
    approach over ~20 steps (0.4 s) and still reach every target (return ≈ -3.9).

    Args:
        env: a Reacher-v5 or ReacherVision env (joints ``joint0``, ``joint1``, target joints
            ``target_x``, ``target_y``).
        noise: std of Gaussian noise added to each action (fraction of the range).
    """

    name = "expert"
    GAIN, MAX_SPEED, KV = 5.0, 10.0, 0.05  # 1/s, rad/s, action per rad/s

    def __init__(self, env: Any, noise: float = 0.0) -> None:
        base = env.unwrapped
        model = base.model
        self._data = base.data
        # link lengths: shoulder → elbow, elbow → fingertip, from the model itself
        self._l1 = float(np.linalg.norm(model.body("body1").pos[:2]))
        self._l2 = float(np.linalg.norm(model.body("fingertip").pos[:2]))
        self._q = [model.joint(n).qposadr[0] for n in ("joint0", "joint1")]
        self._v = [model.joint(n).dofadr[0] for n in ("joint0", "joint1")]
        self._target = [model.joint(n).qposadr[0] for n in ("target_x", "target_y")]
        self._noise = float(noise)
        self._rng = np.random.default_rng(0)

    def reset(self, seed: int) -> None:
        """Reseed the exploration noise."""
        self._rng = np.random.default_rng(seed)

    def _ik(self, x: float, y: float, elbow_now: float) -> tuple[float, float]:
        """Joint angles that put the fingertip at (x, y).

        Of the two elbow solutions, the one nearer the current elbow angle.
        """
        l1, l2 = self._l1, self._l2
        cos_elbow = np.clip((x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2), -1.0, 1.0)
        options = []
        for elbow in (float(np.arccos(cos_elbow)), -float(np.arccos(cos_elbow))):
            shoulder = np.arctan2(y, x) - np.arctan2(l2 * np.sin(elbow), l1 + l2 * np.cos(elbow))
            options.append((abs(elbow - elbow_now), float(shoulder), elbow))
        _, shoulder, elbow = min(options)
        return shoulder, elbow

    def act(self, observation: np.ndarray) -> np.ndarray:
        """Track a capped joint velocity towards the IK solution (plus noise), in [-1, 1]."""
        d = self._data
        q, v = d.qpos[self._q], d.qvel[self._v]
        shoulder, elbow = self._ik(float(d.qpos[self._target[0]]),
                                   float(d.qpos[self._target[1]]), float(q[1]))
        error = np.array([_wrap(shoulder - q[0]), elbow - q[1]])
        speed = np.clip(self.GAIN * error, -self.MAX_SPEED, self.MAX_SPEED)
        u = self.KV * (speed - v)
        if self._noise > 0:
            u = u + self._rng.normal(0.0, self._noise, size=u.shape)
        return np.clip(u, -1.0, 1.0).astype(np.float32)
