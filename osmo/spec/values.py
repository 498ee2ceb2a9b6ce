"""Template values: ``default-values`` of a spec file, overridden by ``--set``/``--set-string``.

Pure functions (the ``default-values`` block is read with the YAML adapter); no Jinja, so the
caller can check ``--set`` items without loading the template engine.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

from osmo.errors import Diagnostic
from osmo.spec.yamlnodes import Map, load_nodes, to_plain

__all__ = ["build_context", "item_diags", "split_items"]


def _cast(value: str) -> Any:
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:  # not a number, or an int beyond Python's digit limit
            pass
    return value


def split_items(file: str, flag: str,
                items: Sequence[str]) -> tuple[dict[str, str], list[Diagnostic]]:
    """``NAME=VALUE`` items of a command-line ``flag`` → (name → value, problems)."""
    out: dict[str, str] = {}
    diags = []
    for item in items:
        name, eq, value = item.partition("=")
        if not eq or not name.strip():
            diags.append(Diagnostic(file, 0, 0, f"{flag} {item!r}: expected NAME=VALUE"))
        else:
            out[name.strip()] = value
    return out, diags


def item_diags(file: str, set_values: Sequence[str],
               set_strings: Sequence[str]) -> list[Diagnostic]:
    """The problems of malformed ``--set``/``--set-string`` items (not ``NAME=VALUE``)."""
    return split_items(file, "--set", set_values)[1] + split_items(
        file, "--set-string", set_strings)[1]


def _default_values_block(text: str) -> str | None:
    """The top-level ``default-values:`` block, with the other lines blanked.

    Earlier lines are blanked so that line numbers stay those of the file (the raw file may not be
    YAML before rendering).
    """
    lines = text.splitlines()
    for start, line in enumerate(lines):
        if re.match(r"default-values\s*:", line):
            end = start + 1
            while end < len(lines) and not re.match(r"[^\s#]", lines[end]):
                end += 1
            return "\n" * start + "\n".join(lines[start:end]) + "\n"
    return None


def build_context(text: str, file: str, set_values: Sequence[str] = (),
                  set_strings: Sequence[str] = ()) -> tuple[dict[str, Any], list[Diagnostic]]:
    """The template context: default values, then ``--set``, then ``--set-string``.

    ``default-values`` of ``text``, then ``--set`` (cast to int, then float, else kept as a string),
    then ``--set-string`` (kept as a string).
    """
    context: dict[str, Any] = {}
    diags: list[Diagnostic] = []
    block = _default_values_block(text)
    if block is not None:
        root, diags = load_nodes(block, file)
        values = root.get("default-values") if isinstance(root, Map) else None
        if isinstance(values, Map):
            context.update(to_plain(values))
    sets, bad = split_items(file, "--set", set_values)
    strings, bad2 = split_items(file, "--set-string", set_strings)
    context.update({k: _cast(v) for k, v in sets.items()})
    context.update(strings)
    return context, diags + bad + bad2
