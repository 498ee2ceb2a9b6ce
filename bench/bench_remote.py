"""Remote workers: dispatch latency, output transfer throughput, fan-out over two workers.

Everything runs as real processes on loopback: a server (``--no-local-pool``) and workers
started with ``osmo worker --connect`` and a worker token of their own (every report is an
authenticated request). Workers get their own ``OSMO_HOST_ID`` so data goes through the
network path (zenoh), not same-host hard links.

- **dispatch round trip:** a chain of ``--chain`` no-op tasks (``true``) on one remote
  worker. For each task, from its placement (INITIALIZING) to COMPLETED, read from the
  server's event log: the server sends the order, the worker prepares the folder, spawns
  ``true``, ingests the (empty) output and reports; the server records it. The same chain
  on the server's own local pool is printed beside it, so the remote part is the difference.
- **output transfer:** one task writes a ``--size-mib`` file on a worker "on another host";
  the server fetches it (chunked, pipelined, verified). The rate is what the server logs
  for the fetch (bytes / seconds).
- **fan-out:** 1 → ``--fanout`` → 1 no-op tasks over two remote workers with 2 cpus each,
  and in the same run (interleaved) the same fan-out on the server's own local pool with the
  same 4 cpu slots; the ratio of the two is issue 16's row (target ≥ 80%).

Usage: python bench/bench_remote.py [--runs 3] [--chain 300] [--fanout 1000]
       [--size-mib 1024] [--json out.json]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shutil
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import machine_info, quick, row, write_rows  # noqa: E402

import osmo  # noqa: E402
from osmo.config import free_port  # noqa: E402


class Cluster:
    """A server and workers in their own processes under one temp folder."""

    def __init__(self, root: Path, *, local_pool: bool = False, cpus: int | None = None) -> None:
        self.root = root
        self.endpoint = f"tcp/127.0.0.1:{free_port(0)}"
        self.env = dict(os.environ, OSMO_HOME=str(root / "server"))
        self.env.pop("OSMO_SERVER", None)
        args = ["server", "start", "--listen", self.endpoint]
        if not local_pool:
            args.append("--no-local-pool")
        if cpus is not None:
            args += ["--cpus", str(cpus)]
        self.osmo(*args)
        self.workers: list[subprocess.Popen[bytes]] = []

    def osmo(self, *args: str) -> str:
        return subprocess.run([sys.executable, "-m", "osmo", *args], env=self.env, check=True,
                              capture_output=True, text=True).stdout

    def worker(self, name: str, cpus: int) -> None:
        token = self.osmo("token", "create", name, "--role", "worker", "--pool",
                           "default").strip()
        env = dict(self.env, OSMO_HOME=str(self.root / name), OSMO_HOST_ID=f"host-{name}",
                   OSMO_TOKEN=token)
        log = open(self.root / f"{name}.log", "wb")
        self.workers.append(subprocess.Popen(
            [sys.executable, "-m", "osmo", "worker", "--connect", self.endpoint, "--name", name,
             "--cpus", str(cpus)], env=env, stdout=log, stderr=log, start_new_session=True))
        log.close()
        deadline = time.monotonic() + 30
        while name not in self.osmo("resource", "list"):
            if time.monotonic() > deadline:
                raise SystemExit(f"worker {name} did not come online")
            time.sleep(0.1)

    def client(self) -> osmo.Client:
        return osmo.Client(self.endpoint, home=self.root / "server")  # its admin token

    def close(self) -> None:
        for proc in self.workers:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
        self.osmo("server", "stop")


def chain(n: int) -> osmo.Workflow:
    wf = osmo.Workflow("bench-remote-chain")
    wf.task("t0", ["true"])
    for i in range(1, n):
        wf.task(f"t{i}", ["true"], inputs=[f"t{i - 1}"])
    return wf


def fan_out(n: int) -> osmo.Workflow:
    wf = osmo.Workflow("bench-remote-fanout")
    wf.task("source", ["true"])
    middle = [f"m{i}" for i in range(n)]
    for name in middle:
        wf.task(name, ["true"], inputs=["source"])
    wf.task("join", ["true"], inputs=middle)
    return wf


def round_trips(home: Path, wf_id: str) -> list[float]:
    """Per task: seconds from INITIALIZING to COMPLETED, from the server's event log."""
    db = sqlite3.connect(f"file:{home / 'state.db'}?mode=ro", uri=True)
    rows = db.execute("SELECT task, status, at FROM events WHERE workflow_id = ? ORDER BY seq",
                      (wf_id,))
    placed: dict[str, float] = {}
    out = []
    for task, status, at in rows:
        if status == "INITIALIZING":
            placed[task] = at
        elif status == "COMPLETED" and task in placed:
            out.append(at - placed.pop(task))
    return out


@contextlib.contextmanager
def cluster(workers: int, *, local_pool: bool = False,
            cpus: int | None = None) -> Iterator[Cluster]:
    """A fresh server with ``workers`` remote workers of 2 cpus each, torn down after.

    ``cpus``: the local pool's cpu slots (default: the cores).
    """
    with tempfile.TemporaryDirectory(prefix="osmo-bench-remote-") as root:
        c = Cluster(Path(root), local_pool=local_pool, cpus=cpus)
        try:
            for i in range(workers):
                c.worker(f"w{i + 1}", 2)
            yield c
        finally:
            c.close()


def dispatch(runs: int, n: int) -> tuple[list[list[float]], list[list[float]]]:
    """Per run: every task's placed → completed seconds, on a remote worker and locally.

    Each run measures both, one after the other (interleaved), so both see the same load.
    """
    remote: list[list[float]] = []
    local: list[list[float]] = []
    for _ in range(runs):
        for on_pool, out in ((False, remote), (True, local)):
            with cluster(0 if on_pool else 1, local_pool=on_pool) as c, c.client() as client:
                info = client.wait(client.submit(chain(n), no_cache=True))
                check_ok(client, info, c)
                out.append(round_trips(c.root / "server", info.id))
    return remote, local


def transfer(runs: int, size_mib: int) -> list[float]:
    rates = []
    for _ in range(runs):
        with cluster(1) as c, c.client() as client:
            wf = osmo.Workflow("bench-remote-transfer")
            write = f"head -c {size_mib}M /dev/urandom > " + "{{output}}/big.bin"
            wf.task("big", ["sh", "-c", write])
            check_ok(client, client.wait(client.submit(wf, no_cache=True)), c)
            log = (c.root / "server" / "server.log").read_text()
            found = re.findall(r"fetched from worker \S+ in [\d.]+s \((\d+) MiB/s\)", log)
            rates.append(float(found[-1]))
    return rates


def check_ok(client: osmo.Client, info: osmo.WorkflowInfo, c: Cluster) -> None:
    """Fail the run, saying which tasks did not complete and why, and keeping the cluster's
    folders (a copy under the system's temp folder) to look at."""
    if info.ok:
        return
    tasks = client.get(info.id).tasks
    bad = [t for t in tasks if t.status.name != "COMPLETED"]
    kept = Path(tempfile.mkdtemp(prefix="osmo-bench-remote-failed-"))
    try:
        shutil.copytree(c.root, kept / "cluster", symlinks=True, dirs_exist_ok=True)
    except (OSError, shutil.Error):
        pass  # sockets and files that went away: what could be copied is kept
    raise SystemExit(f"workflow {info.id} ended {info.status.name}: {len(bad)} of "
                     f"{len(tasks)} tasks not COMPLETED, e.g. {bad[:3]}; folders kept in {kept}")


def fanout(runs: int, n: int) -> tuple[list[float], list[float]]:
    """Tasks/s of the fan-out per run: over 2 remote workers, and on the local pool.

    Each run measures both, one after the other, so both see the same load; the local pool
    gets the 4 cpu slots the two workers offer together.
    """
    remote, local = [], []
    for _ in range(runs):
        for workers, out in ((2, remote), (0, local)):
            with cluster(workers, local_pool=not workers,
                         cpus=None if workers else 4) as c, c.client() as client:
                t0 = time.perf_counter()
                check_ok(client, client.wait(client.submit(fan_out(n), no_cache=True)), c)
                out.append((n + 2) / (time.perf_counter() - t0))
    return remote, local


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--chain", type=int, default=300)
    ap.add_argument("--fanout", type=int, default=1000)
    ap.add_argument("--size-mib", type=int, default=1024)
    ap.add_argument("--json", help="write result rows here")
    args = ap.parse_args()
    if quick():
        args.runs, args.chain, args.fanout, args.size_mib = 1, 10, 20, 8
    print(f"machine: {machine_info()}")
    rows = []
    remote, local = dispatch(args.runs, args.chain)
    for q in (0.5, 0.99):
        name = f"p{int(q * 100)}"
        rem = [pct([s * 1000 for s in run], q) for run in remote]
        loc = statistics.median(pct([s * 1000 for s in run], q) for run in local)
        rows.append(row(f"remote: no-op task round trip {name} (placed → completed)", "ms",
                        rem, higher_is_better=False, target=2.0 if q == 0.5 else 10.0,
                        notes=f"{args.chain} tasks of a chain on one remote worker; the same "
                              f"chain on the server's local pool: {name} {loc:.2f} ms"))
    for q, target in ((0.5, 1.0), (0.99, 10.0)):  # issue 30's targets for the hop alone
        name = f"p{int(q * 100)}"
        added = [pct([s * 1000 for s in r], q) - pct([s * 1000 for s in lo], q)
                 for r, lo in zip(remote, local, strict=True)]
        rows.append(row(f"remote: what the remote hop adds to a task's round trip, {name}", "ms",
                        added, higher_is_better=False, target=target,
                        notes=f"per run: remote chain {name} − local-pool chain {name} "
                              "(same shape)"))
    rows.append(row(f"remote: output transfer ({args.size_mib} MiB, worker → server)", "MiB/s",
                    transfer(args.runs, args.size_mib), higher_is_better=True, target=300.0,
                    limit_of="limit: zenoh put throughput"))
    over_two, on_pool = fanout(args.runs, args.fanout)
    rows.append(row(f"remote: fan-out/join {args.fanout} `true` tasks over 2 workers",
                    "tasks/s", over_two, higher_is_better=True,
                    notes="2 remote workers × 2 cpus"))
    rows.append(row(f"remote: fan-out/join {args.fanout} `true` tasks on the local pool",
                    "tasks/s", on_pool, higher_is_better=True,
                    notes="the server's own pool with --cpus 4, same runs (interleaved)"))
    rows.append(row("remote: fan-out over 2 workers ÷ the same on the local pool", "%",
                    [100 * r / lo for r, lo in zip(over_two, on_pool, strict=True)],
                    higher_is_better=True, target=80.0, notes="per run, then the median"))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
