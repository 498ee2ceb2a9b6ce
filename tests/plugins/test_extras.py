"""The plugins' optional dependencies: a full install must really have them.

``./dev test`` sets ``OSMO_EXPECT_EXTRAS`` (e.g. ``sim,learn,viz``); then a missing or broken
extra fails here loudly instead of silently skipping the plugin tests. The core-only run
(``./dev test-core``) does not set it, and the plugin tests skip cleanly there.
"""

from __future__ import annotations

import importlib
import os

import pytest

MODULES = {
    "sim": ["numpy", "gymnasium", "mujoco", "foxglove", "google.protobuf"],
    "learn": ["torch", "lerobot", "lerobot.datasets", "lerobot.policies.act.modeling_act"],
    "viz": ["rerun"],
}
EXPECTED = [e for e in os.environ.get("OSMO_EXPECT_EXTRAS", "").split(",") if e]


def test_expected_extras_are_known() -> None:
    assert set(EXPECTED) <= set(MODULES), EXPECTED


@pytest.mark.skipif(not EXPECTED, reason="OSMO_EXPECT_EXTRAS is not set: a core-only run")
@pytest.mark.parametrize("module", [m for e in EXPECTED for m in MODULES[e]] or ["-"])
def test_extra_is_importable(module: str) -> None:
    importlib.import_module(module)
