"""``sim.rollout``: run a policy in a gymnasium MuJoCo env and record the episodes as MCAP.

Params are declared here; the work is in :mod:`osmo_plugins.sim._rollout` (imported when the
task runs). One task writes one shard: ``episodes-shardNNN.mcap`` in the episode format of
:mod:`osmo_plugins.episodes`, plus ``summary.json``. Episode ``i`` of shard ``s`` uses seed
``seed + s * episodes + i``, so shards of one workflow never repeat a seed.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import SIM_PRELOAD, PluginType

__all__ = ["ROLLOUT"]

ROLLOUT = PluginType(
    name="sim.rollout",
    version="2",
    description="Roll out a policy in a gymnasium/MuJoCo env; episodes → MCAP (one per shard)",
    impl="osmo_plugins.sim._rollout:run",
    extra="sim",
    preload=SIM_PRELOAD,
    preload_env={"MUJOCO_GL": "disable"},
    resources={"cpu": 1, "memory": "1Gi"},
    params={
        "env": Param(str, "InvertedPendulum-v5", "gymnasium env id (MuJoCo v5 envs)"),
        "xml": Param(str, "", "MuJoCo XML for the env (xml_file); relative: in the first input"),
        "policy": Param(str, "expert", "who acts", choices=("random", "expert", "checkpoint")),
        "noise": Param(float, 0.0, "expert action noise (fraction of the range)", min=0),
        "episodes": Param(int, 10, "episodes in this shard", min=1),
        "seed": Param(int, 0, "base seed"),
        "max_steps": Param(int, 1000, "step limit per episode (0: the env's own)", min=0),
        "render": Param(bool, False, "record offscreen RGB frames (MUJOCO_GL=egl)"),
        "size": Param(int, 64, "frame width and height in pixels", min=16, max=512),
        "shard": Param(int, 0, "this shard's index", min=0),
        "shards": Param(int, 1, "number of shards", min=1),
    },
)
