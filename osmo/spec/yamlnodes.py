"""YAML adapter: the only module of osmo that imports ``yaml``.

It owns safe loading of a YAML document into a small node tree (:class:`Scalar`, :class:`Seq`,
:class:`Map`) in which every node keeps its 1-based source position, and the dumping of plain
data back to YAML text. Loading never builds Python objects from tags (``yaml.SafeLoader``
only) and refuses every tag but the plain ones (``!!str``, ``!!int``...: see
:data:`PLAIN_TAGS`), naming it. It reports duplicate keys, recursive aliases, alias bombs,
nesting deeper than :data:`MAX_DEPTH` and integers longer than Python converts as
:class:`Diagnostic` s, and translates every ``yaml`` error into one. It knows nothing about the
workflow schema.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from typing import Any

import yaml
from yaml import nodes as ynodes

from osmo.errors import Diagnostic
from osmo.spec.model import Pos

__all__ = ["Map", "Node", "Scalar", "Seq", "dump", "from_plain", "load_nodes", "to_plain"]

# libyaml (C) is ~10x faster than the pure-Python parser; both keep positions.
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
MAX_ALIAS_NODES = 100_000  # nodes copied through aliases; bounds "billion laughs" documents
MAX_DEPTH = 100  # levels of nested lists and mappings
_YAML_TAG = "tag:yaml.org,2002:"
_MERGE_TAG = _YAML_TAG + "merge"
PLAIN_TAGS = frozenset(_YAML_TAG + t for t in (
    "str", "int", "float", "bool", "null", "timestamp", "seq", "map", "merge", "value"))
#: libyaml's composer recurses in C once per level and overflows the stack tens of thousands
#: of levels deep; a document this short cannot nest that deep, longer ones are measured first
_SHORT = 2000
_PREFIX = re.compile(r"^[ ?:-]*", re.MULTILINE)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_PAIR = re.compile(r"\[\]|\{\}")


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


class _TooDeepError(Exception):
    def __init__(self, node: ynodes.Node) -> None:
        self.node = node


def _depth_message() -> str:
    return (f"YAML nested more than {MAX_DEPTH} levels deep (lists and mappings), the limit; "
            "flatten the document")


def _flow_depth(text: str, limit: int) -> int | None:
    """How deep the brackets of ``text`` nest, if at most ``limit``.

    None if deeper or if they do not pair up. Brackets in strings and comments count too, so it
    never says less than the document's flow nesting.
    """
    brackets = _NOT_BRACKET.sub("", text)
    for depth in range(limit + 1):
        if not brackets:
            return depth
        shorter = _PAIR.sub("", brackets)  # one level per pass
        if shorter == brackets:
            return None
        brackets = shorter
    return None


def _surely_shallow(text: str) -> bool:
    """True if ``text`` cannot nest deeper than :data:`MAX_DEPTH` (cheap, conservative).

    A block level takes a column of indentation or an indicator (``- ``, ``? ``), a flow level a
    bracket.
    """
    if len(text) <= _SHORT:
        return True
    block = 2 * (max(map(len, _PREFIX.findall(text)), default=0) + 1)
    flow = _flow_depth(text, MAX_DEPTH - block) if block < MAX_DEPTH else None
    return flow is not None


def _depth_problem(text: str, file: str) -> Diagnostic | None:
    """Where the document first nests deeper than :data:`MAX_DEPTH`.

    Read from the parser's events (which keep no stack of their own), before any recursive
    composition.
    """
    if _surely_shallow(text):
        return None
    try:
        return _first_too_deep(text, file, _LOADER)
    except yaml.YAMLError:
        pass
    if _LOADER is yaml.SafeLoader:
        return None  # composing reports it, with its position
    # libyaml (PyYAML >= 6.0.4) refuses flow nesting past its own limit while its scanner reads
    # ahead of the events, before they reach ours; the pure-Python parser has no such limit
    try:
        return _first_too_deep(text, file, yaml.SafeLoader)
    except yaml.YAMLError:
        return None  # composing reports it, with its position


def _first_too_deep(text: str, file: str, loader: Any) -> Diagnostic | None:
    depth = 0
    for event in yaml.parse(text, Loader=loader):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                mark = event.start_mark
                line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
                return Diagnostic(file, line, col, _depth_message())
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1
    return None


class _Converter:
    """Turns a composed ``yaml`` node graph into our node tree, collecting diagnostics."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.diags: list[Diagnostic] = []
        self.copied = 0
        self.seen: set[int] = set()
        self.active: set[int] = set()
        self.depth = 0
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
        if not self.plain(node):
            return Scalar(self.pos(node), None, "")
        self.active.add(id(node))
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:  # aliases can nest what the text does not
                raise _TooDeepError(node)
            if isinstance(node, ynodes.ScalarNode):
                return self.scalar(node)
            if isinstance(node, ynodes.SequenceNode):
                return Seq(self.pos(node), [self.convert(n) for n in node.value])
            assert isinstance(node, ynodes.MappingNode)
            return self.mapping(node)
        finally:
            self.depth -= 1
            self.active.discard(id(node))

    def plain(self, node: ynodes.Node) -> bool:
        """Whether the node's tag is a plain one; an unknown tag is reported, by name."""
        if node.tag in PLAIN_TAGS:
            return True
        tag = node.tag.replace(_YAML_TAG, "!!", 1)
        self.error(node, f"unknown YAML tag {tag!r}: osmo reads plain YAML values only "
                         "(strings, numbers, booleans, null, lists, mappings); remove the tag")
        return False

    def scalar(self, node: ynodes.ScalarNode) -> Scalar:
        try:
            value = self.constructor.construct_object(node, deep=True)
        except yaml.YAMLError as exc:
            self.error(node, f"cannot read this YAML value: {_problem(exc)}")
            value = node.value
        except ValueError:  # an integer longer than Python converts
            self.error(node, f"this number has {len(node.value)} characters; integers may have "
                             f"at most {sys.get_int_max_str_digits()} digits, the limit (quote "
                             "it to keep it as text)")
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
        return self.scalar(node) if self.plain(node) else None


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
    deep = _depth_problem(text, file)
    if deep is not None:
        return None, [deep]
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
    except _TooDeepError as exc:
        mark = exc.node.start_mark
        return None, [Diagnostic(file, mark.line + 1, mark.column + 1, _depth_message())]
    return tree, converter.diags


def to_plain(node: Node) -> Any:
    """The plain Python value of a node tree (maps keyed by key text)."""
    if isinstance(node, Map):
        return {k.text: to_plain(v) for k, v in node.entries}
    if isinstance(node, Seq):
        return [to_plain(n) for n in node.items]
    assert isinstance(node, Scalar)
    return node.value


_REPRESENTER = yaml.representer.SafeRepresenter()
_LONE_SURROGATE = re.compile("[\ud800-\udfff]")
_MAX_INT_BITS = 14_000  # ints longer than ~4,300 digits: the YAML path reports them


class _NotPlain(Exception):
    pass


def from_plain(data: Any, file: str) -> Node | None:
    """Plain data as a node tree, as :func:`load_nodes` would read :func:`dump`'s text of it.

    The fast way to check a spec given as data (the SDK's, a stored one): no YAML text is
    written or parsed. Values and scalar texts are those the YAML round trip gives (a float's
    text is its YAML form, a bool's ``true``/``false``); every position is line 0 of ``file``.
    None when the data holds anything the round trip would change or refuse (another type, a
    lone surrogate, an integer longer than Python reads back, nesting deeper than
    :data:`MAX_DEPTH`): the caller then takes the YAML way, which reports it.
    """
    pos = Pos(file, 0, 0)
    try:
        return _plain_node(data, pos, 0)
    except _NotPlain:
        return None


def _plain_node(data: Any, pos: Pos, depth: int) -> Node:
    if isinstance(data, dict | list):
        if depth >= MAX_DEPTH:
            raise _NotPlain
        if isinstance(data, list):
            return Seq(pos, [_plain_node(item, pos, depth + 1) for item in data])
        return Map(pos, [(_plain_scalar(key, pos), _plain_node(value, pos, depth + 1))
                         for key, value in data.items()])
    return _plain_scalar(data, pos)


def _plain_scalar(value: Any, pos: Pos) -> Scalar:
    if isinstance(value, str):
        if not value.isascii() and _LONE_SURROGATE.search(value):
            raise _NotPlain
        return Scalar(pos, value, value)
    if value is None or isinstance(value, bool):
        return Scalar(pos, value, "null" if value is None else "true" if value else "false")
    if isinstance(value, int):
        if value.bit_length() > _MAX_INT_BITS:
            raise _NotPlain
        return Scalar(pos, value, str(value))
    if isinstance(value, float):
        return Scalar(pos, value, _REPRESENTER.represent_float(value).value)
    raise _NotPlain


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
    except UnicodeEncodeError as exc:  # a lone surrogate (JSON can carry one)
        raise TypeError(f"cannot write as YAML: a string holds {exc.object[exc.start:exc.end]!r}, "
                        "which is not a character") from None
    except ValueError:  # str() of an integer longer than Python converts
        raise TypeError(f"cannot write as YAML: an integer has more than "
                        f"{sys.get_int_max_str_digits()} digits, the limit") from None
