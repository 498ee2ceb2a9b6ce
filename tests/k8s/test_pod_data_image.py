"""osmo's own image runs a pod's data side (issue #28 item 2): the offline ``osmo`` test image
(``tests/containers/images.py``) runs ``python3 -m osmo.runtime.kubernetes.podside`` under
podman, as the task's non-root uid, against a node's pod-data API on loopback: the fetch
writes the attempt's files into the pod's volume, the collector sends its output back.

(The chart's Dockerfile itself cannot be built here: its base, ``python:3.12-slim``, would be
pulled from a registry, and none is reachable from these machines.)
"""

from __future__ import annotations

import os
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.runtime.kubernetes import podside
from osmo.runtime.kubernetes.podio import COLLECT, FETCH, PodData, scan_mounts
from osmo.transport.zenoh_link import Link
from tests.containers.conftest import podman_env  # noqa: F401 - fixture
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images

UID = 1000


@pytest.fixture(scope="module")
def osmo_image(podman_env: dict[str, str]) -> str:  # noqa: F811
    ensure_images(podman_env, KINDS_OSMO)
    return OSMO_IMAGE


@pytest.fixture
def node() -> Iterator[tuple[PodData, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint])
    data = PodData(router, "node-image")
    yield data, endpoint
    data.stop()
    router.close()


def _side(env: dict[str, str], image: str, side: str, endpoint: str, ticket: Path,
          root: Path) -> subprocess.CompletedProcess[str]:
    name = f"osmo-podside-{uuid.uuid4().hex[:8]}"
    try:
        return subprocess.run(
            ["podman", "run", "--rm", "--name", name, "--network", "host", "--pull=never",
             "--user", f"{UID}:{UID}", "-v", f"{root}:/osmo-pod",
             "-v", f"{ticket.parent}:/run/osmo:ro", image,
             "python3", "-m", "osmo.runtime.kubernetes.podside", side, "--connect", endpoint,
             "--node", "node-image", "--attempt", "a1", "--ticket", f"/run/osmo/{ticket.name}",
             "--root", "/osmo-pod"], capture_output=True, text=True, env=env, timeout=120)
    finally:
        subprocess.run(["podman", "rm", "-f", "--ignore", name], capture_output=True, env=env)


def test_the_osmo_image_fetches_and_collects_as_a_non_root_uid(
        podman_env: dict[str, str], osmo_image: str, node: tuple[PodData, str],  # noqa: F811
        tmp_path: Path) -> None:
    data, endpoint = node
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
    os.chown(root, UID, UID)
    fetched = _side(podman_env, osmo_image, "fetch", endpoint, secret / FETCH, root)
    assert fetched.returncode == 0, fetched.stderr
    assert (root / "osmo/data/input/0/a.txt").read_text() == "hello pod\n"
    assert (root / podside.OUTPUT).stat().st_uid == UID
    (root / podside.OUTPUT / "result.txt").write_text("made in the pod\n")  # the task's part
    data.ended("a1", collect=True)
    collected = _side(podman_env, osmo_image, "collect", endpoint, secret / COLLECT, root)
    assert collected.returncode == 0, collected.stderr
    assert data.collected("a1", 10) is None
    assert (output / "result.txt").read_text() == "made in the pod\n"
