"""Resolving task types: entry points (a real dist-info on sys.path) and module:attr."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import osmo
from osmo.tasktypes.registry import (
    Resolver,
    TaskTypeError,
    builtin_type,
    entry_target,
    list_types,
    ref_of,
    resolve,
)
from tests.conftest import write
from tests.tasktypes.conftest import write_dist

GOOD = '''
from osmo import Param, task_type

@task_type(name="demo.count", version="4", extra="sim",
           params={"n": Param(int, default=2, help="how many")})
def COUNT(ctx):
    """Count to n."""
'''


def test_installed_types_resolve_and_list_with_broken_ones(on_path: Path) -> None:
    write(on_path / "demo_plugin.py", GOOD)
    write(on_path / "demo_broken.py", "import mujoco_not_installed_here\nX = 1\n")
    write_dist(on_path, "demo-plugins", {
        "demo.count": "demo_plugin:COUNT",
        "sim.broken": "demo_broken:X",            # no extra declared: no guess from the name
        "demo.tagged": "demo_broken:X [learn]",   # extra from the entry point's value
    })
    found = resolve("demo.count")
    assert (found.name, found.version, found.extra) == ("demo.count", "4", "sim")
    entries = {e.name: e for e in list_types()}
    assert entries["demo.count"].version == "4"
    assert entries["demo.count"].description == "Count to n."
    assert entries["demo.count"].distribution == "demo-plugins"
    assert entries["sim.broken"].error == (
        "task type 'sim.broken' needs module 'mujoco_not_installed_here', which is not "
        "installed")
    assert entries["demo.tagged"].error is not None
    assert 'pip install "osmo[learn]"' in entries["demo.tagged"].error
    with pytest.raises(TaskTypeError, match=r"unknown task type 'demo\.cont' \(did you mean "
                                            r"'demo\.count'\?\)"):
        resolve("demo.cont")


def test_custom_types_are_imported_in_isolation(tmp_path: Path) -> None:
    one, two = tmp_path / "one", tmp_path / "two"
    write(one / "tasks.py", GOOD.replace('name="demo.count", version="4"', 'version="1"'))
    write(two / "tasks.py", GOOD.replace('name="demo.count", version="4"', 'version="2"'))
    assert resolve("tasks:COUNT", paths=[str(one)]).version == "1"
    assert resolve("tasks:COUNT", paths=[str(two)]).version == "2"  # not the cached module
    assert "tasks" not in sys.modules and str(one) not in sys.path
    resolver = Resolver([str(two)])
    assert resolver.paths_for("tasks:COUNT") == (str(two),)
    assert resolver.paths_for("tasks:COUNT") == (str(two),)


def test_a_class_is_instantiated(tmp_path: Path) -> None:
    write(tmp_path / "klass.py", '''
class Render:
    name = "render"
    version = "7"
    params = {}
    resources = {"cpu": 2}
    extra = None
    description = "render frames"

    def run(self, ctx):
        pass
''')
    found = resolve("klass:Render", paths=[str(tmp_path)])
    assert found.version == "7" and not isinstance(found, type)


def test_shape_errors_name_every_problem(tmp_path: Path) -> None:
    write(tmp_path / "shapes.py", '''
class Bad:
    name = "bad"
    version = 3
    params = {}
    resources = {}
    extra = None
    description = ""

    def run(self):
        pass
''')
    with pytest.raises(TaskTypeError) as err:
        resolve("shapes:Bad", paths=[str(tmp_path)])
    assert "'version' must be a string, got 3" in str(err.value)
    assert "'run' must take exactly one argument (ctx)" in str(err.value)


def test_ref_of_names_the_module_attribute(on_path: Path) -> None:
    write(on_path / "reftypes.py", GOOD + "\nclass T:\n    pass\n\nINSTANCE = T()\n")
    import reftypes  # type: ignore[import-not-found]

    assert ref_of(reftypes.COUNT) == "reftypes:COUNT"
    assert ref_of(reftypes.INSTANCE) == "reftypes:INSTANCE"


def test_types_of_the_main_script_are_refused() -> None:
    fake = osmo.task_type(version="1")(lambda ctx: None)
    fake.fn.__module__ = "__main__"
    with pytest.raises(TaskTypeError, match="move them into a module"):
        ref_of(fake)


def test_a_distribution_installed_later_is_seen_by_the_shipped_type_check(on_path: Path) -> None:
    """``builtin_type`` keeps its answer only while no ``sys.path`` folder changed: a
    distribution installed first on the path, shadowing a shipped type, is seen at once."""
    assert builtin_type("sim.rollout") and builtin_type("sim.rollout")  # the second: kept
    write(on_path / "shadow_types.py", GOOD)
    write_dist(on_path, "shadow-types", {"sim.rollout": "shadow_types:COUNT"})
    assert not builtin_type("sim.rollout")


def test_an_installed_type_s_entry_point_is_what_a_runner_in_an_image_imports() -> None:
    """In a task's image osmo's code is there, its package metadata is not: the runner is
    told the installed type's ``module:attr``, which resolves to the same type."""
    target = entry_target("sim.rollout")
    assert target == "osmo_plugins.sim.rollout:ROLLOUT"
    assert resolve(target) is resolve("sim.rollout")
    assert entry_target("tasks:power") is None and entry_target("no.such.type") is None
