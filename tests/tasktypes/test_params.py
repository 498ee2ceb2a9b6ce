"""Parameter values against Param schemas: one rule set for submit, runner and the kit."""

from __future__ import annotations

from typing import Any

import pytest

from osmo.params import fill_defaults, schema_problems, value_problem
from osmo.tasktypes import REQUIRED, Param


@pytest.mark.parametrize(("param", "value", "problem"), [
    (Param(int), 3, None),
    (Param(int), True, "must be int, got bool True"),
    (Param(int), 2.5, "must be int, got float 2.5"),
    (Param(float), 2, None),
    (Param(float), "2", "must be float, got str '2'"),
    (Param(bool), 1, "must be bool, got int 1"),
    (Param(str), None, "must be str, got null"),
    (Param(list), [1], None),
    (Param(dict), [], "must be dict, got list []"),
    (Param(int, min=1, max=3), 0, "must be at least 1; got 0"),
    (Param(int, min=1, max=3), 4, "must be at most 3; got 4"),
    (Param(str, choices=("a", "b")), "c", "must be one of 'a', 'b'; got 'c'"),
    (Param(str, choices=("a", "b")), "b", None),
])
def test_value_problem(param: Param, value: Any, problem: str | None) -> None:
    assert value_problem(param, value) == problem


def test_fill_defaults_keeps_given_and_skips_required() -> None:
    schema = {"n": Param(int, default=3), "m": Param(int), "s": Param(str, default="x")}
    assert fill_defaults(schema, {"s": "y"}) == {"n": 3, "s": "y"}


@pytest.mark.parametrize(("schema", "problem"), [
    ({"n": Param(int, default="3")}, "param 'n': its default must be int, got str '3'"),
    ({"n": Param(int, min=5, max=1)}, "param 'n': min 5 is above max 1"),
    ({"n": Param(str, choices=("a", 1))}, "param 'n': choice 1 is not str"),
    ({"n": 3}, "param 'n' must be an osmo Param, got int"),
    ([Param(int)], "'params' must be a mapping of name to Param, got list"),
])
def test_schema_problems(schema: Any, problem: str) -> None:
    assert problem in schema_problems(schema)


def test_sound_schema_has_no_problems() -> None:
    assert schema_problems({"n": Param(int, default=2, min=1), "k": Param(str, default=REQUIRED)}) == []
