"""Fixtures for the tests that run real containers with podman.

- ``podman_env`` (session): the containers.conf these machines need (``images.py``) handed
  to podman through ``CONTAINERS_CONF`` in this process's environment (so servers the tests
  start inherit it). Without podman the tests are skipped, or fail when
  ``OSMO_EXPECT_CONTAINERS=1`` (``./dev test`` sets it: a full run must not skip them).
- ``images`` (session): the tutorials' images, built offline (``ensure_images``).
- ``labels``: the labels every container and network a test makes must carry; at the end
  the test must have removed them all (it fails otherwise, and the leftovers are removed).
- ``cosmo``: a CLI whose server runs image tasks in containers; nothing of it may be left.
- ``engine`` / ``runtime``: osmo's adapter for podman, and a ``ContainerRuns`` that is
  closed (its background kills and removals finished) before ``labels`` checks.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine, ContainerRuns, detect_engine
from tests.conftest import Osmo
from tests.containers.images import KINDS_PYTHON, ensure_images, write_containers_conf
from tests.containers.submitting import container_osmo, leftovers, owner_labels

TEST_LABEL = "osmo.test-session"


@pytest.fixture(scope="session")
def podman_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """This process's environment with ``CONTAINERS_CONF`` set (and set in os.environ)."""
    if shutil.which("podman") is None:
        message = "podman is not installed (./dev test installs it: apt-get install podman runc)"
        if os.environ.get("OSMO_EXPECT_CONTAINERS") == "1":
            pytest.fail(message)
        pytest.skip(message)
    conf = write_containers_conf(tmp_path_factory.mktemp("podman"))
    old = os.environ.get("CONTAINERS_CONF")
    os.environ["CONTAINERS_CONF"] = str(conf)
    yield dict(os.environ)
    if old is None:
        os.environ.pop("CONTAINERS_CONF", None)
    else:
        os.environ["CONTAINERS_CONF"] = old


@pytest.fixture(scope="session")
def images(podman_env: dict[str, str]) -> dict[str, str]:
    """The tutorials' images (name → image id)."""
    return ensure_images(podman_env)


@pytest.fixture(scope="session")
def python_image(podman_env: dict[str, str]) -> str:
    """The name of an image with this interpreter's ``python3`` (built on first use)."""
    names = ensure_images(podman_env, KINDS_PYTHON)
    return next(name for name in names if not name.startswith("localhost/"))


@pytest.fixture(scope="session")
def engine(podman_env: dict[str, str]) -> ContainerEngine:
    """osmo's podman adapter (environment read at each call: CONTAINERS_CONF applies)."""
    return ContainerEngine(detect_engine("podman"))


@pytest.fixture(scope="session")
def session_label() -> dict[str, str]:
    """A label no other test session (another worktree on this machine) carries."""
    return {TEST_LABEL: uuid.uuid4().hex}


@pytest.fixture
def labels(engine: ContainerEngine, session_label: dict[str, str]) -> Iterator[dict[str, str]]:
    """Labels for everything a test creates; afterwards nothing carrying them may remain."""
    yield dict(session_label)
    containers, networks = engine.remove_labelled(session_label)
    assert not containers and not networks, (
        f"the test left containers {containers} and networks {networks} behind")


@pytest.fixture
def runtime(engine: ContainerEngine, labels: dict[str, str]) -> Iterator[ContainerRuns]:
    """A container runtime, closed before ``labels`` looks for leftovers."""
    rt = ContainerRuns(engine)
    yield rt
    rt.close()


@pytest.fixture
def cosmo(podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
          tmp_path: Path) -> Iterator[Osmo]:
    """A CLI whose server runs image tasks in containers; nothing of it may be left after."""
    runner = container_osmo(tmp_path / "home", podman_env)
    yield runner
    runner.stop_server()
    assert leftovers(engine, owner_labels(runner)) == ([], [])
