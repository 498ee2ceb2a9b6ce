"""The Kubernetes runtime's cost: tasks as pods through the API stand-in, against podman alone.

Runs a server and one ``osmo worker --runtime kubernetes`` whose pods go through the official
client to the API stand-in of ``tests/k8s`` and run under ``podman kube play`` (host network,
the offline busybox image). Rows:

- **limit: podman kube play of the same pod, N** — N pods running ``true``, played with bare
  ``podman kube play`` at once and waited for (``tests/k8s/measure.py``'s ``bare_play``): what
  the machine needs with no orchestrator and no API.
- **k8s: N tasks, submit → COMPLETED** — ``osmo submit --wait`` of a workflow of N
  independent tasks of that image running ``true``, each a pod; target: 1.2 × the limit
  (the issue's "at most 20% over").
- **k8s: API writes per attempt** — writes the stand-in counted (create, delete, ...)
  divided by the attempts; target 3 (pod, Secret, delete).

N is 1 and 100 (1 and 5 with ``OSMO_BENCH_QUICK=1``). Needs root, podman and its offline test
images (built on first use): otherwise the script writes no rows.

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


def spec(n: int) -> str:
    """A workflow of ``n`` independent tasks running ``true`` in the busybox image."""
    tasks = "".join(f"  - name: t{i}\n    image: alpine:3.18\n    command: [\"true\"]\n"
                    for i in range(n))
    return f"workflow:\n  name: bench-k8s-{n}\n  tasks:\n{tasks}"


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
        try:
            cluster.kubelet.add_node("node-big", cpu="256", memory="256Gi")
            cluster.start_worker("kube-bench", "--cpus", "256", groupNetwork="host")
            cluster.osmo("submit", _write(folder, 1), "--wait", check=True)  # warm-up
            for n in (1, args.tasks):
                bare = [bare_play(n, env, folder) for _ in range(args.runs)]
                limit = row(f"limit: podman kube play of the same pod, {n}", "s", bare,
                            higher_is_better=False)
                rows.append(limit)
                before = sum(cluster.server.writes.values())
                took = []
                for _ in range(args.runs):
                    start = time.monotonic()
                    cluster.osmo("submit", _write(folder, n), "--wait", check=True,
                                 timeout=1800)
                    took.append(time.monotonic() - start)
                rows.append(row(f"k8s: {n} tasks as pods, submit → COMPLETED", "s", took,
                                higher_is_better=False, limit_of=limit["name"],
                                target=1.2 * statistics.median(bare)))
                writes = (sum(cluster.server.writes.values()) - before) / (n * args.runs)
                rows.append(row(f"k8s: API writes per attempt, {n} tasks", "writes",
                                [writes], higher_is_better=False, target=3.0,
                                notes="counted by the API stand-in"))
        finally:
            left = cluster.stop()
        if left != ([], []):
            print(f"bench_k8s: podman still had {left}", file=sys.stderr)
    write_rows(args.json, rows)
    return 0


def _write(folder: Path, n: int) -> str:
    path = folder / f"bench-{n}.yaml"
    path.write_text(spec(n))
    return str(path)


if __name__ == "__main__":
    sys.exit(main())
