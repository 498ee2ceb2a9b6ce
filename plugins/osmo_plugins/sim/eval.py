"""``sim.eval``: a fixed-seed evaluation suite of policies × envs, with metrics.

Every policy runs the same episode seeds on every env. ``policies`` lists ``checkpoint``
(every trained checkpoint among the inputs, named after the task that made it), ``random``
and ``expert`` (skipped, with a log line, on envs that have none). Writes:

- ``metrics.json``: per policy and env, the success rate and the criterion it used, mean
  return with a 95% confidence interval (Student t), the normalised score, mean episode
  length, and the per-episode returns;
- ``rollouts/<policy>--<env>.mcap``: every evaluation episode (the episode format);
- ``eval.rrd``: the same episodes as a rerun recording (when the ``viz`` extra is installed).

Success is defined per env (:mod:`osmo_plugins.sim.metrics`): the env's own
``info["is_success"]``/``info["success"]``, else a return threshold (``success:
{return_at_least: X}`` for every env, ``success: {ENV: {return_at_least: X}}`` for one, else
gymnasium's ``reward_threshold`` when the suite runs the env's registered episode length),
else no success rate at all (``null``, shown as ``n/a``). The normalised score is ``(return -
random) / (expert - random)`` on envs where both baselines ran in this suite.

Its report (``osmo eval report``) is the leaderboard of :mod:`osmo_plugins.sim.report`.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import ACT_PRELOAD, HF_ENV, SIM_PRELOAD, PluginType
from osmo_plugins.sim.report import LEADERBOARD

__all__ = ["EVAL"]

EVAL = PluginType(
    name="sim.eval",
    version="2",
    description="Evaluate checkpoints and baselines on fixed seeds × envs → metrics, MCAP, .rrd",
    impl="osmo_plugins.sim._eval:run",
    extra="sim",
    preload=(*SIM_PRELOAD, *ACT_PRELOAD, "osmo_plugins.lerobot.policy_io"),
    preload_env={"MUJOCO_GL": "disable", **HF_ENV},
    resources={"cpu": 1, "memory": "2Gi"},
    report=LEADERBOARD,
    params={
        "envs": Param(list, ["InvertedPendulum-v5"], "gymnasium env ids"),
        "policies": Param(list, ["checkpoint", "random"],
                          "checkpoint (each one in the inputs), random, expert"),
        "episodes": Param(int, 10, "episodes per policy and env", min=1),
        "seed": Param(int, 10_000, "first seed (episode i uses seed + i)"),
        "max_steps": Param(int, 1000, "step limit per episode", min=1),
        "record": Param(bool, True, "write the evaluation episodes as MCAP"),
        "rrd": Param(bool, True, "write eval.rrd (needs the viz extra)"),
        "threads": Param(int, 1, "torch CPU threads for checkpoints", min=0),
        "success": Param(dict, {}, "return thresholds: {return_at_least: X} and/or "
                         "{ENV: {return_at_least: X}} (else the env's signal or gymnasium's)"),
    },
)
