"""Typed reading of YAML nodes with diagnostics: the vocabulary the schema parsers are written in.

:class:`Ctx` collects diagnostics; the ``read_*`` helpers check one node's type, report a
problem at the node's position, and return ``None`` (or a neutral value) so parsing continues
and every problem in a file is reported once. Knows no workflow field names.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from osmo.errors import Diagnostic
from osmo.names import did_you_mean, name_problem
from osmo.spec.model import Pos
from osmo.spec.yamlnodes import Map, Node, Scalar, Seq

__all__ = ["Ctx", "did_you_mean", "is_empty", "read_bool", "read_fields", "read_int",
           "read_list", "read_map", "read_name", "read_str", "read_str_list", "scalar_text"]


@dataclass
class Ctx:
    """Where diagnostics go while one document is read."""

    file: str
    diags: list[Diagnostic] = field(default_factory=list)
    #: (id of a mapping node, key) pairs that an unknown key was suggested as; a missing
    #: required key already hinted at is not reported a second time.
    suggested: set[tuple[int, str]] = field(default_factory=set)

    def hinted(self, node: Node, key: str) -> bool:
        """True if an unknown key of ``node`` was reported with "did you mean '<key>'"."""
        return (id(node), key) in self.suggested

    def error(self, where: Node | Pos | None, message: str) -> None:
        """Record ``message`` at a node or position (line 0 when unknown)."""
        pos = where.pos if isinstance(where, Node) else where
        if pos is None:
            self.diags.append(Diagnostic(self.file, 0, 0, message))
        else:
            self.diags.append(Diagnostic(pos.file, pos.line, pos.col, message))


def _kind(node: Node) -> str:
    if isinstance(node, Map):
        return "a mapping"
    if isinstance(node, Seq):
        return "a list"
    assert isinstance(node, Scalar)
    value = node.value
    if value is None:
        return "nothing (null)"
    return {bool: "a boolean", int: "a number", float: "a number", str: "a string"}.get(
        type(value), type(value).__name__)


def read_fields(ctx: Ctx, node: Node, allowed: Sequence[str], where: str,
                required: Sequence[str] = ()) -> dict[str, Node] | None:
    """Check ``node`` is a mapping with only ``allowed`` keys and every ``required`` one.

    Returns:
        key → value node (keys not allowed are reported and dropped), or None if not a map.
    """
    if not isinstance(node, Map):
        ctx.error(node, f"{where} must be a mapping, not {_kind(node)}")
        return None
    out: dict[str, Node] = {}
    for key, value in node.entries:
        if key.text in allowed:
            out[key.text] = value
        else:
            hint = did_you_mean(key.text, allowed)
            ctx.error(key, f"unknown key '{key.text}' in {where}{hint}")
            if hint:
                ctx.suggested.add((id(node), hint.split("'")[1]))
    for name in required:
        if name not in out and not ctx.hinted(node, name):
            ctx.error(node, f"{where} is missing required key '{name}'")
    return out


def read_map(ctx: Ctx, node: Node, what: str) -> list[tuple[Scalar, Node]] | None:
    """The entries of a mapping node, or None (reported) if it is not one."""
    if isinstance(node, Map):
        return node.entries
    if isinstance(node, Scalar) and node.value is None:
        return []
    ctx.error(node, f"{what} must be a mapping, not {_kind(node)}")
    return None


def read_list(ctx: Ctx, node: Node, what: str) -> list[Node]:
    """The items of a sequence node; [] (reported) if it is not one. ``null`` is empty."""
    if isinstance(node, Seq):
        return node.items
    if isinstance(node, Scalar) and node.value is None:
        return []
    ctx.error(node, f"{what} must be a list, not {_kind(node)}")
    return []


def read_str(ctx: Ctx, node: Node, what: str, *, allow_empty: bool = False) -> str | None:
    """A string scalar, or None (reported)."""
    if isinstance(node, Scalar) and isinstance(node.value, str):
        if node.value or allow_empty:
            return node.value
        ctx.error(node, f"{what} must not be empty")
        return None
    ctx.error(node, f"{what} must be a string, not {_kind(node)}")
    return None


def read_int(ctx: Ctx, node: Node, what: str, *, minimum: int = 0) -> int | None:
    """An integer scalar ≥ ``minimum``, or None (reported)."""
    value = node.value if isinstance(node, Scalar) else None
    if not isinstance(value, int) or isinstance(value, bool):
        ctx.error(node, f"{what} must be a whole number, not {_kind(node)}")
        return None
    if value < minimum:
        ctx.error(node, f"{what} must be at least {minimum}, not {value}")
        return None
    return value


def read_bool(ctx: Ctx, node: Node, what: str) -> bool | None:
    """A boolean scalar, or None (reported)."""
    if isinstance(node, Scalar) and isinstance(node.value, bool):
        return node.value
    ctx.error(node, f"{what} must be true or false, not {_kind(node)}")
    return None


def read_str_list(ctx: Ctx, node: Node, what: str) -> tuple[str, ...]:
    """A list of strings (numbers are accepted and stringified); bad items are reported."""
    out = []
    for item in read_list(ctx, node, what):
        value = item.value if isinstance(item, Scalar) else None
        if isinstance(value, str):
            out.append(value)
        elif isinstance(item, Scalar) and isinstance(value, int | float) and (
                not isinstance(value, bool)):
            out.append(item.text)
        else:
            ctx.error(item, f"items of {what} must be strings, not {_kind(item)}")
    return tuple(out)


def read_name(ctx: Ctx, node: Node, what: str) -> str | None:
    """A user-chosen name (workflow, group, task, dataset).

    It matches ``osmo.names.NAME_RE``, at most ``osmo.names.MAX_NAME`` characters.

    A malformed name is reported and still returned, so later checks can use it.
    """
    name = read_str(ctx, node, what)
    if name is None:
        return None
    problem = name_problem(name, what)
    if problem is not None:
        ctx.error(node, problem)
    return name


def scalar_text(node: Node) -> Any:
    """The stringified value of a scalar for string-typed maps (bools lower-case), or None."""
    if not isinstance(node, Scalar) or node.value is None:
        return None
    if isinstance(node.value, bool):
        return "true" if node.value else "false"
    if isinstance(node.value, int | float):
        return node.text
    return str(node.value)


def is_empty(node: Node) -> bool:
    """True for an empty list or a null value (``key:`` with nothing after it)."""
    return (isinstance(node, Seq) and not node.items) or (
        isinstance(node, Scalar) and node.value is None)
