"""Prefect 3 running osmo's benchmark shapes; run by the peer virtualenv's python.

Local mode: no ``PREFECT_API_URL``, so Prefect starts its own temporary (ephemeral) API
server in a subprocess with a SQLite database under ``PREFECT_HOME`` (the harness gives a
private one), and stops it when this process exits. Tasks run on Prefect's
``ThreadPoolTaskRunner(max_workers=2)``, matching osmo's 2 cpu slots. Everything else is
Prefect's default (result persistence off, run logging on, each task run tracked through the
API).

Shapes (dependencies with ``wait_for``, like osmo's ``inputs``): a chain of N tasks, and a
fan-out/join (1 source → N-2 → 1 join). Task bodies: ``shell`` runs ``subprocess.run(["true"])``
(osmo's tasks are processes, so this is the like-for-like body); ``noop`` returns at once.

Before measuring, a warm-up flow of 2 tasks starts the API server and loads everything; its
time from process start is reported as ``startup_s``. Each measured flow is timed from the
flow call to its return.

Usage: python prefect_dag.py --tasks 1000 --shapes chain,fanout --bodies shell,noop --json OUT
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time

T_START = time.perf_counter()

from prefect import __version__, flow, task  # noqa: E402
from prefect.task_runners import ThreadPoolTaskRunner  # noqa: E402


@task
def shell() -> None:
    """Spawn `true` and wait for it."""
    subprocess.run(["true"], check=True)


@task
def noop() -> None:
    """Do nothing."""


BODIES = {"shell": shell, "noop": noop}


@flow(task_runner=ThreadPoolTaskRunner(max_workers=2))
def chain(n: int, body: str) -> None:
    """n tasks, each waiting for the previous one."""
    t = BODIES[body]
    prev = t.submit()
    for _ in range(n - 1):
        prev = t.submit(wait_for=[prev])
    prev.result()


@flow(task_runner=ThreadPoolTaskRunner(max_workers=2))
def fanout(n: int, body: str) -> None:
    """1 source, n-2 tasks waiting for it, 1 join waiting for them all."""
    t = BODIES[body]
    src = t.submit()
    middle = [t.submit(wait_for=[src]) for _ in range(n - 2)]
    t.submit(wait_for=middle).result()


def main() -> None:
    """Warm up, then time every shape × body once; write JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--tasks", type=int, default=1000)
    ap.add_argument("--shapes", default="chain,fanout")
    ap.add_argument("--bodies", default="shell,noop")
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    chain(2, "noop")
    out: dict[str, object] = {"peer": "prefect", "version": __version__,
                              "startup_s": time.perf_counter() - T_START, "results": []}
    flows = {"chain": chain, "fanout": fanout}
    for body in args.bodies.split(","):  # the `true` body first: it is the one compared
        for shape in args.shapes.split(","):
            t0 = time.perf_counter()
            flows[shape](args.tasks, body)
            out["results"].append({"shape": shape, "body": body, "tasks": args.tasks,  # type: ignore[attr-defined]
                                   "seconds": time.perf_counter() - t0})
    with open(args.json, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
