"""Fixtures for the Kubernetes API stand-in (see README.md here).

- ``api``: an :class:`ApiServer` on loopback with a :class:`Kubelet` attached (so pods are
  scheduled and status scripts play) and one node; ``api.core`` / ``api.custom`` are the
  official client's ``CoreV1Api`` / ``CustomObjectsApi`` pointed at it. ``strict_api`` also
  checks objects against the 1.33 schema. Pods that reach podman need ``images`` as well.
- ``podman_env`` and ``images`` are the container tests' fixtures (``tests/containers``):
  podman's environment with the settings these machines need, and the offline test images;
  without podman the test is skipped, or fails when ``OSMO_EXPECT_CONTAINERS=1``.

After each test the kubelet removes what is left and the test fails if podman still has a
pod or container of it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from kubernetes import client

from tests.containers.conftest import images, podman_env  # noqa: F401 - the same fixtures
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
def api(tmp_path: Path, podman_env: dict[str, str]) -> Iterator[Cluster]:  # noqa: F811
    """The stand-in with one node (4 cpu, 8Gi, 1 GPU)."""
    yield from _cluster(tmp_path, podman_env, validate=None)


@pytest.fixture
def strict_api(tmp_path: Path, podman_env: dict[str, str]) -> Iterator[Cluster]:  # noqa: F811
    """The stand-in refusing what fails the Kubernetes 1.33 schema (strict)."""
    yield from _cluster(tmp_path, podman_env, validate="1.33")
