"""Loading a checkpoint written by ``lerobot.train`` as a policy for gymnasium envs.

Imports torch and lerobot only when a :class:`CheckpointPolicy` is made. The folder holds the
LeRobot policy and processors (``save_pretrained``) and ``osmo_policy.json``, which gives the
env's true action width (the dataset pads 1-D actions) and whether frames are an input.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["POLICY_MARKER", "CheckpointPolicy", "frame_size"]

POLICY_MARKER = "osmo_policy.json"
"""The file that marks a checkpoint folder written by ``lerobot.train``."""


def frame_size(folder: Path | None) -> int | None:
    """The camera frame size a checkpoint was trained on, or None for a state-only one.

    Its env must then be made with ``render=True`` at that size.
    """
    if folder is None:
        return None
    info = json.loads((Path(folder) / POLICY_MARKER).read_text())
    return int(info.get("image_size") or 64) if info.get("images") else None


class CheckpointPolicy:
    """A trained LeRobot policy acting in a gymnasium env (CPU, offline).

    Args:
        folder: the checkpoint folder (holding ``osmo_policy.json``).
        env: the env it acts in (for frames when the policy sees images).
    """

    name = "checkpoint"

    def __init__(self, folder: Path, env: Any) -> None:
        from osmo_plugins._base import offline
        from osmo_plugins.sim.envs import require

        offline()
        self._torch = require("torch", "learn")
        require("lerobot", "learn")
        from lerobot.policies.act.modeling_act import ACTPolicy
        from lerobot.policies.factory import make_pre_post_processors

        self.info = json.loads((Path(folder) / POLICY_MARKER).read_text())
        self._policy = ACTPolicy.from_pretrained(str(folder), local_files_only=True)
        self._policy.eval()
        self._pre, self._post = make_pre_post_processors(
            self._policy.config, pretrained_path=str(folder))
        self._width = int(self._policy.config.input_features["observation.state"].shape[0])
        self._act_dim = int(self.info["action_dim"])
        self._env = env

    def reset(self, seed: int) -> None:
        """Clear the action queue and seed torch."""
        self._torch.manual_seed(seed)
        self._policy.reset()

    def act(self, observation: np.ndarray) -> np.ndarray:
        """One ``select_action`` call; the padding is cut off the action."""
        torch = self._torch
        obs: np.ndarray = np.zeros(self._width, dtype=np.float32)
        flat = np.asarray(observation, dtype=np.float32).ravel()
        obs[: flat.shape[0]] = flat
        state = torch.from_numpy(obs).unsqueeze(0)
        batch = {"observation.state": state, "observation.environment_state": state.clone()}
        if self.info.get("images"):
            frame = np.asarray(self._env.render(), dtype=np.float32) / 255.0
            batch["observation.images.camera"] = torch.from_numpy(frame).permute(2, 0, 1)[None]
        with torch.inference_mode():
            action = self._post(self._policy.select_action(self._pre(batch)))
        return np.asarray(action.squeeze(0).cpu().numpy()[: self._act_dim], dtype=np.float32)
