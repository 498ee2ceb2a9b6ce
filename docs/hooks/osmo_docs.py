"""MkDocs hook: the reference pages that are generated, so they cannot drift.

A page holds a marker on a line of its own and this hook replaces it when the site is built:

- ``<!-- generated: cli -->``: every verb of ``osmo.cli.main.build_parser()``, with its usage,
  arguments, defaults and help, walked from the argparse parser itself;
- ``<!-- generated: helm-values -->``: every documented key of ``helm/osmo/values.yaml``
  (helm-docs style ``# --`` comments), with its default read from the YAML.

A code block the docs tests do not run carries ``<!-- not run: REASON -->`` on the line before
it (``tests/docs/blocks.py``); the hook shows that reason to the reader too.

The functions are importable (``tests/docs`` checks what they produce) and need only the
standard library, PyYAML and osmo itself.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
VALUES = REPO / "helm" / "osmo" / "values.yaml"
_MARKER = re.compile(r"^<!-- generated: ([a-z-]+) -->$", re.M)
_NOT_RUN = re.compile(r"^<!-- not run: (.*?) -->$", re.M)
_TEST = re.compile(r"(tests/[\w/]+\.py(?:::\w+)?)")


def on_page_markdown(markdown: str, **_: Any) -> str:
    """Replace each ``<!-- generated: NAME -->`` line with what NAME generates."""
    makers = {"cli": cli_markdown, "helm-values": helm_values_markdown}

    def replace(m: re.Match[str]) -> str:
        if m.group(1) not in makers:
            raise ValueError(f"unknown generated section {m.group(1)!r}")
        return makers[m.group(1)]()

    def not_run(m: re.Match[str]) -> str:
        reason = _TEST.sub(r"`\1`", m.group(1))
        return f"_Not run by the docs tests:_ {reason}.\n"

    return _NOT_RUN.sub(not_run, _MARKER.sub(replace, markdown))


# --- the CLI ---------------------------------------------------------------------------------

_Sub = tuple[str, list[str], str, argparse.ArgumentParser]


def _subparsers(parser: argparse.ArgumentParser) -> Iterator[_Sub]:
    """(name, aliases, help, parser) of each direct sub-command, in declaration order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {c.dest: c.help or "" for c in action._choices_actions}
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:
                    continue
                seen.add(id(sub))
                aliases = [n for n, s in action.choices.items() if s is sub and n != name]
                yield name, aliases, helps.get(name, ""), sub


def _escape(text: str) -> str:
    """Prose for a table cell (a pipe inside a code span needs no escape: Python-Markdown)."""
    return text.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _argument_rows(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for a in parser._actions:
        if a.help == argparse.SUPPRESS or isinstance(a, (argparse._HelpAction,
                                                           argparse._SubParsersAction)):
            continue
        if a.option_strings:
            name = ", ".join(a.option_strings)
            if a.nargs != 0:
                name += f" {a.metavar or a.dest.upper()}"
        else:
            name = str(a.metavar or a.dest)
        default = a.default
        shown = "" if default in (None, False, argparse.SUPPRESS) or a.nargs == 0 else (
            f"`{default}`")
        choices = f" One of: {', '.join(f'`{c}`' for c in a.choices)}." if a.choices else ""
        repeat = " Repeatable." if isinstance(a, (argparse._AppendAction,
                                                 argparse._ExtendAction)) else ""
        rows.append(f"| `{name}` | {shown} | {_escape(a.help or '')}{choices}{repeat} |")
    return rows


def _verb_markdown(path: str, aliases: list[str], help_text: str,
                   parser: argparse.ArgumentParser, depth: int) -> list[str]:
    out = [f"{'#' * depth} `{path}`", ""]
    if aliases:
        parent = path.rsplit(" ", 1)[0]
        out += ["Alias: " + ", ".join(f"`{parent} {a}`" for a in aliases) + ".", ""]
    if help_text or parser.description:
        out += [_escape(parser.description or help_text), ""]
    out += ["```text", parser.format_usage().strip(), "```", ""]
    rows = _argument_rows(parser)
    if rows:
        out += ["| argument | default | meaning |", "|---|---|---|", *rows, ""]
    for name, names, sub_help, sub in _subparsers(parser):
        if path == "osmo workflow":
            continue  # the same verbs as the top level (said on the page)
        out += _verb_markdown(f"{path} {name}", names, sub_help, sub, min(depth + 1, 4))
    return out


def cli_markdown() -> str:
    """The CLI reference: every verb of the real parser, at a fixed width of 100 columns."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        if str(REPO) not in sys.path:
            sys.path.insert(0, str(REPO))
        from osmo.cli.main import build_parser

        parser = build_parser()
        return "\n".join(_verb_markdown("osmo", [], "", parser, 2)) + "\n"
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


# --- Helm values -----------------------------------------------------------------------------

_KEY = re.compile(r"^( *)(- )?([A-Za-z0-9_.-]+):(.*)$")


def helm_values() -> list[tuple[str, Any, str]]:
    """(dotted key, default, description) of every ``# --`` documented key of values.yaml."""
    import yaml

    data = yaml.safe_load(VALUES.read_text())
    rows: list[tuple[str, Any, str]] = []
    stack: list[tuple[int, str]] = []
    comment: list[str] = []
    documented = False
    for line in VALUES.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("# --"):
            comment, documented = [stripped[4:].strip()], True
            continue
        if stripped.startswith("#"):
            if documented:
                comment.append(stripped[1:].strip())
            continue
        m = _KEY.match(line)
        if not stripped or m is None or m.group(2):
            if not stripped:
                comment, documented = [], False
            continue
        indent, key = len(m.group(1)), m.group(3)
        while stack and stack[-1][0] >= indent:
            stack.pop()
        path = [k for _, k in stack] + [key]
        if documented and not any(p.startswith("\0") for p in path):
            value: Any = data
            for k in path:
                value = value[k]
            rows.append((".".join(path), value, " ".join(comment)))
            key = "\0" + key  # what lies under a documented key is its default, not a row
        stack.append((indent, key))
        comment, documented = [], False
    return rows


def helm_values_markdown() -> str:
    """The Helm values table, one row per documented key."""
    out = ["| key | default | meaning |", "|---|---|---|"]
    for key, value, text in helm_values():
        shown = json.dumps(value, separators=(", ", ": "))
        out.append(f"| `{key}` | `{shown}` | {_escape(text)} |")
    return "\n".join(out) + "\n"
