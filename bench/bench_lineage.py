"""Lineage overhead per task: what osmo adds to each completed attempt for artifacts.

For a 1,000-task chain this times exactly the work the server does per attempt beyond running
it: ingest the output folder (one small file, sha256, hard link), read the inputs' manifests
at placement, build the lineage record, and commit the manifest, blob, output and lineage
rows to the real SQLite store (one transaction per task, as in a chain). Prints the median
of several runs with min/max. The end-to-end effect is in bench_engine.py's numbers, which
include all of this.

Usage: python bench/bench_lineage.py [--runs 3] [--tasks 1000] [--base DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import quick, row, write_rows  # noqa: E402

from osmo.artifacts import ArtifactStore  # noqa: E402
from osmo.scheduler.types import AttemptExited, Changes, PrepareAttempt  # noqa: E402
from osmo.server.cache import input_sources  # noqa: E402
from osmo.server.provenance import Provenance  # noqa: E402
from osmo.spec.model import TaskSpec  # noqa: E402
from osmo.store.sqlite import Store  # noqa: E402


def one_run(n: int, base: str | None) -> tuple[float, float]:
    """Seconds per task for (ingest, lineage record + commit)."""
    with tempfile.TemporaryDirectory(dir=base) as tmp:
        root = Path(tmp)
        store = Store(root / "state.db")
        artifacts = ArtifactStore(root / "artifacts")
        provenance = Provenance()
        task = TaskSpec(name="t", command=("sh", "-c", "echo $RANDOM > {{output}}/x"))
        folders = []
        for i in range(n):
            out = root / "runs" / f"t{i}" / "output"
            out.mkdir(parents=True)
            (out / "x.txt").write_text(f"value {i}\n")
            folders.append(out)
        t0 = time.perf_counter()
        manifests = [artifacts.ingest(f) for f in folders]
        t1 = time.perf_counter()
        previous: str | None = None
        for i, (folder, manifest) in enumerate(zip(folders, manifests, strict=True)):
            aid = f"w-1:t{i}:0"
            cmd = PrepareAttempt(aid, "w-1", f"t{i}", 0, "local",
                                 {f"t{i - 1}": previous} if previous else {}, {}, run=True)
            provenance.placed(cmd, "127.0.0.1", None, input_sources(store, cmd))
            row = provenance.exited(AttemptExited(aid, 0, str(folder), manifest=manifest.to_json()),
                                    task, started_at=t1, now=time.time())
            assert row is not None
            store.commit(Changes(), lineage=[row])
            previous = str(folder)
        t2 = time.perf_counter()
        store.close()
    return (t1 - t0) / n, (t2 - t1) / n


def main() -> None:
    """Measure ``--runs`` chains and write the rows (ms per task)."""
    small = quick()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if small else 3)
    parser.add_argument("--tasks", type=int, default=20 if small else 1000)
    parser.add_argument("--base")
    parser.add_argument("--json")
    args = parser.parse_args()
    runs = [one_run(args.tasks, args.base) for _ in range(args.runs)]
    where = f"{args.tasks:,}-task chain under {args.base or tempfile.gettempdir()}"
    rows = [
        row("lineage: ingest one small output", "ms/task", [r[0] * 1000 for r in runs],
            higher_is_better=False, notes=where),
        row("lineage: inputs read + record + commit", "ms/task", [r[1] * 1000 for r in runs],
            higher_is_better=False),
        row("lineage: overhead per task (total)", "ms/task", [sum(r) * 1000 for r in runs],
            higher_is_better=False, target=1.0, notes=where),
    ]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
