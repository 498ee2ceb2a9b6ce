"""``spec_from_dict`` checks data without writing YAML, and says exactly what the YAML way says.

The fast way (``yamlnodes.from_plain``) must give the same model for valid data and the same
messages, positions included, for data with a problem (it falls back to the YAML way then).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from osmo.errors import Diagnostic, SpecError
from osmo.spec import load_spec, spec_from_dict, spec_to_dict, yamlnodes
from osmo.spec.loader import _build
from osmo.spec.localfiles import LocalFiles
from tests.conftest import REPO

CORPUS = Path(__file__).parent


def _yaml_way(d: dict[str, Any]) -> Any:
    """What spec_from_dict gave before it had a fast way: dump the data, read the text."""
    try:
        text = yamlnodes.dump(d)
    except TypeError as exc:
        return [str(Diagnostic("<stored>", 0, 0, str(exc)))]
    try:
        return _build(text, "<stored>", LocalFiles.none(), {}, None)
    except SpecError as exc:
        return [str(x) for x in exc.diagnostics]


def _fast_way(d: dict[str, Any]) -> Any:
    try:
        return spec_from_dict(d)
    except SpecError as exc:
        return [str(x) for x in exc.diagnostics]


def _plain_documents() -> list[tuple[str, dict[str, Any]]]:
    docs = []
    for path in sorted((CORPUS / "invalid").glob("*.yaml")) + sorted(
            (CORPUS / "valid").glob("*.yaml")):
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError:
            continue
        if isinstance(data, dict):
            docs.append((path.name, data))
    for path in sorted((REPO / "workflows").glob("*.yaml")):
        docs.append((path.name, spec_to_dict(load_spec(path))))
    return docs


@pytest.mark.parametrize(("name", "data"), _plain_documents(), ids=lambda v: v
                         if isinstance(v, str) else "")
def test_the_fast_way_says_what_the_yaml_way_says(name: str, data: dict[str, Any]) -> None:
    assert _fast_way(data) == _yaml_way(data)


def test_the_corpus_has_both_kinds() -> None:
    results = [_fast_way(d) for _, d in _plain_documents()]
    assert sum(isinstance(r, list) for r in results) >= 20  # invalid ones, with messages
    assert sum(not isinstance(r, list) for r in results) >= 5  # valid ones


def _task(env: dict[str, Any], args: list[Any]) -> dict[str, Any]:
    return {"workflow": {"name": "w", "tasks": [
        {"name": "t", "command": ["echo"], "args": args, "environment": env}]}}


SCALARS = st.one_of(
    st.text(), st.integers(), st.booleans(), st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**300), max_value=10**300),
    st.sampled_from(["\ud800", "yes", "null", "1e3", "0x10", "~", "", " a ", "a\r\nb", "\u2028"]),
)


@settings(max_examples=300, deadline=None)
@given(env=st.dictionaries(st.from_regex(r"[A-Z][A-Z0-9_]{0,8}", fullmatch=True), SCALARS,
                           max_size=4),
       args=st.lists(SCALARS, max_size=4))
def test_scalars_read_as_the_yaml_round_trip_reads_them(env: dict[str, Any],
                                                        args: list[Any]) -> None:
    fast, slow = _fast_way(_task(env, args)), _yaml_way(_task(env, args))
    if isinstance(slow, list) or isinstance(fast, list):
        assert fast == slow
        return
    ft, stask = fast.task("t"), slow.task("t")
    assert ft.args == stask.args
    assert ft.environment.keys() == stask.environment.keys()
    for key, value in ft.environment.items():
        other = stask.environment[key]
        assert value == other or (isinstance(value, float) and math.isnan(value)
                                  and math.isnan(other)), (key, value, other)


def test_what_the_fast_way_cannot_read_goes_the_yaml_way() -> None:
    assert yamlnodes.from_plain({"a": ("tuple",)}, "f") is None
    assert yamlnodes.from_plain({"a": "\udcff"}, "f") is None
    assert yamlnodes.from_plain({"a": 10**5000}, "f") is None
    huge = _task({"A": 10**5000}, [])
    assert _fast_way(huge) == _yaml_way(huge)
    deep: dict[str, Any] = {}
    node = deep
    for _ in range(yamlnodes.MAX_DEPTH + 1):
        node["x"] = {}
        node = node["x"]
    assert yamlnodes.from_plain(deep, "f") is None
    with pytest.raises(SpecError, match="nested more than 100 levels"):
        spec_from_dict(deep)


# ---------------------------------------------------------------- tasks written alike (shapes)

def _with_copies(data: dict[str, Any], copies: int, rename: Any) -> dict[str, Any]:
    """``data`` with each bare task followed by ``copies`` copies under other names."""
    workflow = data.get("workflow")
    tasks = workflow.get("tasks") if isinstance(workflow, dict) else None
    if not isinstance(tasks, list):
        return data
    out: list[Any] = []
    for task in tasks:
        out.append(task)
        if isinstance(task, dict):
            out += [{**task, "name": rename(task.get("name"), i)} for i in range(copies)]
    return {**data, "workflow": {**workflow, "tasks": out}}


@pytest.mark.parametrize(("name", "data"), _plain_documents(), ids=lambda v: v
                         if isinstance(v, str) else "")
def test_tasks_written_alike_read_as_the_yaml_way_reads_them(name: str,
                                                             data: dict[str, Any]) -> None:
    copied = _with_copies(data, 2, lambda n, i: f"{n}-copy{i}" if isinstance(n, str) else n)
    assert _fast_way(copied) == _yaml_way(copied)


NAMES = st.one_of(st.from_regex(r"[a-z][a-z0-9_-]{0,6}", fullmatch=True),
                  st.sampled_from(["", "A B", "x" * 80, "src", "SRC", "s_rc", "-x", "é"]),
                  st.integers(), st.none())


@settings(max_examples=200, deadline=None)
@given(names=st.lists(NAMES, min_size=2, max_size=8),
       inputs=st.sampled_from([[], [{"task": "src"}], [{"task": "nowhere"}], "bad"]),
       command=st.sampled_from([["true"], [], "true", ["{{input:0}}"], ["{{host:src}}"]]))
def test_a_fan_out_reads_as_the_yaml_way_reads_it(names: list[Any], inputs: Any,
                                                  command: Any) -> None:
    data = {"workflow": {"name": "w", "tasks": [{"name": "src", "command": ["true"]}] + [
        {"name": n, "command": command, "inputs": inputs} for n in names]}}
    assert _fast_way(data) == _yaml_way(data)


def test_a_fan_out_is_parsed_once_per_shape() -> None:
    from osmo.spec.shapes import reduce_tasks

    data = {"workflow": {"name": "w", "tasks": [{"name": "src", "command": ["true"]}] + [
        {"name": f"m{i}", "command": ["true"], "inputs": [{"task": "src"}]}
        for i in range(1000)] + [{"name": "m1000", "command": ["true"], "args": ["x"]}]}}
    reduced = reduce_tasks(data)
    assert reduced is not None and len(reduced.data["workflow"]["tasks"]) == 3
    spec = spec_from_dict(data)
    assert [t.name for t in spec.all_tasks()] == ["src", *(f"m{i}" for i in range(1001))]
    assert spec == _yaml_way(data)
    assert spec.task("m999").inputs == spec.task("m0").inputs
    # a copy with a bad name or a clashing one is reported as the YAML way reports it
    for bad in ("M5", "no spaces", ""):
        data["workflow"]["tasks"][3]["name"] = bad
        wrong = _fast_way(data)
        assert isinstance(wrong, list) and wrong == _yaml_way(data)
        assert all(":" in line and not line.startswith("<stored>:0:") for line in wrong)
