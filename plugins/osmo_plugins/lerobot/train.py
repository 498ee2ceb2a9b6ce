"""``lerobot.train``: behaviour cloning of a small LeRobot ACT policy on CPU.

Reads the LeRobotDatasets made by ``lerobot.dataset`` (every input holding one, as one
dataset: shards converted by parallel tasks need no merge), trains for ``steps`` optimiser
steps with a fixed seed, and writes:

- ``checkpoint/``: the policy and its pre/post-processors saved the LeRobot way
  (``save_pretrained``; loads offline with ``from_pretrained``), plus ``osmo_policy.json``
  (env, true action width, training settings) that marks the folder for ``sim.eval``;
- ``loss.csv``, ``loss.json`` and ``loss.mcap`` (channel ``/train/loss``): the loss curve.

The default config is a small ACT (one encoder and one decoder layer, no VAE, chunk of 10,
re-planned every step); no pretrained weights are ever downloaded.
"""

from __future__ import annotations

from osmo.tasktypes.api import Param
from osmo_plugins._base import PluginType

__all__ = ["TRAIN"]

TRAIN = PluginType(
    name="lerobot.train",
    version="3",
    description="Train a small LeRobot ACT policy (behaviour cloning) on CPU; checkpoint + loss",
    impl="osmo_plugins.lerobot._train:run",
    extra="learn",
    resources={"cpu": 1, "memory": "4Gi"},
    params={
        "steps": Param(int, 1500, "optimiser steps", min=1),
        "batch_size": Param(int, 64, "batch size", min=1),
        "lr": Param(float, 1e-3, "learning rate", min=0),
        "lr_schedule": Param(str, "constant", "constant, or cosine decay to 0 over the steps",
                             choices=("constant", "cosine")),
        "seed": Param(int, 0, "seed for weights, batches and dropout"),
        "chunk_size": Param(int, 10, "ACT action chunk length", min=1),
        "n_action_steps": Param(int, 1, "actions executed per policy query", min=1),
        "dim_model": Param(int, 64, "transformer width", min=8),
        "log_every": Param(int, 25, "record the loss every N steps", min=1),
        # Intra-op threads only slow a model this small down (and fight other tasks).
        "threads": Param(int, 1, "torch CPU threads (0: torch's default)", min=0),
    },
)
