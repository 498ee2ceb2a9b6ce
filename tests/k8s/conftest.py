"""Fixtures for the Kubernetes API stand-in (see README.md here).

- ``api``: an :class:`ApiServer` on loopback with a :class:`Kubelet` attached (so pods are
  scheduled and status scripts play) and one node; ``api.core`` / ``api.custom`` are the
  official client's ``CoreV1Api`` / ``CustomObjectsApi`` pointed at it. Pods that reach
  podman need the ``podman`` fixture as well.
- ``podman``: podman's environment and the offline test images (``tests/containers``);
  without podman the test is skipped, or fails when ``OSMO_EXPECT_CONTAINERS=1``.

After each test the kubelet removes what is left and the test fails if podman still has a
pod or container of it.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from kubernetes import client

from tests.containers.images import ensure_images, write_containers_conf
from tests.k8s.apiserver import ApiServer
from tests.k8s.kubelet import Kubelet


@dataclass
class Cluster:
    """A stand-in API server, its node side and the real client's APIs."""

    server: ApiServer
    kubelet: Kubelet
    core: client.CoreV1Api
    custom: client.CustomObjectsApi
    client: client.ApiClient


def _client(url: str) -> client.ApiClient:
    config = client.Configuration()
    config.host = url
    return client.ApiClient(config)


@pytest.fixture(scope="session")
def podman_conf(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """podman's environment with the containers.conf these machines need (no images)."""
    if shutil.which("podman") is None:
        message = "podman is not installed (./dev test installs it: apt-get install podman runc)"
        if os.environ.get("OSMO_EXPECT_CONTAINERS") == "1":
            pytest.fail(message)
        pytest.skip(message)
    conf = write_containers_conf(tmp_path_factory.mktemp("k8s-podman"))
    return dict(os.environ, CONTAINERS_CONF=str(conf))


@pytest.fixture(scope="session")
def podman(podman_conf: dict[str, str]) -> dict[str, str]:
    """podman's environment, with the offline test images built (alpine:3.18 ...)."""
    ensure_images(podman_conf)
    return podman_conf


def _cluster(tmp_path: Path, env: dict[str, str], validate: str | None) -> Iterator[Cluster]:
    server = ApiServer(validate=validate).start()
    kubelet = Kubelet(server, env, tmp_path / "node")
    kubelet.add_node("node-1", cpu="4", memory="8Gi", gpus=1)
    api_client = _client(server.url)
    try:
        yield Cluster(server, kubelet, client.CoreV1Api(api_client),
                      client.CustomObjectsApi(api_client), api_client)
    finally:
        api_client.close()
        pods, containers = kubelet.close()
        server.stop()
    assert (pods, containers) == ([], []), f"podman still has pods {pods}, containers {containers}"


@pytest.fixture
def api(tmp_path: Path, podman_conf: dict[str, str]) -> Iterator[Cluster]:
    """The stand-in with one node (4 cpu, 8Gi, 1 GPU)."""
    yield from _cluster(tmp_path, podman_conf, validate=None)


@pytest.fixture
def strict_api(tmp_path: Path, podman_conf: dict[str, str]) -> Iterator[Cluster]:
    """The stand-in refusing what fails the Kubernetes 1.33 schema (strict)."""
    yield from _cluster(tmp_path, podman_conf, validate="1.33")
