"""One contract, every runtime (``osmo.runtime.api.Runtime``): the conformance kit
``osmo.testing.check_runtime`` runs over the process runtime, the sandboxed process runtime
(bubblewrap in the node's namespaces), the container runtime (podman, with the offline
images of tests/containers), the Kubernetes runtime (pods of the API stand-in of tests/k8s,
under podman kube play, its exec through the stand-in's WebSocket) and the Slurm runtime (a
batch job per attempt, on the session's cluster of tests/slurm). The next runtime is done when
it joins :data:`RUNTIMES` and passes.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from osmo.runtime.api import Launch, ProcessHandle, Runtime
from osmo.runtime.choose import processes_for_node
from osmo.runtime.container import ContainerEngine, ContainerRuntime
from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.kube import Kube
from osmo.runtime.kubernetes.runtime import KubernetesRuntime
from osmo.runtime.process.runtime import ProcessRuntime
from osmo.runtime.process.sandbox import choose, node_network
from osmo.runtime.process.sandboxed import SandboxRuntime
from osmo.runtime.process.warm import WarmRunners
from osmo.runtime.slurm import Slurm, SlurmRuntime
from osmo.testing import check_runtime
from osmo.worker.taskenv import base_env
from tests.containers.conftest import (  # noqa: F401 - fixtures the container case asks for
    engine,
    images,
    podman_env,
)
from tests.k8s.conftest import Cluster, api  # noqa: F401 - the Kubernetes case's stand-in
from tests.k8s.nodes import kubeconfig
from tests.k8s.store import PODS, SECRETS
from tests.slurm.cluster import SlurmCluster
from tests.slurm.conftest import slurm_session  # noqa: F401 - the Slurm case's cluster

HOST_LISTENER = ("busybox", "nc", "-l", "-p", "{port}")  # busybox-static: ./dev installs it


@dataclass
class Case:
    """A runtime under test and how its tasks are written."""

    runtime: Runtime
    image: str | None = None  # what every task names (a runtime that runs tasks in images)
    listen: Sequence[str] = ("nc", "-l", "-p", "{port}")
    merged_output: bool = False


def _process(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    runtime = ProcessRuntime()
    yield Case(runtime, listen=HOST_LISTENER)
    runtime.close()


def _warm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    """The process runtime whose every command is forked from a warm runner, then exec'd."""
    warm = WarmRunners(base_env(os.environ))
    runtime = ProcessRuntime(warm=warm, warm_commands=True)
    yield Case(runtime, listen=HOST_LISTENER)
    assert [(r.type, r.started) for r in warm.runners()] == [("", 6)], "not forked warm"
    runtime.close()


def _sandbox(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    runtime = processes_for_node("on", (), home=tmp_path / "home", address=None,
                                 pool="contract")
    assert isinstance(runtime, SandboxRuntime)  # ./dev test installs bubblewrap
    yield Case(runtime, listen=HOST_LISTENER)
    runtime.close()


def _sandbox_warm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    """The sandboxed runtime whose every command is forked from a sandboxed warm runner.

    Each attempt gets, in a fork of the runner, the view bubblewrap would give it cold.
    """
    if os.geteuid() != 0:
        pytest.skip("sandboxed warm starts need a root osmo (a non-root one starts cold)")
    warm = WarmRunners(base_env(os.environ))
    found = choose("on")
    assert found is not None  # ./dev test installs bubblewrap
    network = node_network(outbound=False)
    runtime = SandboxRuntime(found.joined(network), network, hidden=(tmp_path / "home",),
                             warm=warm, warm_commands=True)
    yield Case(runtime, listen=HOST_LISTENER)
    assert [(r.type, r.started) for r in warm.runners()] == [("", 6)], "not forked warm"
    runtime.close()


def _container(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    found: ContainerEngine = request.getfixturevalue("engine")
    request.getfixturevalue("images")
    owner = f"contract-{uuid.uuid4().hex}"
    runtime = ContainerRuntime(found, owner=owner)
    yield Case(runtime, image="alpine:3.18")
    runtime.close()
    assert found.remove_labelled({"osmo.owner": owner}) == ([], []), "containers were left"


def _kubernetes(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    """Pods of the API stand-in (tests/k8s), run under podman kube play."""
    request.getfixturevalue("images")
    cluster: Cluster = request.getfixturevalue("api")
    pool = KubePool(kubeconfig=str(kubeconfig(cluster.server.url, tmp_path)))
    runtime = KubernetesRuntime(pool, Kube(cluster.client), instance="contract")
    yield Case(runtime, image="alpine:3.18", merged_output=True)
    runtime.close()
    assert [obj["metadata"]["name"] for _, obj in cluster.server.store.objects(
        [PODS, SECRETS])] == [], "pods or Secrets were left"


def _slurm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    cluster: SlurmCluster = request.getfixturevalue("slurm_session")
    owner = f"contract-{uuid.uuid4().hex}"
    runtime = SlurmRuntime(Slurm(cluster.env), owner=owner)
    yield Case(runtime, listen=HOST_LISTENER)
    runtime.close()
    left = [job for job in runtime.slurm.owned(owner) if job.state in ("PENDING", "RUNNING")]
    assert not left, f"jobs were left: {left}"


RUNTIMES: dict[str, Callable[[pytest.FixtureRequest, Path], Iterator[Case]]] = {
    "process": _process,
    "warm": _warm,
    "sandbox": _sandbox,
    "sandbox-warm": _sandbox_warm,
    "container": _container,
    "kubernetes": _kubernetes,
    "slurm": _slurm,
}
"""Every runtime, by name: what the contract runs over (add the next one here)."""


@pytest.fixture(params=sorted(RUNTIMES))
def case(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Case]:
    yield from RUNTIMES[request.param](request, tmp_path)


def test_every_runtime_keeps_the_contract(case: Case, tmp_path: Path) -> None:
    check_runtime(case.runtime, tmp_path / "attempts", image=case.image, listen=case.listen,
                  merged_output=case.merged_output)


class _Broken:
    """A process runtime that loses exit codes and ignores SIGTERM: the kit must say so."""

    def __init__(self, inner: ProcessRuntime) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        if force:
            self._inner.kill(handle, force=True)

    def reap(self, handle: ProcessHandle) -> int:
        self._inner.reap(handle)
        return 0

    def paths(self, cmd: object) -> object:
        return self._inner.paths(cmd)  # type: ignore[arg-type]

    def prepare(self, launch: Launch, attempt: object, *, progress: object) -> Launch:
        return launch


def test_the_kit_finds_a_broken_runtime(tmp_path: Path) -> None:
    with pytest.raises(AssertionError) as found:
        check_runtime(_Broken(ProcessRuntime()), tmp_path,  # type: ignore[arg-type]
                      listen=HOST_LISTENER, timeout=5.0)
    message = str(found.value)
    assert "exit3: exit code 0, expected 3" in message, message
    assert "term: exit code None after SIGTERM" in message, message
