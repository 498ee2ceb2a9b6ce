"""What end-to-end sealing costs an order and a report (issue 26: p50 at most 0.1 ms each).

Everything osmo sends is sealed (``osmo.transport.seal``): a worker's report is an API request
sealed on its channel and answered sealed; an order is a put sealed for its worker. Rows:

- **report:** the p50 round trip of a sealed API request (``ApiClient.call`` against a real
  ``ApiServer`` with the server's ``Authenticator`` over a real SQLite token store, on a
  router with the server's allow-list; reports are answered on zenoh's thread, as the
  server does) minus the same request and reply sent in clear to a bare queryable that
  answers the same JSON (no sealing, no token check): what sealing and authentication add
  to each report.
- **order:** the p50 time from a put to its delivery in a subscriber, sealed (seal, put,
  open with the replay window, parse) minus the same JSON put in clear.
- **seal + open, CPU:** one order's seal and open alone, without the network (µs).

Usage: python bench/bench_auth.py [--runs 5] [--requests 2000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import machine_info, quick, row, write_rows  # noqa: E402

from osmo.server.auth import Authenticator  # noqa: E402
from osmo.store.sqlite import Store  # noqa: E402
from osmo.transport.auth import Role, new_token, token_digest  # noqa: E402
from osmo.transport.rpc import ApiClient, ApiServer  # noqa: E402
from osmo.transport.seal import Purpose, Signer, seal_json  # noqa: E402
from osmo.transport.wire import PEER_ALLOW, PEER_DENY  # noqa: E402
from osmo.transport.zenoh_link import Link  # noqa: E402

REPORT = {"id": "w1", "report": {"op": "started", "attempt_id": "fan-1:t-123:0"}}
ORDER = {"op": "prepare", "attempt_id": "fan-1:t-123:0", "manifests": {}, "secrets": False,
         "cmd": {"attempt_id": "fan-1:t-123:0", "workflow_id": "fan-1", "task": "t-123",
                 "retry": 0, "node_id": "w1", "inputs": {}, "hosts": {}, "run": False}}


def _p50(samples: list[float]) -> float:
    samples.sort()
    return samples[len(samples) // 2] * 1000


def _alternated(sealed: Callable[[], float], clear: Callable[[], float], runs: int,
                count: int) -> tuple[list[float], list[float]]:
    """p50 (ms) per run of each, called alternately (a busy moment costs both the same)."""
    for _ in range(200):  # warm up
        sealed(), clear()
    out: tuple[list[float], list[float]] = ([], [])
    for _ in range(runs):
        a, b = [], []
        for _ in range(count):
            a.append(sealed())
            b.append(clear())
        out[0].append(_p50(a))
        out[1].append(_p50(b))
    return out


def reports(root: Path, runs: int, requests: int) -> tuple[list[float], list[float]]:
    """p50 (ms) per run of a sealed report round trip, and of the same in clear."""
    store = Store(root / "state.db")
    token = new_token()
    store.add_token("w", Role.WORKER.value, token_digest(token), time.time())
    sock = f"unixsock-stream/{root}/api.sock"
    router = Link.router([sock], "bench", allow=PEER_ALLOW, deny=PEER_DENY)
    server = ApiServer(router, lambda _verb, _request, _who: {},
                       Authenticator(store, Signer()), inline=frozenset({"worker_report"}))
    bare = router.serve(router.key("plain", "*"),
                        lambda r: r.reply(json.dumps({"ok": json.loads(r.payload)}).encode()))
    link = Link.client([sock], "bench")
    client = ApiClient(link, token=token)
    payload = json.dumps(REPORT).encode()

    def sealed() -> float:
        t0 = time.perf_counter()
        client.call("worker_report", REPORT)
        return time.perf_counter() - t0

    def clear() -> float:
        t0 = time.perf_counter()
        for data, _att in Link.replies(link.ask(link.key("plain", "report"), payload)):
            json.loads(data)
            break
        return time.perf_counter() - t0

    out = _alternated(sealed, clear, runs, requests)
    link.close()
    bare.close()
    server.close()
    router.close()
    store.close()
    return out


def orders(root: Path, runs: int, count: int) -> tuple[list[float], list[float], float]:
    """p50 (ms) per run of a sealed order's delivery, of the same in clear, and µs of CPU."""
    from osmo.transport.seal import ChannelTable, finish, hello

    token = new_token()
    digest = token_digest(token)
    table = ChannelTable(lambda _tid: digest, Signer())
    shake = hello(token)
    done = finish(shake, table.accept(shake.request()))
    assert done is not None
    worker = done[0]
    found = table.get(worker.id)
    assert found is not None
    server = found[0]
    sock = f"unixsock-stream/{root}/orders.sock"
    router = Link.router([sock], "bench")
    link = Link.client([sock], "bench")
    got = threading.Semaphore(0)
    rel = "to-worker/w1"

    def on_sealed(_key: str, data: bytes, att: bytes | None) -> None:
        opened = worker.open(Purpose.PUSH, rel, att, data)
        assert opened is not None
        json.loads(opened[1])
        got.release()

    def on_clear(_key: str, data: bytes, _att: bytes | None) -> None:
        json.loads(data)
        got.release()

    link.subscribe_raw(link.key(rel), on_sealed)
    link.subscribe_raw(link.key("plain", "w1"), on_clear)
    time.sleep(0.3)

    def sealed() -> float:
        t0 = time.perf_counter()
        att, payload = seal_json(server, Purpose.PUSH, rel, ORDER)
        router.put(router.key(rel), payload, att)
        got.acquire()
        return time.perf_counter() - t0

    def clear() -> float:
        t0 = time.perf_counter()
        router.put(router.key("plain", "w1"), json.dumps(ORDER).encode())
        got.acquire()
        return time.perf_counter() - t0

    out = _alternated(sealed, clear, runs, count)
    link.close()
    router.close()
    n = 20000
    t0 = time.perf_counter()
    for _ in range(n):
        att, payload = seal_json(server, Purpose.PUSH, rel, ORDER)
        worker.open(Purpose.PUSH, rel, att, payload)
    cpu = (time.perf_counter() - t0) / n * 1e6
    return out[0], out[1], cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--json", help="write result rows here")
    args = ap.parse_args()
    if quick():
        args.runs, args.requests = 1, 50
    print(f"machine: {machine_info()}")
    with tempfile.TemporaryDirectory(prefix="osmo-bench-auth-") as tmp:
        sealed_r, clear_r = reports(Path(tmp), args.runs, args.requests)
        sealed_o, clear_o, cpu = orders(Path(tmp), args.runs, args.requests)
    rows = [
        row("report: what sealing adds to its round trip, p50", "ms",
            [a - b for a, b in zip(sealed_r, clear_r, strict=True)], higher_is_better=False,
            target=0.1, notes=f"sealed {min(sealed_r):.3f} vs clear {min(clear_r):.3f} ms "
                              "(best runs), token check included"),
        row("order: what sealing adds to its delivery, p50", "ms",
            [a - b for a, b in zip(sealed_o, clear_o, strict=True)], higher_is_better=False,
            target=0.1, notes=f"sealed {min(sealed_o):.3f} vs clear {min(clear_o):.3f} ms "
                              f"(best runs); seal + open alone: {cpu:.1f} µs CPU"),
    ]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
