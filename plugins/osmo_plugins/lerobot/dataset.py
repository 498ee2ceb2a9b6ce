"""``lerobot.dataset``: MCAP episodes from every input (e.g. rollout shards) → a LeRobotDataset.

The dataset (v3 layout: parquet + ``meta/``) is written offline under ``dataset/`` in the
output, with ``osmo_dataset.json`` beside it saying where it came from and how actions were
padded: LeRobot stores a ``(1,)`` feature as a scalar, which breaks ACT, so actions (and
observations) narrower than ``min_dims`` are zero-padded and the true width is recorded.
With ``images: true`` and frames in the episodes, frames become ``observation.images.camera``.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import PluginType

__all__ = ["DATASET"]

DATASET = PluginType(
    name="lerobot.dataset",
    version="1",
    description="MCAP episodes from the inputs → a LeRobotDataset (v3) folder, offline",
    impl="osmo_plugins.lerobot._dataset:run",
    extra="learn",
    resources={"cpu": 1, "memory": "2Gi"},
    params={
        "repo_id": Param(str, "osmo/episodes", "the dataset's repo id (name only; offline)"),
        "task": Param(str, "balance the pole", "the language task stored with every frame"),
        "images": Param(bool, True, "include camera frames when the episodes have them"),
        "min_dims": Param(int, 2, "pad vector features narrower than this", min=1),
        "image_threads": Param(int, 2, "threads writing PNG frames", min=1, max=16),
    },
)
