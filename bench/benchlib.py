"""The row protocol shared by every ``bench/bench_*.py`` script and the ``bench/run`` harness.

A benchmark script accepts ``--json PATH`` and writes there a JSON list of rows::

    {"name": str, "unit": str, "median": float, "min": float, "max": float, "runs": int,
     "higher_is_better": bool,
     "limit": float,      # optional: the machine's own limit for this figure, same unit
     "limit_of": str,     # optional: name of another row (any script) that is the limit
     "target": float,     # optional: the figure the issue asks for, same unit
     "notes": str}        # optional

The harness sets ``OSMO_BENCH_QUICK=1`` for ``bench/run --quick``: a script should then use
tiny sizes and one run (it is a smoke test of the script, not a measurement). This module
only depends on the standard library, so the peer scripts (another virtualenv) can use it.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["Row", "machine_info", "quick", "row", "timed", "write_rows"]

Row = dict[str, Any]


def quick() -> bool:
    """True when the harness asked for a smoke run (tiny sizes, one run)."""
    return os.environ.get("OSMO_BENCH_QUICK") == "1"


def row(name: str, unit: str, values: Sequence[float], *, higher_is_better: bool,
        limit: float | None = None, limit_of: str | None = None,
        target: float | None = None, notes: str | None = None) -> Row:
    """Summarise ``values`` (one per run) as a protocol row and print it."""
    out: Row = {"name": name, "unit": unit, "median": float(statistics.median(values)),
                "min": float(min(values)), "max": float(max(values)), "runs": len(values),
                "higher_is_better": higher_is_better}
    for key, value in (("limit", limit), ("limit_of", limit_of), ("target", target),
                       ("notes", notes)):
        if value is not None:
            out[key] = value
    print(f"  {name:<58} {out['median']:>12,.3f} {unit}  "
          f"(min {out['min']:,.3f}, max {out['max']:,.3f}, runs {len(values)})", flush=True)
    return out


def timed(fn: Callable[[], object], runs: int) -> list[float]:
    """Wall-clock seconds of ``fn()`` for each of ``runs`` calls."""
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def write_rows(path: str | None, rows: list[Row]) -> None:
    """Write ``rows`` as JSON to ``path`` (no-op without a path)."""
    if path:
        Path(path).write_text(json.dumps(rows, indent=2, ensure_ascii=False) + "\n")


def machine_info() -> dict[str, Any]:
    """CPU model (and whether it has SHA extensions), cores, Python, kernel and the date."""
    cpu = platform.processor() or platform.machine()
    try:
        text = Path("/proc/cpuinfo").read_text()
        for line in text.splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        cpu += " (sha_ni)" if " sha_ni" in text else ""
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else (0.0, 0.0, 0.0)
    return {"cpu": cpu, "cores": os.cpu_count(), "arch": platform.machine(),
            "python": platform.python_version(),
            "kernel": f"{platform.system()} {platform.release()}",
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "loadavg_1m_at_start": round(load[0], 2)}
