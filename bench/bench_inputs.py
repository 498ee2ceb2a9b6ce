"""What handing each attempt its own verified copy of its inputs costs: a fan-out whose
middle tasks each read the source's small output files.

Shape: 1 source writing ``--files`` files of ``--size`` bytes → N-2 tasks that each ``cat``
them → 1 join reading every middle output (empty). Same method as bench_engine.py (fresh
server per run, ``no_cache``, submit → COMPLETED); compare with its `true` fan-out row, whose
inputs are empty, to see the copies' share.

Usage: python bench/bench_inputs.py [--runs 3] [--tasks 1000] [--files 3] [--size 1024]
       [--base DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_engine import SPAWN_LIMIT, run_once  # noqa: E402
from benchlib import quick, row, write_rows  # noqa: E402

import osmo  # noqa: E402


def fan_out_reading(n: int, files: int, size: int) -> osmo.Workflow:
    """1 source writing small files, n-2 tasks reading them, 1 join."""
    wf = osmo.Workflow("bench-inputs")
    write = " && ".join(f"head -c {size} /dev/zero > {{{{output}}}}/f{i}" for i in range(files))
    wf.task("source", ["sh", "-c", write])
    middle = [f"m{i}" for i in range(n - 2)]
    for name in middle:
        wf.task(name, ["sh", "-c", "cat {{input:0}}/* > /dev/null"], inputs=["source"])
    wf.task("join", ["true"], inputs=middle)
    return wf


def main() -> None:
    """Run the shape ``--runs`` times and write the row."""
    small = quick()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if small else 3)
    parser.add_argument("--tasks", type=int, default=20 if small else 1000)
    parser.add_argument("--files", type=int, default=3)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--json")
    parser.add_argument("--base", help="folder for the OSMO_HOMEs (default: system temp)")
    args = parser.parse_args()
    spec = fan_out_reading(args.tasks, args.files, args.size).build()
    runs = [run_once(spec, args.base) for _ in range(args.runs)]
    name = (f"osmo fan-out/join {args.tasks:,} tasks reading {args.files} x {args.size} B "
            f"inputs ({args.base or tempfile.gettempdir()})")
    write_rows(args.json, [row(name, "tasks/s", [args.tasks / t for t in runs],
                               higher_is_better=True, limit_of=SPAWN_LIMIT,
                               notes=f"submit→COMPLETED median {statistics.median(runs):.2f} s")])


if __name__ == "__main__":
    main()
