"""CLI verbs for the robotics pipeline: ``osmo eval report`` and ``osmo view``.

``osmo eval report [WORKFLOW_IDS...]`` shows the reports task types declare
(``osmo.tasktypes.reports``): it finds the files each report reads among the workflows'
outputs (in the artifact store, through the SDK; or local files given as paths), and prints
the table the report makes of them (``sim.eval``'s: a leaderboard of policies across runs).
The format of those files is the task type's business, never this module's.
``osmo view TARGET`` turns an MCAP artifact or file into a rerun ``.rrd`` and opens the
viewer only with ``--open``.

The conversion is a viewer plugin's (``osmo.tasktypes.viewers``: the ``viz`` extra's
``rerun``); it is loaded only when ``view`` runs, so ``import osmo`` stays light.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from osmo.cli.render import console, print_json, safe
from osmo.errors import NotFoundError, UsageError
from osmo.sdk.client import Client

if TYPE_CHECKING:  # the registry reads entry points: imported when a verb needs it
    from osmo.tasktypes.reports import Report, Source, Table
    from osmo.tasktypes.viewers import Viewer

__all__ = ["add_parsers", "report_text", "run_eval", "run_view"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``eval`` and ``view`` on the top-level parser."""
    p = sub.add_parser("eval", help="evaluation results: osmo eval report [WORKFLOW_IDS...]")
    verbs = p.add_subparsers(dest="eval_verb", metavar="VERB", required=True)
    q = verbs.add_parser("report", help="the reports of evaluation task types (sim.eval: a "
                                        "leaderboard of policies)")
    q.add_argument("targets", nargs="*", metavar="WORKFLOW_ID_OR_FILE",
                   help="workflows (default: the 20 most recent) or local report files "
                        "(sim.eval: metrics.json)")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")

    p = sub.add_parser("view", help="MCAP artifact or file → rerun .rrd (viewer with --open)")
    p.add_argument("target", help="a local .mcap/.rrd file, WORKFLOW_ID:TASK[:PATH] or sha256:…")
    p.add_argument("--out", help="the .rrd to write (default: <name>.rrd here)")
    p.add_argument("--open", action="store_true", help="open the viewer on the result")
    p.add_argument("--viewer", metavar="NAME",
                   help="a viewer plugin (osmo.viewers entry points; default: rerun)")


def report_text(table: Table) -> str:
    """A report's table as aligned text, every cell escaped (``render.safe``), then its notes."""
    lines = [tuple(map(safe, row)) for row in (table.columns, *table.cells)]
    widths = [max(len(line[i]) for line in lines) for i in range(len(table.columns))]
    text = ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
            for line in lines]
    return "\n".join(text + (["", *map(safe, table.notes)] if table.notes else []))


def _read(reports: dict[str, Report], data: Any) -> tuple[str | None, str]:
    """The report (type name) ``data`` is a file of, else None and why the first refused it."""
    why = ""
    for name, report in reports.items():
        problem = report.problem(data)
        if problem is None:
            return name, ""
        why = why or problem
    return None, why


def _from_store(client: Client, workflow_id: str, scratch: Path, reports: dict[str, Report],
                found: dict[str, list[Source]]) -> None:
    """Add the report files among ``workflow_id``'s outputs to ``found`` (by type name)."""
    from osmo.tasktypes.reports import Source

    files = {report.file for report in reports.values()}
    for out in client.artifacts(workflow_id):
        for f in out["files"]:
            name = Path(f["path"]).name
            if name not in files:
                continue
            dest = scratch / f"{workflow_id}-{out['task']}-{sum(map(len, found.values()))}"
            client.get_artifact(f"{workflow_id}:{out['task']}:{f['path']}", dest)
            data = json.loads(next(dest.rglob(name)).read_text())
            kind, _ = _read({k: r for k, r in reports.items() if r.file == name}, data)
            if kind is not None:
                found[kind].append(Source(workflow_id, out["task"], data))


def run_eval(args: argparse.Namespace) -> int:
    """``osmo eval report``: the reports task types declare (``osmo.tasktypes.reports``)."""
    from osmo.tasktypes.reports import Source, installed_reports

    reports = installed_reports()
    found: dict[str, list[Source]] = {name: [] for name in reports}
    files = [t for t in args.targets if Path(t).is_file()]
    for path in files:
        data = json.loads(Path(path).read_text())
        kind, why = _read(reports, data)
        if kind is None:
            what = " or ".join(f"{name} {r.file}" for name, r in reports.items())
            raise UsageError(f"{path}: not a {what or 'report file'} ({why or 'no report'})")
        found[kind].append(Source("-", path, data))
    ids = [t for t in args.targets if t not in files]
    if ids or not files:
        with Client(args.server) as client, tempfile.TemporaryDirectory() as tmp:
            if not ids:
                ids = [w.id for w in client.list(limit=20)]
            for wf in ids:
                _from_store(client, wf, Path(tmp), reports, found)
    tables = [reports[name].table(sources) for name, sources in found.items() if sources]
    if args.format == "json":
        print_json([row for table in tables for row in table.rows])
    elif not tables:
        names = " or ".join(reports) or "evaluation"
        console.print(f"no {names} metrics found (run a workflow with a {names} task)",
                      markup=False)
    else:
        console.print("\n\n".join(map(report_text, tables)), markup=False, highlight=False,
                      soft_wrap=True)
    return 0 if tables or args.format == "json" else 1


def _convert(viewer: Viewer, path: Path, out: Path) -> Path:
    if path.suffix == viewer.suffix:
        if path.resolve() != out.resolve():
            shutil.copyfile(path, out)
        return out
    return viewer.convert(path, out)


def run_view(args: argparse.Namespace) -> int:
    """``osmo view TARGET``."""
    from osmo.tasktypes.viewers import find_viewer

    viewer = find_viewer(args.viewer)
    local = Path(args.target)
    with tempfile.TemporaryDirectory() as tmp:
        if local.is_file():
            source = local
        else:
            with Client(args.server) as client:
                client.get_artifact(args.target, tmp)
            candidates = sorted(p for p in Path(tmp).rglob("*")
                                if p.suffix in (".mcap", viewer.suffix))
            if not candidates:
                raise NotFoundError(f"{args.target}: no .mcap or {viewer.suffix} file in that "
                                    "artifact")
            if len(candidates) > 1:
                names = ", ".join(str(p.relative_to(tmp)) for p in candidates[:8])
                raise UsageError(f"{args.target} holds several files ({names}); name one as "
                                 "WORKFLOW_ID:TASK:PATH")
            source = candidates[0]
        out = Path(args.out) if args.out else Path(f"{source.stem}{viewer.suffix}")
        _convert(viewer, source, out)
    console.print(f"wrote {out}", markup=False)
    if args.open and not viewer.open(out):
        console.print(f"no display or {viewer.name} viewer here; open it elsewhere: "
                      f"{viewer.name} {out}", markup=False)
    return 0
