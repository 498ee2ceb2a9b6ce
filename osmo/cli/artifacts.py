"""CLI verbs for artifacts and lineage: ``osmo artifacts list|get|gc`` and ``osmo lineage``.

``osmo lineage`` also reads a local file: an MCAP written with ``osmo.record`` carries its
own lineage (shown even with no server or store), and any other file is looked up by its
sha256 digest.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
from pathlib import Path
from typing import Any

from osmo.cli.render import console, print_error, print_json, safe, transfer_progress
from osmo.errors import OsmoError, UsageError
from osmo.sdk.client import Client

__all__ = ["add_parsers", "run_artifacts", "run_lineage"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``artifacts`` and ``lineage`` on the top-level parser."""
    p = sub.add_parser("artifacts", help="list, fetch or garbage-collect artifacts")
    verbs = p.add_subparsers(dest="artifacts_verb", metavar="VERB", required=True)
    q = verbs.add_parser("list", help="outputs of a workflow (or one task) with their files")
    q.add_argument("workflow_id")
    q.add_argument("task", nargs="?")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")
    q = verbs.add_parser("get", help="write an artifact's files (verified) to a folder")
    q.add_argument("target", help="sha256:<digest> or WORKFLOW_ID:TASK[:PATH]")
    q.add_argument("-o", "--output", required=True, help="destination folder")
    q.add_argument("--force", action="store_true",
                   help="replace DEST if it is a file or a symlink to nothing")
    verbs.add_parser("gc", help="remove blobs that no recorded output references")

    p = sub.add_parser("lineage", help="what made an artifact (or, --downstream, what used it)")
    p.add_argument("target", help="sha256:<digest>, WORKFLOW_ID:TASK[:PATH], or a local file")
    p.add_argument("--downstream", action="store_true", help="consumers instead of sources")
    p.add_argument("--format", "-t", dest="format", choices=("text", "json", "dot"),
                   default="text")


def run_artifacts(args: argparse.Namespace) -> int:
    """``osmo artifacts list|get|gc``."""
    with Client(args.server) as client:
        if args.artifacts_verb == "list":
            outputs = client.artifacts(args.workflow_id, args.task)
            if args.format == "json":
                print_json(outputs)
            for out in outputs if args.format == "text" else ():
                console.print(safe(f"{out['task']}  {out['manifest']}  ({out['attempt_id']})"),
                              markup=False)
                for f in out["files"]:
                    console.print(f"  {safe(f['path'])}  {f['size']} B  {f['digest']}",
                                  markup=False)
        elif args.artifacts_verb == "get":
            _make_room(Path(args.output), force=args.force)
            try:
                with transfer_progress(f"get {args.target}") as progress:
                    written = client.get_artifact(args.target, args.output,
                                                  on_progress=progress)
            except OSError as exc:  # the destination the user chose cannot be written
                raise UsageError(f"cannot write into {safe(args.output)}: "
                                 f"{exc.strerror or exc}") from None
            for path in written:
                console.print(safe(path), markup=False)
        else:
            count, size = client.gc_artifacts()
            console.print(f"removed {count} unreferenced blob(s), {size} bytes", markup=False)
    return 0


def _make_room(dest: Path, *, force: bool) -> None:
    """Refuse (or, with ``--force``, remove) a DEST that exists and is not a folder."""
    if not os.path.lexists(dest) or dest.is_dir():
        return
    if not force:
        kind = "a symlink to nothing" if dest.is_symlink() else "a file"
        raise UsageError(f"{safe(dest)} is {kind}, not a folder; choose a folder, "
                         "or pass --force to replace it")
    dest.unlink()


def run_lineage(args: argparse.Namespace) -> int:
    """``osmo lineage TARGET``."""
    target, embedded = args.target, None
    path = Path(args.target)
    if path.is_file():
        embedded = _embedded(path)
        target = f"sha256:{_sha256(path)}"
        if embedded is not None and not embedded.get("inputs"):
            return _print(args.format, _single(embedded, target), downstream=False)
    if embedded is not None:
        graph = _single(embedded, target)
        try:  # the inputs' own lineage needs the store; the file's record does not
            with Client(args.server, autostart=False) as client:
                for source in embedded.get("inputs", []):
                    _merge(graph, client.lineage(source["manifest"]))
                    graph["edges"].append([source["manifest"], target])
        except OsmoError as exc:
            print_error(f"showing only the lineage stored in {path} ({exc})")
        return _print(args.format, graph, downstream=False)
    with Client(args.server) as client:
        graph = client.lineage(target, downstream=args.downstream)
    return _print(args.format, graph, downstream=args.downstream)


def _embedded(path: Path) -> dict[str, Any] | None:
    if path.suffix != ".mcap":
        return None
    from osmo.record import read_lineage

    lineage = read_lineage(path)
    return lineage.to_dict() if lineage is not None else None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _single(record: dict[str, Any], key: str) -> dict[str, Any]:
    return {"target": key, "roots": [key], "nodes": {key: record}, "edges": [],
            "downstream": False, "embedded": True}


def _merge(graph: dict[str, Any], other: dict[str, Any]) -> None:
    graph["nodes"].update(other["nodes"])
    graph["edges"] += other["edges"]


def _print(fmt: str, graph: dict[str, Any], *, downstream: bool) -> int:
    if fmt == "json":
        print_json(graph)
    elif fmt == "dot":
        sys.stdout.write(_dot(graph))
    else:
        for line in _tree(graph, downstream):
            console.print(safe(line), markup=False)
    return 0


def _label(key: str, node: dict[str, Any]) -> str:
    if "task" not in node:
        return f"{key[:19]}… (no recorded producer)"
    retry = f" retry {node['retry']}" if node.get("retry") else ""
    command = " ".join(node.get("command") or ()) or node.get("plugin") or ""
    ran = f" exit {node['exit_code']}: {command[:60]}" if node.get("exit_code") is not None else ""
    return f"{node['task']} [{node['workflow_id']}{retry}] → {key[:19]}…{ran}"


def _tree(graph: dict[str, Any], downstream: bool) -> list[str]:
    children: dict[str, list[str]] = {}
    for a, b in graph["edges"]:
        parent, child = (a, b) if downstream else (b, a)
        children.setdefault(parent, []).append(child)
    lines: list[str] = []
    seen: set[str] = set()

    def walk(key: str, prefix: str, last: bool, top: bool) -> None:
        branch = "" if top else ("└── " if last else "├── ")
        again = key in seen
        lines.append(prefix + branch + _label(key, graph["nodes"].get(key, {}))
                     + (" (see above)" if again else ""))
        seen.add(key)
        if again:
            return
        kids = sorted(set(children.get(key, [])))
        inner = prefix + ("" if top else ("    " if last else "│   "))
        for i, kid in enumerate(kids):
            walk(kid, inner, i == len(kids) - 1, False)

    for root in graph["roots"]:
        walk(root, "", True, True)
    return lines


def _dot(graph: dict[str, Any]) -> str:
    out = ["digraph lineage {", "  rankdir=LR;"]
    for key, node in graph["nodes"].items():
        label = f"{node.get('task', '?')}\\n{node.get('workflow_id', '')}\\n{key[7:19]}"
        out.append(f'  "{key}" [shape=box, label="{label}"];')
    for a, b in graph["edges"]:
        out.append(f'  "{a}" -> "{b}";')
    out.append("}")
    return "\n".join(out) + "\n"
