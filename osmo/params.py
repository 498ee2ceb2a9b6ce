"""Task-type parameters: the :class:`Param` declaration and the rules values are checked by.

A task type declares its parameters as ``name → Param``; one set of rules serves the spec
(errors at submit, with positions), the runner (defaults filled in) and the conformance kit
(a type's own defaults must pass its own schema):

- ``int`` takes integers, never booleans; ``float`` takes integers and floats; ``bool`` only
  ``true``/``false``; ``str`` only strings (quote ``"1"`` in YAML); ``list`` and ``dict`` take
  YAML lists and mappings. Any other ``type`` is checked with ``isinstance``.
- ``choices`` (when given) must contain the value; ``min``/``max`` bound numbers inclusively.

The bottom layer: pure, imports nothing of osmo, so the spec layer checks params without
importing task types (``osmo.tasktypes.api`` re-exports :class:`Param` for plugins).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["REQUIRED", "SIMPLE_TYPES", "Param", "fill_defaults", "schema_problems",
           "type_label", "value_problem"]


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()
"""Default of a :class:`Param` that the task must be given."""


@dataclass(frozen=True)
class Param:
    """One parameter of a task type, checked at submit (errors point at the spec's line).

    Attributes:
        type: ``int``, ``float``, ``str``, ``bool``, ``list`` or ``dict`` (an ``int`` is
            accepted where ``float`` is asked for).
        default: value when the spec omits it; :data:`REQUIRED` makes it mandatory.
        help: one line shown by ``osmo plugins list -v`` and in error messages.
        choices: allowed values (empty: any value of the type).
        min, max: inclusive bounds for numbers.
    """

    type: type
    default: Any = REQUIRED
    help: str = ""
    choices: tuple[Any, ...] = ()
    min: float | None = None
    max: float | None = None


SIMPLE_TYPES: tuple[type, ...] = (int, float, str, bool, list, dict)
"""The parameter types a spec can write directly."""


def type_label(kind: Any) -> str:
    """The name of a parameter type as messages show it (``int``, ``list``...)."""
    return getattr(kind, "__name__", repr(kind))


def _is(value: Any, kind: type) -> bool:
    if isinstance(value, bool):
        return kind is bool
    if kind is float:
        return isinstance(value, int | float)
    if kind is list:
        return isinstance(value, list | tuple)
    try:
        return isinstance(value, kind)
    except TypeError:  # not a class: reported by schema_problems
        return False


def value_problem(param: Param, value: Any) -> str | None:
    """What is wrong with ``value`` for ``param``, or None when it is acceptable.

    The problem is a phrase like ``must be int, got ...``.
    """
    if not _is(value, param.type):
        shown = "null" if value is None else f"{type_label(type(value))} {value!r}"
        return f"must be {type_label(param.type)}, got {shown}"
    if param.choices and value not in param.choices:
        allowed = ", ".join(repr(c) for c in param.choices)
        return f"must be one of {allowed}; got {value!r}"
    if isinstance(value, int | float) and not isinstance(value, bool):
        if param.min is not None and value < param.min:
            return f"must be at least {param.min:g}; got {value!r}"
        if param.max is not None and value > param.max:
            return f"must be at most {param.max:g}; got {value!r}"
    return None


def fill_defaults(schema: Mapping[str, Param], given: Mapping[str, Any]) -> dict[str, Any]:
    """``given`` plus the default of every parameter it omits (required ones stay absent)."""
    out = dict(given)
    for name, param in schema.items():
        if name not in out and param.default is not REQUIRED:
            out[name] = param.default
    return out


def schema_problems(schema: Any) -> list[str]:
    """Problems of a type's ``params`` declaration itself (empty when it is sound)."""
    if not isinstance(schema, Mapping):
        return [f"'params' must be a mapping of name to Param, got {type(schema).__name__}"]
    problems = []
    for name, param in schema.items():
        if not isinstance(name, str) or not name:
            problems.append(f"param name {name!r} must be a non-empty string")
            continue
        if not isinstance(param, Param):
            problems.append(f"param '{name}' must be an osmo Param, got {type(param).__name__}")
            continue
        if not isinstance(param.type, type):
            problems.append(f"param '{name}': type must be a class like int, got {param.type!r}")
            continue
        if param.min is not None and param.max is not None and param.min > param.max:
            problems.append(f"param '{name}': min {param.min} is above max {param.max}")
        for choice in param.choices:
            if not _is(choice, param.type):
                problems.append(f"param '{name}': choice {choice!r} is not "
                                f"{type_label(param.type)}")
        if param.default is not REQUIRED:
            problem = value_problem(param, param.default)
            if problem:
                problems.append(f"param '{name}': its default {problem}")
    return problems
