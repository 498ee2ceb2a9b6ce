"""YAML adapter: the only module of osmo that imports ``yaml``.

It owns safe loading of a YAML document into a small node tree (:class:`Scalar`, :class:`Seq`,
:class:`Map`) in which every node keeps its 1-based source position, and the dumping of plain
data back to YAML text. Loading never builds Python objects from tags (``yaml.SafeLoader``
only), reports duplicate keys, recursive aliases and alias bombs as :class:`Diagnostic` s, and
translates every ``yaml`` error into one. It knows nothing about the workflow schema.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import yaml
from yaml import nodes as ynodes

from osmo.errors import Diagnostic
from osmo.spec.model import Pos

__all__ = ["Map", "Node", "Scalar", "Seq", "dump", "load_nodes", "to_plain"]

# libyaml (C) is ~10x faster than the pure-Python parser; both keep positions.
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
MAX_ALIAS_NODES = 100_000  # nodes copied through aliases; bounds "billion laughs" documents
_MERGE_TAG = "tag:yaml.org,2002:merge"


@dataclass
class Node:
    """A YAML node and where it starts."""

    pos: Pos


@dataclass
class Scalar(Node):
    """A scalar: ``value`` is the resolved Python value, ``text`` the scalar's string form."""

    value: Any = None
    text: str = ""


@dataclass
class Seq(Node):
    """A sequence of nodes."""

    items: list[Node] = field(default_factory=list)


@dataclass
class Map(Node):
    """A mapping. Keys are scalars (compared by their text); merge keys (``<<``) are applied."""

    entries: list[tuple[Scalar, Node]] = field(default_factory=list)

    def get(self, key: str) -> Node | None:
        """The value node for ``key``, or None."""
        for k, v in self.entries:
            if k.text == key:
                return v
        return None


class _TooBigError(Exception):
    pass


class _Converter:
    """Turns a composed ``yaml`` node graph into our node tree, collecting diagnostics."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.diags: list[Diagnostic] = []
        self.copied = 0
        self.seen: set[int] = set()
        self.active: set[int] = set()
        self.constructor = yaml.SafeLoader("")

    def pos(self, node: ynodes.Node) -> Pos:
        return Pos(self.file, node.start_mark.line + 1, node.start_mark.column + 1)

    def error(self, node: ynodes.Node, message: str) -> None:
        p = self.pos(node)
        self.diags.append(Diagnostic(p.file, p.line, p.col, message))

    def convert(self, node: ynodes.Node) -> Node:
        if id(node) in self.seen:
            self.copied += 1
            if self.copied > MAX_ALIAS_NODES:
                raise _TooBigError
        self.seen.add(id(node))
        if id(node) in self.active:
            self.error(node, "recursive YAML alias; an anchor cannot contain itself")
            return Scalar(self.pos(node), None, "")
        self.active.add(id(node))
        try:
            if isinstance(node, ynodes.ScalarNode):
                return self.scalar(node)
            if isinstance(node, ynodes.SequenceNode):
                return Seq(self.pos(node), [self.convert(n) for n in node.value])
            assert isinstance(node, ynodes.MappingNode)
            return self.mapping(node)
        finally:
            self.active.discard(id(node))

    def scalar(self, node: ynodes.ScalarNode) -> Scalar:
        try:
            value = self.constructor.construct_object(node, deep=True)
        except yaml.YAMLError as exc:
            self.error(node, f"cannot read this YAML value: {_problem(exc)}")
            value = node.value
        return Scalar(self.pos(node), value, str(node.value))

    def mapping(self, node: ynodes.MappingNode) -> Map:
        explicit: list[tuple[Scalar, Node]] = []
        merged: list[tuple[Scalar, Node]] = []
        seen: dict[str, Scalar] = {}
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                merged.extend(self.merge_source(value_node))
                continue
            key = self.key(key_node)
            if key is None:
                continue
            if key.text in seen:
                first = seen[key.text].pos
                self.error(key_node, f"duplicate key '{key.text}' (first at line {first.line});"
                           " remove one of them")
                continue
            seen[key.text] = key
            explicit.append((key, self.convert(value_node)))
        merged = [(k, v) for k, v in merged if k.text not in seen]
        return Map(self.pos(node), _dedupe(merged) + explicit)

    def merge_source(self, node: ynodes.Node) -> list[tuple[Scalar, Node]]:
        sources = node.value if isinstance(node, ynodes.SequenceNode) else [node]
        out: list[tuple[Scalar, Node]] = []
        for src in sources:
            converted = self.convert(src)
            if isinstance(converted, Map):
                out.extend(converted.entries)
            else:
                self.error(src, "a merge key '<<' must refer to a mapping")
        return out

    def key(self, node: ynodes.Node) -> Scalar | None:
        if not isinstance(node, ynodes.ScalarNode):
            self.error(node, "a mapping key must be a plain value, not a list or mapping")
            return None
        return self.scalar(node)


def _dedupe(entries: list[tuple[Scalar, Node]]) -> list[tuple[Scalar, Node]]:
    """Merged entries: the first source that defines a key wins (YAML merge semantics)."""
    seen: set[str] = set()
    out = []
    for k, v in entries:
        if k.text not in seen:
            seen.add(k.text)
            out.append((k, v))
    return out


def _problem(exc: yaml.YAMLError) -> str:
    problem = getattr(exc, "problem", None) or str(exc)
    context = getattr(exc, "context", None)
    return f"{context}, {problem}" if context else str(problem)


def load_nodes(text: str, file: str) -> tuple[Node | None, list[Diagnostic]]:
    """Parse one YAML document into a node tree.

    Returns:
        the root node (None for an empty document or a syntax error) and the diagnostics.
    """
    try:
        root = yaml.compose(text, Loader=_LOADER)
    except yaml.MarkedYAMLError as exc:
        mark, start = exc.problem_mark or exc.context_mark, exc.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
        message = f"YAML syntax error: {_problem(exc)}"
        if start is not None and start.line + 1 != line:
            message += f" (it started at line {start.line + 1}, column {start.column + 1})"
        return None, [Diagnostic(file, line, col, message)]
    except yaml.YAMLError as exc:
        return None, [Diagnostic(file, 0, 0, f"YAML error: {exc}")]
    if root is None:
        return None, []
    converter = _Converter(file)
    try:
        tree = converter.convert(root)
    except _TooBigError:
        message = (f"YAML aliases expand to more than {MAX_ALIAS_NODES} copied nodes "
                   "(alias bomb?); write the values out instead")
        return None, [Diagnostic(file, 1, 1, message)]
    return tree, converter.diags


def to_plain(node: Node) -> Any:
    """The plain Python value of a node tree (maps keyed by key text)."""
    if isinstance(node, Map):
        return {k.text: to_plain(v) for k, v in node.entries}
    if isinstance(node, Seq):
        return [to_plain(n) for n in node.items]
    assert isinstance(node, Scalar)
    return node.value


def dump(data: Any) -> str:
    """Plain data (dicts, lists, str, int, float, bool, None) as block-style YAML text.

    Raises:
        TypeError: if ``data`` holds a value YAML cannot represent safely.
    """
    try:
        return str(yaml.dump(data, Dumper=_DUMPER, sort_keys=False, allow_unicode=True,
                             default_flow_style=False, width=100))
    except yaml.YAMLError as exc:
        raise TypeError(f"cannot write as YAML: {exc}") from None
