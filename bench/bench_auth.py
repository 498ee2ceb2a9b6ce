"""What authentication costs one API request: an authenticated ping against the same ping
served without a token check.

Two real servers' API plumbing (``osmo.transport.rpc.ApiServer`` on a zenoh router, on a
Unix socket, a client session connected to it): one authenticates every request with
``osmo.server.auth.Authenticator`` over a real SQLite token store (a sha256 of the token,
then the cache of digest → identity) on a router that also applies the server's zenoh
access control (``SERVER_ONLY``), the other hands every request a fixed identity on a plain
router. The row is the difference of their p50 round trips (target: at most 0.2 ms, issue 13).

Usage: python bench/bench_auth.py [--runs 5] [--requests 2000] [--json out.json]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import machine_info, quick, row, write_rows  # noqa: E402

from osmo.server.auth import Authenticator  # noqa: E402
from osmo.store.sqlite import Store  # noqa: E402
from osmo.transport.auth import Identity, Role, new_token, token_digest  # noqa: E402
from osmo.transport.rpc import ApiClient, ApiServer  # noqa: E402
from osmo.transport.wire import SERVER_ONLY  # noqa: E402
from osmo.transport.zenoh_link import Link  # noqa: E402


def p50_ms(client: ApiClient, requests: int) -> float:
    """The median round trip of ``requests`` pings, in ms."""
    times = []
    for _ in range(requests):
        t0 = time.perf_counter()
        client.call("ping")
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2] * 1000


def check_us(authenticate: Authenticator, token: str, calls: int = 20000) -> float:
    """Microseconds of one (cached) token check, without the network around it."""
    raw = token.encode()
    t0 = time.perf_counter()
    for _ in range(calls):
        authenticate(raw)
    return (time.perf_counter() - t0) / calls * 1e6


def measure(root: Path, runs: int, requests: int) -> tuple[list[float], list[float], float]:
    """p50 per run (authenticated, unauthenticated), and one check's cost in µs."""
    store = Store(root / "state.db")
    token = new_token()
    store.add_token("bench", Role.USER.value, token_digest(token), time.time())
    fixed = Identity("bench", Role.USER)
    check = check_us(Authenticator(store), token)
    out: tuple[list[float], list[float]] = ([], [])
    for index, authenticate in enumerate((Authenticator(store), lambda _token: fixed)):
        sock = f"unixsock-stream/{root}/api{index}.sock"
        # the checked server's router also refuses the server's keys to peers, as a real one
        router = Link.router([sock], "bench", reserved=SERVER_ONLY if index == 0 else None)
        server = ApiServer(router, lambda _verb, _request, who: {"name": who.name},
                           authenticate)
        link = Link.client([sock], "bench")
        client = ApiClient(link, token=token)
        p50_ms(client, 200)  # warm up
        out[index].extend(p50_ms(client, requests) for _ in range(runs))
        link.close()
        server.close()
        router.close()
    store.close()
    return out[0], out[1], check


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
        authed, plain, check = measure(Path(tmp), args.runs, args.requests)
    rows = [row("api request: auth cost", "ms",
                [a - p for a, p in zip(authed, plain, strict=True)], higher_is_better=False,
                target=0.2, notes=f"p50 of {args.requests} pings with a token check minus the "
                                  f"same without: {min(authed):.3f} vs {min(plain):.3f} ms "
                                  f"(best runs); the check alone: {check:.1f} µs")]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
