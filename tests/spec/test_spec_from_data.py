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
from tests.conftest import REPO

CORPUS = Path(__file__).parent


def _yaml_way(d: dict[str, Any]) -> Any:
    """What spec_from_dict gave before it had a fast way: dump the data, read the text."""
    try:
        text = yamlnodes.dump(d)
    except TypeError as exc:
        return [str(Diagnostic("<stored>", 0, 0, str(exc)))]
    try:
        return _build(text, "<stored>", Path(), {}, None)
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
