"""CLI verbs for the robotics pipeline: ``osmo eval report`` and ``osmo view``.

``osmo eval report [WORKFLOW_IDS...]`` finds the ``metrics.json`` outputs of ``sim.eval``
tasks (in the artifact store, through the SDK; or local files given as paths) and shows one
leaderboard across runs, best mean return first per env, with each success rate's 95%
Wilson interval and its criterion as a footnote (``n/a`` where the suite had none) and the
normalised score. ``osmo view TARGET`` turns an MCAP artifact or file into a rerun ``.rrd``
and opens the viewer only with ``--open``.

The conversion is a viewer plugin's (``osmo.tasktypes.viewers``: the ``viz`` extra's
``rerun``); it is loaded only when ``view`` runs, so ``import osmo`` stays light.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from osmo.cli.render import console, print_json, safe
from osmo.errors import NotFoundError, UsageError
from osmo.sdk.client import Client

if TYPE_CHECKING:  # the registry reads entry points: imported when a viewer is asked for
    from osmo.tasktypes.viewers import Viewer

__all__ = ["add_parsers", "leaderboard_rows", "leaderboard_text", "run_eval", "run_view"]

METRICS_FILE = "metrics.json"


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``eval`` and ``view`` on the top-level parser."""
    p = sub.add_parser("eval", help="evaluation results: osmo eval report [WORKFLOW_IDS...]")
    verbs = p.add_subparsers(dest="eval_verb", metavar="VERB", required=True)
    q = verbs.add_parser("report", help="leaderboard of policies from sim.eval metrics.json")
    q.add_argument("targets", nargs="*", metavar="WORKFLOW_ID_OR_FILE",
                   help="workflows (default: the 20 most recent) or local metrics.json files")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")

    p = sub.add_parser("view", help="MCAP artifact or file → rerun .rrd (viewer with --open)")
    p.add_argument("target", help="a local .mcap/.rrd file, WORKFLOW_ID:TASK[:PATH] or sha256:…")
    p.add_argument("--out", help="the .rrd to write (default: <name>.rrd here)")
    p.add_argument("--open", action="store_true", help="open the viewer on the result")
    p.add_argument("--viewer", metavar="NAME",
                   help="a viewer plugin (osmo.viewers entry points; default: rerun)")


def leaderboard_rows(sources: list[tuple[str, str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """Flatten ``(workflow, task, metrics)`` into rows ranked per env by mean return.

    ``success_rate`` is None where the suite had no success criterion for the env;
    ``criterion`` says how success was decided (older metrics files: the suite's sentence).
    """
    rows = []
    for wf, task, metrics in sources:
        suite = metrics.get("suite", {})
        for r in metrics.get("results", []):
            rows.append({"workflow": wf, "task": task, **{k: r[k] for k in (
                "policy", "kind", "env", "episodes", "success_rate", "mean_return",
                "return_ci95", "mean_length")},
                "criterion": r.get("success_criterion") or _old_criterion(suite),
                "success_ci95": _success_ci(r),
                "normalized_score": r.get("normalized_score"),
                "normalized_ci95": r.get("normalized_ci95")})
    rows.sort(key=lambda r: (r["env"], -r["mean_return"], r["workflow"], r["policy"]))
    rank, env = 0, None
    for row in rows:
        rank = rank + 1 if row["env"] == env else 1
        env = row["env"]
        row["rank"] = rank
    return rows


def wilson95(successes: int, n: int) -> tuple[float, float] | None:
    """The 95% Wilson score interval of a success rate (None for no episodes).

    Unlike the normal approximation it stays inside [0, 1] and is not a point at 0 or n
    successes: 20 of 20 is [0.84, 1].
    """
    if n <= 0:
        return None
    z = 1.959964
    p = successes / n
    scale = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / scale
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / scale
    return max(0.0, centre - half), min(1.0, centre + half)


def _success_ci(row: dict[str, Any]) -> list[float] | None:
    rate, n = row.get("success_rate"), row.get("episodes")
    if rate is None or not isinstance(n, int):
        return None
    ci = wilson95(round(rate * n), n)
    return None if ci is None else list(ci)


def _old_criterion(suite: dict[str, Any]) -> str | None:
    """The criterion of a metrics file written before success was defined per env."""
    text = suite.get("success")
    return f"{text} (older sim.eval)" if isinstance(text, str) else None


def leaderboard_text(rows: list[dict[str, Any]]) -> str:
    """The leaderboard as aligned text.

    Each success rate is marked with its criterion's footnote (``n/a`` where there was none).
    """
    notes: dict[str, int] = {}
    table = [["Env", "#", "Policy", "Workflow", "Task", "Success (95% CI)", "Return (95% CI)",
              "Normalised", "Length", "Episodes"]]
    for r in rows:
        mark = notes.setdefault(r["criterion"] or "not recorded", len(notes) + 1)
        rate = r["success_rate"]
        lo, hi = r["return_ci95"]
        norm = r["normalized_score"]
        table.append([
            safe(r["env"]), str(r["rank"]), safe(r["policy"]), safe(r["workflow"]),
            safe(r["task"]),
            f"{_rate_text(rate, r['success_ci95'])} [{mark}]",
            f"{r['mean_return']:.1f} [{lo:.1f}, {hi:.1f}]",
            "-" if norm is None else f"{norm:.2f}", f"{r['mean_length']:.0f}",
            str(r["episodes"])])
    widths = [max(len(line[i]) for line in table) for i in range(len(table[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
             for line in table]
    lines.append("")
    lines.append("Success criteria:")
    lines.extend(f"  [{n}] {safe(text)}" for text, n in notes.items())
    if any(r["normalized_score"] is not None for r in rows):
        lines.append("Normalised: (return - random) / (expert - random) in the same suite.")
    return "\n".join(lines)


def _rate_text(rate: float | None, ci: list[float] | None) -> str:
    if rate is None:
        return "n/a"
    return f"{100 * rate:.0f}%" + ("" if ci is None else
                                   f" [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]")


def _is_metrics(data: Any) -> bool:
    return isinstance(data, dict) and isinstance(data.get("results"), list) and "suite" in data


def _from_store(client: Client, workflow_id: str, scratch: Path) -> list[tuple[str, str, Any]]:
    found: list[tuple[str, str, Any]] = []
    for out in client.artifacts(workflow_id):
        for f in out["files"]:
            if Path(f["path"]).name != METRICS_FILE:
                continue
            dest = scratch / f"{workflow_id}-{out['task']}-{len(found)}"
            client.get_artifact(f"{workflow_id}:{out['task']}:{f['path']}", dest)
            data = json.loads(next(dest.rglob(METRICS_FILE)).read_text())
            if _is_metrics(data):
                found.append((workflow_id, out["task"], data))
    return found


def run_eval(args: argparse.Namespace) -> int:
    """``osmo eval report``."""
    sources: list[tuple[str, str, Any]] = []
    files = [t for t in args.targets if Path(t).is_file()]
    for path in files:
        data = json.loads(Path(path).read_text())
        if not _is_metrics(data):
            raise UsageError(f"{path}: not a sim.eval metrics.json (no suite/results)")
        sources.append(("-", path, data))
    ids = [t for t in args.targets if t not in files]
    if ids or not files:
        with Client(args.server) as client, tempfile.TemporaryDirectory() as tmp:
            if not ids:
                ids = [w.id for w in client.list(limit=20)]
            for wf in ids:
                sources.extend(_from_store(client, wf, Path(tmp)))
    rows = leaderboard_rows(sources)
    if args.format == "json":
        print_json(rows)
    elif not rows:
        console.print("no sim.eval metrics found (run a workflow with a sim.eval task)",
                      markup=False)
    else:
        console.print(leaderboard_text(rows), markup=False, highlight=False, soft_wrap=True)
    return 0 if rows or args.format == "json" else 1


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
