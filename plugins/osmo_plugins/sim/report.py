"""``sim.eval``'s report: one leaderboard of its ``metrics.json`` files across runs.

``osmo eval report`` shows it (``osmo.tasktypes.reports``): rows ranked per env by mean
return, each success rate with its 95% Wilson interval and its criterion as a footnote
(``n/a`` where the suite had none), and the normalised score. Pure Python: it imports
nothing of the ``sim`` extra, so the report works wherever osmo is installed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from osmo.tasktypes.reports import Source, Table

__all__ = ["LEADERBOARD", "Leaderboard", "leaderboard_rows", "wilson95"]

COLUMNS = ("Env", "#", "Policy", "Workflow", "Task", "Success (95% CI)", "Return (95% CI)",
           "Normalised", "Length", "Episodes")


class Leaderboard:
    """The report ``sim.eval`` declares (the ``osmo.tasktypes.reports.Report`` shape)."""

    file = "metrics.json"

    def problem(self, data: Any) -> str | None:
        """None for a ``sim.eval`` metrics file; else what it lacks."""
        if isinstance(data, dict) and isinstance(data.get("results"), list) and "suite" in data:
            return None
        return "no suite/results"

    def table(self, sources: Sequence[Source]) -> Table:
        """The leaderboard of every source's results."""
        rows = leaderboard_rows([(s.workflow, s.task, s.data) for s in sources])
        notes: dict[str, int] = {}
        cells = []
        for r in rows:
            mark = notes.setdefault(r["criterion"] or "not recorded", len(notes) + 1)
            lo, hi = r["return_ci95"]
            norm = r["normalized_score"]
            cells.append((
                str(r["env"]), str(r["rank"]), str(r["policy"]), str(r["workflow"]),
                str(r["task"]), f"{_rate_text(r['success_rate'], r['success_ci95'])} [{mark}]",
                f"{r['mean_return']:.1f} [{lo:.1f}, {hi:.1f}]",
                "-" if norm is None else f"{norm:.2f}", f"{r['mean_length']:.0f}",
                str(r["episodes"])))
        lines = ["Success criteria:", *(f"  [{n}] {text}" for text, n in notes.items())]
        if any(r["normalized_score"] is not None for r in rows):
            lines.append("Normalised: (return - random) / (expert - random) in the same suite.")
        return Table(COLUMNS, tuple(cells), tuple(rows), tuple(lines))


LEADERBOARD = Leaderboard()
"""The report of ``sim.eval`` (``osmo_plugins.sim.eval.EVAL.report``)."""


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


def _rate_text(rate: float | None, ci: list[float] | None) -> str:
    if rate is None:
        return "n/a"
    return f"{100 * rate:.0f}%" + ("" if ci is None else
                                   f" [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]")
