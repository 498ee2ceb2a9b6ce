"""The built-in task types: registered as entry points, importable with the core alone."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import entry_points

import pytest

from osmo.tasktypes.api import Param, TaskType

NAMES = {"sim.rollout", "sim.eval", "lerobot.dataset", "lerobot.train", "viz.rerun"}
HEAVY = ("numpy", "gymnasium", "mujoco", "torch", "lerobot", "rerun")


def _points() -> dict[str, object]:
    return {ep.name: ep for ep in entry_points(group="osmo.task_types")}


def test_every_builtin_is_registered() -> None:
    assert NAMES <= set(_points())


@pytest.mark.parametrize("name", sorted(NAMES))
def test_entry_point_is_a_task_type(name: str) -> None:
    obj = _points()[name].load()  # type: ignore[attr-defined]
    assert isinstance(obj, TaskType)
    assert obj.name == name
    assert obj.extra in ("sim", "learn", "viz")
    # the entry point declares the same extra, so a type that fails to import still names it
    assert _points()[name].extras == [obj.extra]  # type: ignore[attr-defined]
    assert obj.description and obj.version
    for pname, param in obj.params.items():
        assert isinstance(param, Param), pname
        assert param.help, f"{name}.{pname} has no help"


def test_the_rerun_viewer_is_registered_and_loads_light() -> None:
    from osmo.tasktypes.viewers import Viewer, find_viewer

    viewer = find_viewer("rerun")
    assert isinstance(viewer, Viewer)
    assert (viewer.name, viewer.suffix) == ("rerun", ".rrd")


@pytest.mark.parametrize("group", ["osmo.task_types", "osmo.viewers"])
def test_loading_entry_points_imports_nothing_heavy(group: str) -> None:
    code = ("import sys\nfrom importlib.metadata import entry_points\n"
            f"[ep.load() for ep in entry_points(group={group!r})]\n"
            f"print([m for m in {HEAVY!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"
