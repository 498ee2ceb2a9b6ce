"""``osmo plugins list``: the task types installed in this Python environment.

Runs client-side (no server): it reads the ``osmo.task_types`` entry points and imports each
type, so a broken one shows its import error and the ``pip install`` that fixes it.
"""

from __future__ import annotations

import argparse
from typing import Any

from osmo.cli.render import console, plugin_table, print_json

__all__ = ["add_parsers", "plugin_rows", "run_plugins"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``plugins list``."""
    p = sub.add_parser("plugins", help="installed task types (plugins)")
    verbs = p.add_subparsers(dest="plugins_verb", metavar="VERB", required=True)
    q = verbs.add_parser("list", help="name, version, extra, description; broken ones with "
                                      "their import error")
    q.add_argument("-v", "--verbose", action="store_true", help="show each type's params")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")


def _param(param: Any) -> dict[str, Any]:
    from osmo.params import REQUIRED

    required = param.default is REQUIRED
    return {"type": getattr(param.type, "__name__", repr(param.type)), "required": required,
            "default": None if required else param.default, "help": param.help,
            "choices": list(param.choices), "min": param.min, "max": param.max}


def plugin_rows() -> list[dict[str, Any]]:
    """Every installed task type as plain data (JSON-safe)."""
    from osmo.tasktypes.registry import list_types

    return [{"name": t.name, "version": t.version, "extra": t.extra,
             "description": t.description, "ref": t.ref, "distribution": t.distribution,
             "error": t.error, "params": {n: _param(p) for n, p in t.params.items()}}
            for t in list_types()]


def run_plugins(args: argparse.Namespace) -> int:
    """``osmo plugins list``; exit 0 even when some types are broken (they are listed)."""
    rows = plugin_rows()
    if args.format == "json":
        print_json(rows)
    elif not rows:
        console.print("no task types installed (plugins register them in the "
                      "'osmo.task_types' entry-point group)", markup=False)
    else:
        console.print(plugin_table(rows, verbose=args.verbose))
    return 0
