"""Artifact ingest throughput: hashing + storing a 1 GiB output, and many small files.

Cases, each the median of N runs (min/max), in MiB/s of output:

- **limit: sha256 in memory** — hashlib over 1 GiB already in memory, 1 MiB updates. No
  ingest can beat this: every byte must be hashed once.
- **limit: sha256 of the file** — the same over the file, read with 1 MiB ``readinto``.
- **ingest, new blob, same filesystem** — ``ArtifactStore.ingest`` into a fresh store (hash,
  then ``os.link``; no copy).
- **ingest, blob exists** — ingest the same content again (hash only; dedup).
- **ingest, new blob, across filesystems** — output on ``/dev/shm``, store on ``--base``:
  hash, copy, fsync, link (disk-bound).
- **8 files** — the same bytes split into 8 files, which ingest hashes on a thread pool.
- **materialize** — write the 1 GiB file back out of the store, verified.
- **small files** — 10,000 files of 4 KiB in 100 folders (files/s; metadata-bound).

The file is written once and stays in the page cache (warm reads), which is the common case
right after a task wrote its outputs. Target from the brief: ≥ 500 MiB/s for the same-filesystem
ingest of a 1 GiB file.

Every ingest and materialize row carries the file-hashing row's median as its limit.

Usage: python bench/bench_ingest.py [--runs 3] [--mib 1024] [--small 10000] [--base DIR]
       [--json out.json]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import Row, quick, row, write_rows  # noqa: E402

from osmo.artifacts import ArtifactStore  # noqa: E402
from osmo.artifacts.fsops import hash_fd  # noqa: E402

MiB = 1 << 20


def fs_type(path: Path) -> str:
    """Return the filesystem type that holds ``path`` (from /proc/mounts), or '?'."""
    best, kind = "", "?"
    try:
        for line in Path("/proc/mounts").read_text().splitlines():
            _, mnt, typ, *_ = line.split()
            if str(path.resolve()).startswith(mnt) and len(mnt) > len(best):
                best, kind = mnt, typ
    except OSError:
        pass
    return kind


def timed(runs: int, setup: Callable[[], object], work: Callable[[object], object]
          ) -> list[float]:
    """Run ``work(setup())`` ``runs`` times; return the durations of ``work`` alone."""
    out = []
    for _ in range(runs):
        arg = setup()
        t0 = time.perf_counter()
        work(arg)
        out.append(time.perf_counter() - t0)
    return out


def report(name: str, times: list[float], amount: float, unit: str,
           limit: float | None = None, target: float | None = None) -> Row:
    """One protocol row: the rate of each run (``amount`` per second)."""
    return row(f"ingest: {name}", unit, [amount / t for t in times], higher_is_better=True,
               limit=limit, target=target)


def write_random(path: Path, mib: int) -> None:
    """Write ``mib`` MiB of random bytes to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    block = os.urandom(16 * MiB)
    with open(path, "wb") as f:
        for i in range(0, mib, 16):
            f.write(block[: min(16, mib - i) * MiB])
            block = hashlib.sha512(block[:64]).digest() + block[64:]  # vary each block


def main() -> None:
    """Run every case and write the rows."""
    small_run = quick()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1 if small_run else 3)
    ap.add_argument("--mib", type=int, default=8 if small_run else 1024)
    ap.add_argument("--small", type=int, default=200 if small_run else 10_000,
                    help="number of 4 KiB files in the small-files case")
    ap.add_argument("--base", default=None, help="folder for outputs and stores (default: tmp)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    results: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="osmo-bench-ingest-", dir=args.base) as tmp:
        base = Path(tmp)
        print(f"{args.mib} MiB file under {base} ({fs_type(base)}), warm page cache:")
        out = base / "out"
        write_random(out / "big.bin", args.mib)
        stores = iter(range(10**6))
        fresh = lambda: ArtifactStore(base / f"store{next(stores)}")  # noqa: E731

        data = memoryview((out / "big.bin").read_bytes())

        def hash_memory(_: object) -> None:
            h = hashlib.sha256()
            for i in range(0, len(data), MiB):
                h.update(data[i:i + MiB])
        results.append(report("limit: sha256 in memory (1 MiB updates)",
                              timed(args.runs, lambda: None, hash_memory), args.mib, "MiB/s"))
        data.release()

        def hash_file(_: object) -> None:
            with open(out / "big.bin", "rb", buffering=0) as f:
                hash_fd(f, MiB)
        results.append(report("limit: sha256 of the file (1 MiB reads)",
                              timed(args.runs, lambda: None, hash_file), args.mib, "MiB/s"))
        limit = float(results[-1]["median"])

        def ingest(store: object) -> None:
            assert isinstance(store, ArtifactStore)
            store.ingest(out)
        results.append(report(f"{args.mib:,} MiB file, new blob, same filesystem (link)",
                              timed(args.runs, fresh, ingest), args.mib, "MiB/s", limit,
                              target=500.0 if args.mib >= 1024 else None))
        shared = fresh()
        shared.ingest(out)
        results.append(report(f"{args.mib:,} MiB file, blob exists (dedup)",
                              timed(args.runs, lambda: shared, ingest), args.mib, "MiB/s",
                              limit))

        manifest = shared.ingest(out)
        results.append(report("materialize (verified copy out)", timed(
            args.runs, lambda: shutil.rmtree(base / "dest", ignore_errors=True),
            lambda _: shared.materialize(manifest, base / "dest")), args.mib, "MiB/s", limit))
        shutil.rmtree(base / "dest", ignore_errors=True)

        shm = Path("/dev/shm")
        if shm.is_dir() and os.stat(shm).st_dev != os.stat(base).st_dev:
            shm_out = Path(tempfile.mkdtemp(prefix="osmo-bench-", dir=shm))
            try:
                shutil.copyfile(out / "big.bin", shm_out / "big.bin")

                def ingest_shm(store: object) -> None:
                    assert isinstance(store, ArtifactStore)
                    store.ingest(shm_out)
                results.append(report("new blob, across filesystems (copy + fsync)",
                                      timed(args.runs, fresh, ingest_shm), args.mib, "MiB/s",
                                      limit))
            finally:
                shutil.rmtree(shm_out, ignore_errors=True)

        parts = base / "parts"
        parts.mkdir()
        with open(out / "big.bin", "rb") as f:
            for i in range(8):
                (parts / f"part{i}").write_bytes(f.read(args.mib * MiB // 8))

        def ingest_parts(store: object) -> None:
            assert isinstance(store, ArtifactStore)
            store.ingest(parts)
        results.append(report("same bytes as 8 files (parallel hashing)",
                              timed(args.runs, fresh, ingest_parts), args.mib, "MiB/s"))

        small = base / "small"
        for i in range(args.small):
            p = small / f"d{i % 100}" / f"f{i}.bin"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(os.urandom(4096))

        def ingest_small(store: object) -> None:
            assert isinstance(store, ArtifactStore)
            store.ingest(small)
        results.append(report(f"small files: {args.small:,} × 4 KiB, new blobs",
                              timed(args.runs, fresh, ingest_small), args.small, "files/s"))
    write_rows(args.json, results)


if __name__ == "__main__":
    main()
