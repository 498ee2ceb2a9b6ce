"""Plain data (a spec sent or stored as JSON-like values) as the node tree the parser reads.

Owns :func:`from_plain`: the fast way to check a spec given as data (the SDK's, a stored
one), with no YAML text written or parsed. It must give, for any data it accepts, the tree
:func:`osmo.spec.yamlnodes.load_nodes` would read from :func:`osmo.spec.yamlnodes.dump`'s
text of it, and refuse (None) whatever that round trip would change or reject, so that the
caller takes the YAML way and reports it with positions. It imports no YAML library.
"""

from __future__ import annotations

import re
from typing import Any

from osmo.spec.model import Pos
from osmo.spec.yamlnodes import MAX_DEPTH, Map, Node, Scalar, Seq, float_text

__all__ = ["from_plain"]

_LONE_SURROGATE = re.compile("[\ud800-\udfff]")
_MAX_INT_BITS = 14_000  # ints longer than ~4,300 digits: the YAML path reports them


class _NotPlain(Exception):
    pass


def from_plain(data: Any, file: str) -> Node | None:
    """Plain data as a node tree, as ``load_nodes`` would read ``dump``'s text of it.

    Values and scalar texts are those the YAML round trip gives (a float's text is its YAML
    form, a bool's ``true``/``false``); every position is line 0 of ``file``. None when the
    data holds anything the round trip would change or refuse (another type, a lone
    surrogate, an integer longer than Python reads back, nesting deeper than
    :data:`~osmo.spec.yamlnodes.MAX_DEPTH`).
    """
    try:
        return _Plain(Pos(file, 0, 0)).node(data, 0)
    except _NotPlain:
        return None


class _Plain:
    """One conversion.

    Equal scalars share one node: a spec of many alike tasks repeats the same keys and values
    (``name``, ``command``, ``true``...) hundreds of thousands of times, and the parser never
    changes a node.
    """

    def __init__(self, pos: Pos) -> None:
        self.pos = pos
        self.scalars: dict[tuple[type, Any], Scalar] = {}

    def node(self, data: Any, depth: int) -> Node:
        if isinstance(data, dict):
            if depth >= MAX_DEPTH:
                raise _NotPlain
            return Map(self.pos, [(self.scalar(key), self.node(value, depth + 1))
                                  for key, value in data.items()])
        if isinstance(data, list):
            if depth >= MAX_DEPTH:
                raise _NotPlain
            return Seq(self.pos, [self.node(item, depth + 1) for item in data])
        return self.scalar(data)

    def scalar(self, value: Any) -> Scalar:
        key = (type(value), value)  # the type too: 1, 1.0 and True are equal dict keys
        try:
            return self.scalars[key]
        except KeyError:
            pass
        except TypeError:  # not hashable, so not plain
            raise _NotPlain from None
        node = self.scalars[key] = _scalar(value, self.pos)
        return node


def _scalar(value: Any, pos: Pos) -> Scalar:
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
        return Scalar(pos, value, float_text(value))
    raise _NotPlain
