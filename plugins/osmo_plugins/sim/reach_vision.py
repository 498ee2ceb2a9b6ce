"""``osmo/ReachVision-v1``: reaching that can only be learnt from pixels, and its expert.

A 2-link arm in the plane seen from above (gymnasium's Reacher-v5 model: links of 0.1 and
0.11, 50 steps of 0.02 s), given as MJCF in ``assets/reach_vision.xml``, with four changes so
that a policy must look at the camera and has something learnable to look for:

- **position actuators**: the action is the pair of joint angles to servo to (absolute
  targets, scaled to [-1, 1] over each actuator's ctrl range), not torques. The expert's
  action is then the inverse-kinematics solution for the target, held for the whole episode,
  which does not fade to zero near the goal as a torque or velocity command does;
- the observation is the arm's proprioception only — cos and sin of both joint angles and
  their velocities (6 numbers); the target's position appears only in the camera image,
  where it is drawn larger and pure red on a dark floor (~50 pixels at 64×64);
- targets are drawn uniformly at 0.05–0.2 from the base, in the three quarters of the disk
  in front of it (polar angle within ±135°): there the elbow-up solution is one continuous
  function of the target, with no 2π jump in the shoulder angle a policy would have to learn;
- ``info["is_success"]`` turns true once the fingertip has been within 3 cm of the target's
  centre (the two spheres touch) for 10 consecutive steps (0.2 s): reached and held.

The reward is minus the fingertip's distance to the target (an action costs nothing: every
action is a pose). The env is registered with gymnasium when
:func:`osmo_plugins.sim.envs.make_env` first needs it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.envs.mujoco.reacher_v5 import ReacherEnv
from gymnasium.spaces import Box

from osmo_plugins.sim.reacher import two_link_ik

__all__ = ["ENV_ID", "HOLD_STEPS", "SUCCESS_RADIUS", "ReachVisionEnv", "ReachVisionExpert",
           "register"]

ENV_ID = "osmo/ReachVision-v1"
SUCCESS_RADIUS = 0.03
HOLD_STEPS = 10
TARGET_RADII = (0.05, 0.2)
TARGET_MAX_ANGLE = 0.75 * np.pi
XML = Path(__file__).parent / "assets" / "reach_vision.xml"
TOP_DOWN = {"distance": 0.55, "elevation": -90.0, "azimuth": 90.0, "lookat": (0.0, 0.0, 0.0)}


def register() -> None:
    """Register :data:`ENV_ID` with gymnasium (once per process)."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="osmo_plugins.sim.reach_vision:ReachVisionEnv",
                           max_episode_steps=50)


class ReachVisionEnv(ReacherEnv):  # type: ignore[misc]
    """The position-controlled arm seen from above (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("xml_file", str(XML))
        kwargs.setdefault("default_camera_config",
                          {**TOP_DOWN, "lookat": np.array(TOP_DOWN["lookat"])})
        kwargs.setdefault("reward_control_weight", 0.0)
        super().__init__(**kwargs)
        self.observation_space = Box(-np.inf, np.inf, (6,), np.float64)
        self.action_space = Box(-1.0, 1.0, (2,), np.float32)
        ranges = self.model.actuator_ctrlrange
        self._low, self._high = ranges[:, 0].copy(), ranges[:, 1].copy()
        self._held = 0

    def to_ctrl(self, action: Any) -> np.ndarray:
        """Joint angles (radians) for an action in [-1, 1] (clipped into the range)."""
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        return np.asarray(self._low + (a + 1.0) / 2.0 * (self._high - self._low))

    def to_action(self, angles: Any) -> np.ndarray:
        """The action that commands these joint angles (the inverse of :meth:`to_ctrl`)."""
        a = 2.0 * (np.asarray(angles, dtype=np.float64) - self._low) / (self._high - self._low)
        return np.clip(a - 1.0, -1.0, 1.0).astype(np.float32)

    def _get_obs(self) -> np.ndarray:
        theta = self.data.qpos[:2]
        return np.concatenate([np.cos(theta), np.sin(theta), self.data.qvel[:2]])

    def reset_model(self) -> np.ndarray:
        """The arm near straight (as Reacher-v5), the target drawn as the docstring says."""
        self._held = 0
        qpos = self.init_qpos + self.np_random.uniform(-0.1, 0.1, size=self.model.nq)
        while True:
            goal = self.np_random.uniform(-TARGET_RADII[1], TARGET_RADII[1], size=2)
            radius, angle = float(np.linalg.norm(goal)), float(np.arctan2(goal[1], goal[0]))
            if TARGET_RADII[0] <= radius <= TARGET_RADII[1] and abs(angle) <= TARGET_MAX_ANGLE:
                break
        self.goal = goal
        qpos[-2:] = goal
        qvel = self.init_qvel + self.np_random.uniform(-0.005, 0.005, size=self.model.nv)
        qvel[-2:] = 0
        self.set_state(qpos, qvel)
        return self._get_obs()

    def step(self, action: Any) -> Any:
        """Servo to the commanded angles; ``info["is_success"]`` once reached and held."""
        obs, reward, terminated, truncated, info = super().step(self.to_ctrl(action))
        self._held = self._held + 1 if -info["reward_dist"] < SUCCESS_RADIUS else 0
        info["is_success"] = self._held >= HOLD_STEPS
        return obs, reward, terminated, truncated, info


class ReachVisionExpert:
    """Commands the inverse-kinematics pose for the target, elbow bent the positive way.

    It reads the true target, which the policy being taught never gets as a number.

    Args:
        env: an ``osmo/ReachVision-v1`` env.
        noise: std of Gaussian noise added to each action (fraction of the range).
    """

    name = "expert"

    def __init__(self, env: Any, noise: float = 0.0) -> None:
        self._env = env.unwrapped
        model = self._env.model
        self._l1 = float(np.linalg.norm(model.body("body1").pos[:2]))
        self._l2 = float(np.linalg.norm(model.body("fingertip").pos[:2]))
        self._target = [model.joint(n).qposadr[0] for n in ("target_x", "target_y")]
        self._noise = float(noise)
        self._rng = np.random.default_rng(0)

    def reset(self, seed: int) -> None:
        """Reseed the exploration noise."""
        self._rng = np.random.default_rng(seed)

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The target's joint angles as an action in [-1, 1] (plus noise)."""
        x, y = (float(self._env.data.qpos[i]) for i in self._target)
        shoulder, elbow = two_link_ik(self._l1, self._l2, x, y, elbow_sign=1.0)
        action = self._env.to_action([shoulder, elbow]).astype(np.float64)
        if self._noise > 0:
            action = action + self._rng.normal(0.0, self._noise, size=action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32)
