"""The chart's Dockerfile, built for real with podman and used as the chart uses it.

No registry is reachable here, so ``python:3.12-slim`` is replaced by a local stand-in made as
the official image is (``python_slim.py``: Debian bookworm minbase from Debian's mirror plus
CPython 3.12 under ``/usr/local``) and handed over with ``--build-arg PYTHON_IMAGE``; every
step of the repository's ``Dockerfile`` runs unchanged: ``apt-get`` of bubblewrap,
slirp4netns and util-linux, ``pip install`` of ``osmo[kubernetes]`` from the build context.
The build runs with ``--network host``: those steps reach Debian's mirror and PyPI through the
host's network, the only way out of these machines (podman's bridge would add its own NAT and
DNS and test nothing of the Dockerfile). And pip in the build trusts what the host trusts: the
host's CA bundle and a ``pip.conf`` naming it are mounted for the build's steps only (nothing
of them lands in the image), since these machines reach PyPI through an egress that re-signs
TLS, which pip's own certifi bundle refuses ("self-signed certificate in certificate chain").
A missing mirror, PyPI or mmdebstrap fails the tests; nothing is skipped.

The built image then does what the chart runs it for, as its user 10001: ``osmo --help``,
``osmo worker --runtime kubernetes --help`` (a pool of kind ``kubernetes``), and a task pod's
fetch and collect sides (``tests/k8s/podside_image.py``). Both images are removed at the end,
by id.
"""

from __future__ import annotations

import json
import ssl
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.containers.conftest import podman_env  # noqa: F401 - fixture
from tests.helm import python_slim
from tests.helm.chart import REPO
from tests.k8s.podside_image import fetch_and_collect

UID = 10001  # the Dockerfile's OSMO_UID, the chart's podSecurityContext.runAsUser
# the first test carries the build: 2.5-5 min here (a Debian bootstrap and two stages' downloads),
# longer at load 8 on 2 cores
pytestmark = pytest.mark.timeout(1500)


def _podman(env: dict[str, str], *args: str, timeout: float = 120
            ) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["podman", *args], capture_output=True, text=True, env=env,
                          timeout=timeout)


@pytest.fixture(scope="module")
def chart_image(podman_env: dict[str, str],  # noqa: F811
                tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The id of the image built from the repository's Dockerfile on the stand-in."""
    folder = tmp_path_factory.mktemp("dockerfile-build")
    run = uuid.uuid4().hex[:12]
    base = f"localhost/osmo-dockerfile-test/python:{python_slim.PY}-slim-{run}"
    made: list[str] = []
    try:
        made.append(python_slim.build(folder, base, podman_env))
        iidfile = folder / "iid"
        bundle = Path(ssl.get_default_verify_paths().openssl_cafile).resolve()
        assert bundle.is_file(), f"the host has no CA bundle at {bundle}"
        (folder / "pip.conf").write_text("[global]\ncert = /etc/osmo-build-ca.crt\n")
        # --jobs 2: the runtime stage's apt-get runs beside the builder's pip install
        built = _podman(podman_env, "build", "--network", "host", "--pull=never", "--jobs", "2",
                        "--layers=false", "-v", f"{folder / 'pip.conf'}:/etc/pip.conf:ro",
                        "-v", f"{bundle}:/etc/osmo-build-ca.crt:ro",
                        "--build-arg", f"PYTHON_IMAGE={base}",
                        "--iidfile", str(iidfile), "-f", str(REPO / "Dockerfile"), str(REPO),
                        timeout=1800)
        if iidfile.exists():
            made.append(iidfile.read_text().strip())
        assert built.returncode == 0, built.stdout[-6000:] + built.stderr[-4000:]
        yield made[-1]
    finally:
        for image in reversed(made):
            _podman(podman_env, "rmi", "-f", image)


def test_the_image_is_configured_as_the_chart_expects(
        podman_env: dict[str, str], chart_image: str) -> None:  # noqa: F811
    config = json.loads(_podman(podman_env, "image", "inspect", chart_image).stdout)[0]["Config"]
    assert config["User"] == f"{UID}:{UID}"
    assert config["Entrypoint"] == ["osmo"]
    assert "OSMO_HOME=/var/lib/osmo" in config["Env"]


def test_the_built_image_runs_osmo_as_its_user(
        podman_env: dict[str, str], chart_image: str) -> None:  # noqa: F811
    who = _podman(podman_env, "run", "--rm", "--entrypoint", "id", chart_image)
    assert who.returncode == 0 and who.stdout.split()[0] == f"uid={UID}(osmo)", who
    usage = _podman(podman_env, "run", "--rm", chart_image, "--help")
    assert usage.returncode == 0, usage.stderr
    assert "worker" in usage.stdout
    worker = _podman(podman_env, "run", "--rm", chart_image, "worker", "--runtime",
                     "kubernetes", "--help")
    assert worker.returncode == 0, worker.stderr
    assert "--runtime" in worker.stdout
    # the task sandbox's parts, which the chart's `--sandbox on` needs at start
    tools = _podman(podman_env, "run", "--rm", "--entrypoint", "sh", chart_image, "-c",
                    "bwrap --version && slirp4netns --version && command -v nsenter setpriv")
    assert tools.returncode == 0, tools.stderr


def test_the_built_image_fetches_and_collects_a_pods_data_as_its_user(
        podman_env: dict[str, str], chart_image: str, tmp_path: Path) -> None:  # noqa: F811
    fetch_and_collect(podman_env, chart_image, UID, tmp_path)
