"""The machine's own limits, with no orchestrator: what osmo's figures are compared with.

Rows, each the median of N runs (min/max):

- **spawn `true`, 2 parallel** — ``subprocess.run(["true"])`` N times from a pool of 2
  threads (osmo's local pool runs 2 one-cpu tasks at once on 2 cores). No scheduler, no
  state, no folders: the floor for any orchestrator whose tasks are processes.
- **zenoh get round trip p50/p99** — a client session ``get``s a key that a queryable in
  another process (a zenoh router, like osmo's server) answers with a small payload,
  over loopback TCP. eclipse-zenoh is used directly here; this is the floor for any osmo
  request (CLI/SDK call, remote dispatch).
- **zenoh put throughput** — 128 KiB puts with ``CongestionControl.BLOCK`` from a client to a
  subscriber in the router process, until it has counted every byte.
- **sha256 of a file** — hashlib over a file in the page cache, 1 MiB reads: the floor for
  artifact ingest (every byte is hashed once).

Usage: python bench/bench_limits.py [--runs 3] [--spawns 1000] [--gets 2000] [--put-mib 256]
       [--hash-mib 512] [--json out.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchlib import quick, row, timed, write_rows  # noqa: E402

MiB = 1 << 20
CHUNK = 128 * 1024


def spawn(n: int, parallel: int = 2) -> None:
    """Spawn ``true`` n times, ``parallel`` at once, and wait for all of them."""
    with ThreadPoolExecutor(parallel) as pool:
        list(pool.map(lambda _i: subprocess.run(["true"], check=True), range(n)))


def _config(mode: str, endpoint: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints" if mode == "router" else "connect/endpoints",
                      json.dumps([endpoint]))
    return conf


def serve(endpoint: str) -> None:
    """The other process: a router with an echo queryable and a byte-counting subscriber."""
    session = zenoh.open(_config("router", endpoint))
    received = [0]
    cond = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        with cond:
            received[0] += len(sample.payload)
            cond.notify_all()

    def on_echo(query: zenoh.Query) -> None:
        query.reply(query.key_expr, b'{"ok": {"pong": true}}')

    def on_count(query: zenoh.Query) -> None:
        want = int(query.payload.to_bytes()) if query.payload else 0
        with cond:
            cond.wait_for(lambda: received[0] >= want, timeout=60)
            got, received[0] = received[0], 0
        query.reply(query.key_expr, str(got).encode())

    keep = [session.declare_queryable("bench/echo", on_echo),
            session.declare_queryable("bench/count", on_count),
            session.declare_subscriber("bench/data", on_sample)]
    print("ready", flush=True)
    sys.stdin.read()  # run until the parent closes our stdin
    del keep
    session.close()


def free_port() -> int:
    """A free TCP port on loopback."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def get_once(session: zenoh.Session, key: str, payload: bytes | None = None) -> bytes:
    """One request/reply; returns the reply's payload."""
    for reply in session.get(key, payload=payload, timeout=60):
        if reply.ok is not None:
            return bytes(reply.ok.payload.to_bytes())
    raise RuntimeError(f"no reply on {key}")


def zenoh_rows(runs: int, gets: int, put_mib: int) -> list[dict[str, object]]:
    """Round trip p50/p99 and put throughput against a router in another process."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, __file__, "--serve", endpoint],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        session = zenoh.open(_config("client", endpoint))
        try:
            for _ in range(50):  # warm up the link and both ends
                get_once(session, "bench/echo", b'{"verb": "ping"}')
            p50s, p99s, rates = [], [], []
            publisher = session.declare_publisher(
                "bench/data", congestion_control=zenoh.CongestionControl.BLOCK)
            block = os.urandom(CHUNK)
            for _ in range(runs):
                rtts = []
                for _ in range(gets):
                    t0 = time.perf_counter()
                    get_once(session, "bench/echo", b'{"verb": "ping"}')
                    rtts.append((time.perf_counter() - t0) * 1000)
                rtts.sort()
                p50s.append(statistics.median(rtts))
                p99s.append(rtts[min(len(rtts) - 1, int(len(rtts) * 0.99))])
                total = put_mib * MiB
                t0 = time.perf_counter()
                for _ in range(total // CHUNK):
                    publisher.put(block)
                got = int(get_once(session, "bench/count", str(total).encode()))
                rates.append(got / MiB / (time.perf_counter() - t0))
            publisher.undeclare()
        finally:
            session.close()
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(timeout=30)
    note = "client session → router in another process, loopback TCP"
    return [
        row("limit: zenoh get round trip p50", "ms", p50s, higher_is_better=False,
            notes=f"{gets} gets per run; {note}"),
        row("limit: zenoh get round trip p99", "ms", p99s, higher_is_better=False, notes=note),
        row("limit: zenoh put throughput", "MiB/s", rates, higher_is_better=True,
            notes=f"{put_mib} MiB as {CHUNK // 1024} KiB puts, CongestionControl.BLOCK, "
                  f"every byte counted by the subscriber; {note}; the first batch on a fresh "
                  "link is much slower (0.9–1.3 GiB/s for 64 MiB)"),
    ]


def sha256_rows(runs: int, mib: int) -> list[dict[str, object]]:
    """sha256 of a file in the page cache, 1 MiB reads."""
    with tempfile.TemporaryDirectory(prefix="osmo-bench-limits-") as tmp:
        path = Path(tmp) / "data.bin"
        with open(path, "wb") as f:
            for _ in range(mib):
                f.write(os.urandom(MiB))
        buf = bytearray(MiB)

        def hash_file() -> None:
            h = hashlib.sha256()
            view = memoryview(buf)
            with open(path, "rb", buffering=0) as f:
                while n := f.readinto(buf):
                    h.update(view[:n])
        hash_file()  # warm the page cache
        times = timed(hash_file, runs)
    return [row("limit: sha256 of a file (page cache, 1 MiB reads)", "MiB/s",
                [mib / t for t in times], higher_is_better=True, notes=f"{mib} MiB file")]


def main() -> None:
    """Measure every limit and write the rows."""
    if len(sys.argv) == 3 and sys.argv[1] == "--serve":
        serve(sys.argv[2])
        return
    small = quick()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1 if small else 3)
    ap.add_argument("--spawns", type=int, default=50 if small else 1000)
    ap.add_argument("--gets", type=int, default=100 if small else 2000)
    ap.add_argument("--put-mib", type=int, default=8 if small else 256)
    ap.add_argument("--hash-mib", type=int, default=8 if small else 512)
    ap.add_argument("--json")
    args = ap.parse_args()
    spawns = timed(lambda: spawn(args.spawns), args.runs)
    rows = [row("limit: spawn `true`, 2 parallel, no orchestrator", "tasks/s",
                [args.spawns / t for t in spawns], higher_is_better=True,
                notes=f"{args.spawns} spawns per run, subprocess.run from 2 threads")]
    rows += zenoh_rows(args.runs, args.gets, args.put_mib)
    rows += sha256_rows(args.runs, args.hash_mib)
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
