"""Saving and loading trained LeRobot policies as osmo checkpoints (torch imported lazily)."""

from __future__ import annotations

POLICY_MARKER = "osmo_policy.json"
"""The file that marks a checkpoint folder written by ``lerobot.train``."""
