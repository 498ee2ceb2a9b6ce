"""``viz.rerun``: turn MCAP files from the task's inputs into rerun ``.rrd`` recordings.

Writes one ``<name>.rrd`` per input MCAP file (episode files get per-episode plots and camera
images; any other MCAP goes through rerun's own loader), or a single ``combined.rrd`` with
``combine: true``. No viewer is started.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import PluginType

__all__ = ["RERUN"]

RERUN = PluginType(
    name="viz.rerun",
    version="1",
    description="MCAP files from the inputs → rerun .rrd recordings (no viewer)",
    impl="osmo_plugins.viz._rerun_task:run",
    extra="viz",
    resources={"cpu": 1, "memory": "1Gi"},
    params={
        "combine": Param(bool, False, "one combined.rrd instead of one file per MCAP"),
        "pattern": Param(str, "*.mcap", "which files of the inputs to convert (glob)"),
    },
)
