"""An expert for gymnasium's ``Reacher-v5``, and the two-link inverse kinematics it shares.

:class:`ReacherExpert` solves a torque-driven Reacher from its true state: inverse kinematics
of the two links (lengths read from the model) for the target, then joint velocity control.
``osmo/ReachVision-v1`` (:mod:`osmo_plugins.sim.reach_vision`) commands the same inverse
kinematics as joint positions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["ReacherExpert", "two_link_ik"]


def two_link_ik(l1: float, l2: float, x: float, y: float,
                elbow_sign: float) -> tuple[float, float]:
    """Shoulder and elbow angles that put a planar two-link arm's tip at (x, y).

    ``elbow_sign`` picks the solution: the elbow angle has that sign (a point out of reach
    gives the nearest pose on the line to it). The shoulder angle is not wrapped.
    """
    cos_elbow = np.clip((x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2), -1.0, 1.0)
    elbow = float(np.copysign(np.arccos(cos_elbow), elbow_sign))
    shoulder = np.arctan2(y, x) - np.arctan2(l2 * np.sin(elbow), l1 + l2 * np.cos(elbow))
    return float(shoulder), elbow


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
        env: a Reacher-v5 env (joints ``joint0``, ``joint1``, target joints
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
        """Joint angles that put the fingertip at (x, y), the elbow solution nearer now's."""
        options = [two_link_ik(self._l1, self._l2, x, y, sign) for sign in (1.0, -1.0)]
        return min(options, key=lambda q: abs(q[1] - elbow_now))

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
