"""Timings of the stand-in (README.md here): ``python -m tests.k8s.measure [N ...]``.

For each N (default 1 and 10): N pods of the offline busybox image running ``true`` are
created at once through the official client; the time until every one is seen Succeeded on a
watch is reported, then the same pods played with bare ``podman kube play`` (host network,
as the stand-in plays them) and waited for: the limit the stand-in adds its overhead to.
Medians of three runs. Also the API writes per pod (create and
delete). podman, its test images and root are needed, as for the tests.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from kubernetes import client, watch

from tests.containers.images import ensure_images, write_containers_conf
from tests.k8s.apiserver import ApiServer
from tests.k8s.kubelet import Kubelet

NS = "default"
REPEAT = 3


def _pod(name: str) -> dict[str, object]:
    return {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": name},
            "spec": {"restartPolicy": "Never", "containers": [
                {"name": "main", "image": "alpine:3.18", "command": ["true"]}]}}


def through_standin(n: int, env: dict[str, str], folder: Path) -> tuple[float, float]:
    """Seconds until N pods are Succeeded through the stand-in; API writes per pod."""
    server = ApiServer().start()
    kubelet = Kubelet(server, env, folder)
    kubelet.add_node("node-1", cpu="64", memory="64Gi")
    api = client.ApiClient(client.Configuration(host=server.url))
    core = client.CoreV1Api(api)
    try:
        since = core.list_namespaced_pod(NS).metadata.resource_version
        start = time.monotonic()
        for i in range(n):
            core.create_namespaced_pod(NS, _pod(f"p{i}"))
        done: set[str] = set()
        for event in watch.Watch().stream(core.list_namespaced_pod, NS, resource_version=since,
                                          timeout_seconds=600):
            if event["object"].status.phase == "Succeeded":
                done.add(event["object"].metadata.name)
                if len(done) == n:
                    break
        took = time.monotonic() - start
        for i in range(n):
            core.delete_namespaced_pod(f"p{i}", NS)
        writes = sum(server.writes.values()) / n
    finally:
        api.close()
        left = kubelet.close()
        server.stop()
    assert left == ([], []), left
    return took, writes


def bare_play(n: int, env: dict[str, str], folder: Path) -> float:
    """Seconds to play N such pods with podman kube play and wait for their exit."""
    names = [f"bare-{os.getpid()}-{i}" for i in range(n)]
    try:
        start = time.monotonic()
        plays = []
        for name in names:
            path = folder / f"{name}.json"
            body = _pod(name)
            path.write_text(json.dumps(body))
            plays.append(subprocess.Popen(["podman", "kube", "play", "--network", "host",
                                           str(path)], env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        for play in plays:
            play.wait()
        subprocess.run(["podman", "wait", *[f"{name}-main" for name in names]], env=env,
                       capture_output=True)
        return time.monotonic() - start
    finally:
        for name in names:
            subprocess.run(["podman", "pod", "rm", "-f", "-t", "0", name], env=env,
                           capture_output=True)


def main(counts: list[int]) -> None:
    with tempfile.TemporaryDirectory(prefix="osmo-k8s-measure-") as tmp:
        folder = Path(tmp)
        env = dict(os.environ, CONTAINERS_CONF=str(write_containers_conf(folder)))
        ensure_images(env)
        print(f"pods  stand-in (s)  bare kube play (s)  writes/pod   (median of {REPEAT})")
        for n in counts:
            runs = [through_standin(n, env, folder / f"node-{n}-{i}") for i in range(REPEAT)]
            bare = statistics.median(bare_play(n, env, folder) for _ in range(REPEAT))
            took = statistics.median(t for t, _ in runs)
            print(f"{n:4d}  {took:12.2f}  {bare:18.2f}  {runs[0][1]:10.1f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [1, 10])
