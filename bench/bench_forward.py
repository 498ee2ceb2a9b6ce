"""Port-forward: throughput and latency through ``osmo workflow port-forward`` vs raw TCP.

A server and one remote worker run as real processes on loopback (``bench_remote.Cluster``;
the worker on "another host", so nothing is short-cut). A task on the worker runs a small
TCP server; ``osmo workflow port-forward`` (the real CLI) forwards a local port to it, so
every byte goes client → CLI → zenoh router (in the server) → worker → task and back.

- **one stream:** the task sends ``--size-mib`` (1 GiB) on one connection; MiB/s received.
- **20 streams:** 20 concurrent connections share the same total; aggregate MiB/s.
- **1-byte round trip:** ping-pong of one byte, ``--pings`` times; p50 in ms.

The limit of each is the same task script run as a plain process and reached over raw
loopback TCP (no osmo). The target (issue 17) is ≥ 50% of the raw throughput.

Two bounds say what any relayed design can reach on this machine:

- **3 bare relays:** the raw task reached through three relay processes that only copy
  bytes (``recv_into`` a 1 MiB buffer, ``sendall``; no framing, no authentication, no
  zenoh), the hop count of port-forward's path (CLI, router, worker);
- **AES-256-GCM of the stream on one core:** what sealing every frame costs one side (the
  trust model: any zenoh peer may publish or listen, so a frame is encrypted and must prove
  its sender).

The target (issue 26) is ≥ 50% of the 3-relay bound, for 1 and for 20 streams, with every
frame encrypted; it replaced "≥ 50% of raw TCP", which three relays cannot reach on 2 cores.

Usage: python bench/bench_forward.py [--runs 3] [--size-mib 1024] [--streams 20]
       [--pings 2000] [--json out.json]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import socket
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_remote import cluster  # noqa: E402
from benchlib import machine_info, quick, row, write_rows  # noqa: E402

from osmo.config import free_port  # noqa: E402

# The task: 'S' + u64 n → sends n bytes and closes; 'E' → echoes until closed.
SERVER = """
import socket, struct, sys, threading
def serve(conn):
    with conn:
        kind = conn.recv(1)
        if kind == b"S":
            n = struct.unpack(">Q", conn.recv(8, socket.MSG_WAITALL))[0]
            block = memoryview(bytes(1 << 20))
            while n > 0:
                conn.sendall(block[:min(n, len(block))]); n -= len(block)
        elif kind == b"E":
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while data := conn.recv(65536):
                conn.sendall(data)
srv = socket.create_server(("127.0.0.1", int(sys.argv[1])), backlog=128)
while True:
    threading.Thread(target=serve, args=(srv.accept()[0],), daemon=True).start()
"""
# A relay: each accepted connection is copied both ways to argv[1]'s port.
RELAY = """
import socket, sys, threading
def pump(src, dst):
    buf = bytearray(1 << 20); view = memoryview(buf)
    try:
        while k := src.recv_into(buf):
            dst.sendall(view[:k])
    except OSError:
        pass
    for s in (src, dst):
        try: s.shutdown(socket.SHUT_RDWR)
        except OSError: pass
def serve(conn):
    up = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
    for s in (conn, up): s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    threading.Thread(target=pump, args=(up, conn), daemon=True).start()
    pump(conn, up)
srv = socket.create_server(("127.0.0.1", int(sys.argv[2])), backlog=128)
while True:
    threading.Thread(target=serve, args=(srv.accept()[0],), daemon=True).start()
"""
MIB = 1 << 20


def fetch(port: int, n: int) -> float:
    """Seconds to receive ``n`` bytes from the task on ``port``."""
    with socket.create_connection(("127.0.0.1", port), timeout=120) as sock:
        t0 = time.perf_counter()
        sock.sendall(b"S" + struct.pack(">Q", n))
        got = 0
        buf = bytearray(1 << 20)
        while got < n:
            k = sock.recv_into(buf)
            if not k:
                raise SystemExit(f"stream ended after {got} of {n} bytes")
            got += k
        return time.perf_counter() - t0


def throughput(port: int, total: int, streams: int) -> float:
    """Aggregate MiB/s of ``streams`` concurrent fetches of ``total`` bytes in all."""
    each = total // streams
    t0 = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(streams) as pool:
        list(pool.map(lambda _: fetch(port, each), range(streams)))
    return each * streams / MIB / (time.perf_counter() - t0)


def pings(port: int, n: int) -> list[float]:
    """Milliseconds of each 1-byte round trip."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.sendall(b"E")
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            sock.sendall(b"x")
            if sock.recv(1) != b"x":
                raise SystemExit("echo broke")
            out.append((time.perf_counter() - t0) * 1000)
        return out


def wait_port(port: int, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            pings(port, 1)
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def measure(port: int, args: argparse.Namespace) -> dict[str, list[float]]:
    """Every figure on ``port``, ``args.runs`` times."""
    wait_port(port)
    out: dict[str, list[float]] = {"one": [], "many": [], "rtt": []}
    for _ in range(args.runs):
        out["one"].append(throughput(port, args.size_mib * MIB, 1))
        out["many"].append(throughput(port, args.size_mib * MIB, args.streams))
        out["rtt"].append(statistics.median(pings(port, args.pings)))
    return out


def relayed(args: argparse.Namespace, hops: int) -> dict[str, list[float]]:
    """The task as a plain process, reached through ``hops`` bare copy relays (0: raw TCP;
    no osmo, no authentication)."""
    port = free_port(0)
    procs = [subprocess.Popen([sys.executable, "-c", SERVER, str(port)])]
    try:
        for _ in range(hops):
            upstream, port = port, free_port(0)
            procs.append(subprocess.Popen([sys.executable, "-c", RELAY, str(upstream),
                                           str(port)]))
        return measure(port, args)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def aead_mib_s(size_mib: int, runs: int) -> list[float]:
    """MiB/s of sealing 128 KiB frames with AES-256-GCM on one core (what a sender pays)."""
    from osmo.transport.seal import Aead
    from osmo.transport.streams import CHUNK

    aead, frame, out = Aead(bytes(32)), bytes(CHUNK), []
    frames = size_mib * MIB // CHUNK
    for _ in range(runs):
        t0 = time.perf_counter()
        for i in range(frames):
            aead.seal(i.to_bytes(12, "big"), frame, b"header")
        out.append(size_mib / (time.perf_counter() - t0))
    return out


def forwarded(args: argparse.Namespace) -> dict[str, list[float]]:
    import osmo

    task_port, local = free_port(0), free_port(0)
    with cluster(1) as c, c.client() as client:
        wf = osmo.Workflow("bench-forward")
        wf.task("t", [sys.executable, "-c", SERVER, str(task_port)])
        wf_id = client.submit(wf, no_cache=True)
        deadline = time.monotonic() + 60
        while client.get(wf_id).tasks[0].status.name != "RUNNING":
            if time.monotonic() > deadline:
                raise SystemExit("the task never ran")
            time.sleep(0.1)
        proc = subprocess.Popen([sys.executable, "-m", "osmo", "--server", c.endpoint,
                                 "workflow", "port-forward", wf_id, "t", "--port",
                                 f"{local}:{task_port}"], env=c.env, stdout=subprocess.PIPE,
                                text=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().startswith("Forwarding")
            return measure(local, args)
        finally:
            proc.kill()
            proc.wait()
            client.cancel(wf_id)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--size-mib", type=int, default=1024)
    p.add_argument("--streams", type=int, default=20)
    p.add_argument("--pings", type=int, default=2000)
    p.add_argument("--json")
    args = p.parse_args()
    if quick():
        args.runs, args.size_mib, args.pings = 1, 8, 50
    print(machine_info(), flush=True)
    limit, bare, fwd = relayed(args, 0), relayed(args, 3), forwarded(args)
    one, many = f"{args.size_mib} MiB, 1 stream", f"{args.size_mib} MiB, {args.streams} streams"
    rows = [
        row(f"limit: raw loopback TCP, {one}", "MiB/s", limit["one"], higher_is_better=True),
        row(f"limit: raw loopback TCP, {many}", "MiB/s", limit["many"], higher_is_better=True),
        row("limit: raw loopback TCP, 1-byte round trip p50", "ms", limit["rtt"],
            higher_is_better=False),
        row(f"bound: 3 bare copy relays (no framing, no authentication), {one}", "MiB/s",
            bare["one"], higher_is_better=True, limit_of=f"limit: raw loopback TCP, {one}"),
        row(f"bound: 3 bare copy relays (no framing, no authentication), {many}", "MiB/s",
            bare["many"], higher_is_better=True, limit_of=f"limit: raw loopback TCP, {many}"),
        row("bound: AES-256-GCM sealing of 128 KiB frames, one core", "MiB/s",
            aead_mib_s(args.size_mib, args.runs), higher_is_better=True),
        row(f"port-forward (remote worker), {one}", "MiB/s", fwd["one"], higher_is_better=True,
            limit_of=f"bound: 3 bare copy relays (no framing, no authentication), {one}",
            target=0.5 * statistics.median(bare["one"])),
        row(f"port-forward (remote worker), {many}", "MiB/s", fwd["many"],
            higher_is_better=True,
            limit_of=f"bound: 3 bare copy relays (no framing, no authentication), {many}",
            target=0.5 * statistics.median(bare["many"])),
        row("port-forward (remote worker), 1-byte round trip p50", "ms", fwd["rtt"],
            higher_is_better=False, limit_of="limit: raw loopback TCP, 1-byte round trip p50"),
    ]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
