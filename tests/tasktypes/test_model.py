"""Typed tasks in the model: the builder, resource precedence and the cache key."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest

import osmo
from osmo.errors import SpecError, UsageError
from osmo.server.cache import fingerprint
from osmo.spec import ResolvedType, ResourceSpec, load_spec, spec_from_dict
from osmo.tasktypes.registry import Resolver
from tests.conftest import write

TYPES = '''
from osmo import Param, task_type

@task_type(version="2", params={"n": Param(int)}, resources={"cpu": 3, "memory": "1Gi"})
def heavy(ctx):
    pass
'''


def test_builder_takes_a_type_object_or_name(on_path: Path) -> None:
    write(on_path / "btypes.py", TYPES)
    import btypes  # type: ignore[import-not-found]

    wf = osmo.Workflow("typed")
    wf.task("a", type=btypes.heavy, params={"n": 1})
    wf.task("b", type="btypes:heavy", params={"n": 2}, inputs=["a"])
    assert wf.to_dict()["workflow"]["tasks"][0] == {
        "name": "a", "type": "btypes:heavy", "params": {"n": 1}}
    spec = spec_from_dict(wf.to_dict(), types=Resolver())
    assert spec.task("a").resolved == ResolvedType(
        "2", ResourceSpec(cpu=3, memory=1 << 30), (str(on_path),))
    assert spec == wf.build()  # resolution is derived data, outside equality


def test_builder_names_an_instance_and_refuses_what_a_worker_cannot_import(
        on_path: Path) -> None:
    write(on_path / "itypes.py", TYPES + "\nclass T:\n    pass\n\nINSTANCE = T()\n")
    import itypes  # type: ignore[import-not-found]

    wf = osmo.Workflow("typed").task("a", type=itypes.INSTANCE)
    assert wf.to_dict()["workflow"]["tasks"][0]["type"] == "itypes:INSTANCE"
    in_main = osmo.task_type(version="1")(lambda ctx: None)
    in_main.fn.__module__ = "__main__"
    with pytest.raises(UsageError, match="move them into a module"):
        osmo.Workflow("typed").task("a", type=in_main).to_dict()
    with pytest.raises(UsageError, match="cannot find .* in its module 'itypes'"):
        osmo.Workflow("typed").task("a", type=itypes.T()).to_dict()


def test_type_resources_apply_unless_a_resource_is_named(tmp_path: Path) -> None:
    spec_file = write(tmp_path / "wf.yaml", """
workflow:
  name: res
  resources:
    small: {cpu: 1}
  tasks:
  - {name: a, type: "rtypes:heavy", params: {n: 1}}
  - {name: b, type: "rtypes:heavy", params: {n: 1}, resource: small}
""")
    write(tmp_path / "rtypes.py", TYPES)
    spec = load_spec(spec_file, types=Resolver([str(tmp_path)]))
    assert spec.resource_for(spec.task("a")) == ResourceSpec(cpu=3, memory=1 << 30)
    assert spec.resource_for(spec.task("b")).cpu == 1
    assert "rtypes" not in sys.modules
    # without a resolver a typed task's params and defaults are not checked, nor is the
    # missing default entry its type's resources stand for
    bare = load_spec(spec_file)
    assert bare.task("a").resolved is None and bare.resource_for(bare.task("b")).cpu == 1
    plain = write(tmp_path / "plain.yaml", spec_file.read_text().replace(
        '{name: a, type: "rtypes:heavy", params: {n: 1}}', "{name: a, command: [true]}"))
    with pytest.raises(SpecError, match="task 'a' has no 'resource:'"):
        load_spec(plain)  # an untyped task still needs the default entry


def test_fingerprint_changes_with_the_type_version() -> None:
    task = osmo.spec.TaskSpec(name="a", type="x:y", params={"n": 1},
                              resolved=ResolvedType("1"))
    newer = dataclasses.replace(task, resolved=ResolvedType("2"))
    assert fingerprint(task, []) != fingerprint(newer, [])
    assert fingerprint(task, []) == fingerprint(dataclasses.replace(task), [])
