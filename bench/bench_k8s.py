"""The Kubernetes runtime's cost: tasks as pods through the API stand-in, against podman alone.

Runs a server and one ``osmo worker --runtime kubernetes`` whose pods go through the official
client to the API stand-in of ``tests/k8s`` and run under ``podman kube play`` (host network,
the offline busybox image). Rows:

- **limit: podman kube play of the same pod, N** — N pods running ``true``, played with bare
  ``podman kube play`` at once and waited for (``tests/k8s/measure.py``'s ``bare_play``): what
  the machine needs with no orchestrator and no API.
- **k8s: N tasks, submit → COMPLETED** — SDK submit of a workflow of N independent tasks
  of that image running ``true``, each a pod, until COMPLETED; target: 1.2 × the limit (the
  issue's "at most 20% over").
- **the same 1 task as a process** — on the same worker, no image: osmo's own cost.
- **k8s: API writes per attempt** — writes the stand-in counted (create, delete, ...)
  divided by the attempts; target 3 (pod, Secret, delete).

N is 1 and 100 (1 and 5 with ``OSMO_BENCH_QUICK=1``). The limit's runs and the measured ones
alternate, so that what other work loads the machine meanwhile falls on both alike; before
each, the previous run's pods are gone (the stand-in's garbage swept, bare pods removed).
Needs root, podman and its offline test images (built on first use): otherwise the script
writes no rows.

Usage: python bench/bench_k8s.py [--runs 3] [--tasks 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import Row, quick, row, write_rows  # noqa: E402


def submit(client: object, n: int, image: str | None = "alpine:3.18") -> float:
    """Seconds from submitting ``n`` independent ``true`` tasks to COMPLETED."""
    import osmo

    assert isinstance(client, osmo.Client)
    wf = osmo.Workflow(f"bench-k8s-{n}")
    for i in range(n):
        wf.task(f"t{i}", ["true"], image=image)
    start = time.monotonic()
    info = client.wait(client.submit(wf, no_cache=True), min_interval=0.01)
    if not info.ok:
        raise SystemExit(f"bench workflow ended {info.status.name}")
    return time.monotonic() - start


def settle(cluster: object) -> None:
    """Wait until the last run's pods left the API and podman (so the next run is alone)."""
    from tests.k8s import store as st
    from tests.k8s.nodes import KubeCluster

    assert isinstance(cluster, KubeCluster)
    deadline = time.monotonic() + 120
    while cluster.server.store.list(st.PODS)[0] and time.monotonic() < deadline:
        time.sleep(0.1)
    cluster.kubelet.sweep()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if quick() else 3)
    parser.add_argument("--tasks", type=int, default=5 if quick() else 100)
    parser.add_argument("--json")
    args = parser.parse_args()
    if shutil.which("podman") is None or os.geteuid() != 0:
        print("bench_k8s: needs root and podman; no rows")
        write_rows(args.json, [])
        return 0
    from tests.containers.images import ensure_images, write_containers_conf
    from tests.k8s.measure import bare_play
    from tests.k8s.nodes import KubeCluster

    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="osmo-bench-k8s-") as tmp:
        folder = Path(tmp)
        env = dict(os.environ, CONTAINERS_CONF=str(write_containers_conf(folder)))
        os.environ["CONTAINERS_CONF"] = env["CONTAINERS_CONF"]
        ensure_images(env)
        cluster = KubeCluster(folder / "cluster", env)
        import osmo

        client = osmo.Client(home=cluster.osmo.home)
        try:
            cluster.kubelet.add_node("node-big", cpu="256", memory="256Gi")
            cluster.start_worker("kube-bench", "--cpus", "256", groupNetwork="host")
            submit(client, 1)  # warm-up
            rows.append(row("k8s: the same 1 task as a process (no image), submit → "
                            "COMPLETED", "s", [submit(client, 1, None)
                                               for _ in range(args.runs)],
                            higher_is_better=False, notes="osmo's own cost on this worker"))
            for n in (1, args.tasks):
                before = sum(cluster.server.writes.values())
                bare, took = [], []
                for _ in range(args.runs):  # in turn: other load falls on both alike
                    bare.append(bare_play(n, env, folder))
                    took.append(submit(client, n))
                    settle(cluster)
                limit = row(f"limit: podman kube play of the same pod, {n}", "s", bare,
                            higher_is_better=False)
                rows.append(limit)
                rows.append(row(f"k8s: {n} tasks as pods, submit → COMPLETED", "s", took,
                                higher_is_better=False, limit_of=limit["name"],
                                target=1.2 * statistics.median(bare)))
                writes = (sum(cluster.server.writes.values()) - before) / (n * args.runs)
                rows.append(row(f"k8s: API writes per attempt, {n} tasks", "writes",
                                [writes], higher_is_better=False, target=3.0,
                                notes="counted by the API stand-in"))
        finally:
            client.close()
            left = cluster.stop()
        if left != ([], []):
            print(f"bench_k8s: podman still had {left}", file=sys.stderr)
    write_rows(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
