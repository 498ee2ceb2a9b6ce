"""``sim.eval``: a fixed-seed evaluation suite of policies × envs, with metrics.

Every policy runs the same episode seeds on every env. ``policies`` lists ``checkpoint``
(every trained checkpoint among the inputs, named after the task that made it), ``random``
and ``expert`` (skipped, with a log line, on envs that have none). Writes:

- ``metrics.json``: per policy and env, success rate, mean return with a 95% confidence
  interval (Student t), mean episode length, and the per-episode returns;
- ``rollouts/<policy>--<env>.mcap``: every evaluation episode (the episode format);
- ``eval.rrd``: the same episodes as a rerun recording (when the ``viz`` extra is installed).

Success means the episode ran to the step limit without terminating (the pole stayed up,
the hopper did not fall): the natural bar for envs that end on failure.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import PluginType

__all__ = ["EVAL"]

EVAL = PluginType(
    name="sim.eval",
    version="1",
    description="Evaluate checkpoints and baselines on fixed seeds × envs → metrics, MCAP, .rrd",
    impl="osmo_plugins.sim._eval:run",
    extra="sim",
    resources={"cpu": 1, "memory": "2Gi"},
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
    },
)
