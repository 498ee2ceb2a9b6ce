"""An image's run of a pod's data side: osmo's init container fetches, its collector collects.

:func:`fetch_and_collect` plays what a task pod's ``osmo-fetch`` and ``osmo-collect`` containers
do (the ``command`` of ``osmo.runtime.kubernetes.manifest``, which replaces the image's
entrypoint) under ``podman run``, as a non-root uid, against a node's pod-data API on loopback,
and checks that the attempt's files reached the pod's volume and the task's output came back.
The offline ``osmo`` test image (``tests/k8s/test_pod_data_image.py``) and the image built
from the chart's Dockerfile (``tests/helm/test_dockerfile_build.py``) both run it.
"""

from __future__ import annotations

import os
import subprocess
import uuid
from collections.abc import Mapping
from pathlib import Path

from osmo.config import free_port
from osmo.runtime.kubernetes import podside
from osmo.runtime.kubernetes.podio import COLLECT, FETCH, PodData, scan_mounts
from osmo.transport.zenoh_link import Link

NODE = "node-image"


def _side(env: Mapping[str, str], image: str, uid: int, side: str, endpoint: str,
          ticket: Path, root: Path) -> subprocess.CompletedProcess[str]:
    name = f"osmo-podside-{uuid.uuid4().hex[:8]}"
    try:
        return subprocess.run(
            ["podman", "run", "--rm", "--name", name, "--network", "host", "--pull=never",
             "--user", f"{uid}:{uid}", "-v", f"{root}:/osmo-pod",
             "-v", f"{ticket.parent}:/run/osmo:ro", "--entrypoint", "python3", image,
             "-m", "osmo.runtime.kubernetes.podside", side, "--connect", endpoint,
             "--node", NODE, "--attempt", "a1", "--ticket", f"/run/osmo/{ticket.name}",
             "--root", "/osmo-pod"], capture_output=True, text=True, env=dict(env), timeout=120)
    finally:
        subprocess.run(["podman", "rm", "-f", "--ignore", name], capture_output=True,
                       env=dict(env))


def fetch_and_collect(env: Mapping[str, str], image: str, uid: int, tmp_path: Path) -> None:
    """Run ``image``'s fetch then collect side as ``uid``; assert what each must leave."""
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint])
    data = PodData(router, NODE)
    try:
        src = tmp_path / "node" / "in0"
        src.mkdir(parents=True)
        (src / "a.txt").write_text("hello pod\n")
        output = tmp_path / "node" / "output.partial"
        output.mkdir()
        files, dirs = scan_mounts([(src, "osmo/data/input/0")])
        tickets = data.open("a1", files, [*dirs, podside.OUTPUT], output)
        secret = tmp_path / "secret"
        secret.mkdir(mode=0o755)
        for role, token in tickets.items():
            (secret / role).write_text(token)
            (secret / role).chmod(0o644)
        root = tmp_path / "pod"
        root.mkdir()
        os.chown(root, uid, uid)
        fetched = _side(env, image, uid, "fetch", endpoint, secret / FETCH, root)
        assert fetched.returncode == 0, fetched.stderr
        assert (root / "osmo/data/input/0/a.txt").read_text() == "hello pod\n"
        assert (root / podside.OUTPUT).stat().st_uid == uid
        (root / podside.OUTPUT / "result.txt").write_text("made in the pod\n")  # the task's part
        data.ended("a1", collect=True)
        collected = _side(env, image, uid, "collect", endpoint, secret / COLLECT, root)
        assert collected.returncode == 0, collected.stderr
        assert data.collected("a1", 10) is None
        assert (output / "result.txt").read_text() == "made in the pod\n"
    finally:
        data.stop()
        router.close()
