"""Pulling a missing image through ``osmo submit``: its progress reaches the task's log as the
engine prints it (while the pull is still under way), ``osmo submit --wait`` on a terminal shows
it live, and a failed pull keeps its ``image 'x' not found: …`` message.

The registry is the loopback stand-in of ``tests/containers/registry.py``; it holds the
manifest request until the test has seen the pull's first line in ``osmo logs``.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from osmo.runtime.container import ContainerEngine
from tests.cli.terminal import in_pty
from tests.conftest import Osmo, ended, write
from tests.containers.registry import FakeRegistry, fake_registry
from tests.containers.submitting import container_osmo, leftovers, osmo_lines, owner_labels, tasks


@contextmanager
def _held_pull(podman_env: dict[str, str], tmp_path: Path
               ) -> Iterator[tuple[FakeRegistry, Osmo, str, Path]]:
    """A registry holding its manifests, a CLI whose server pulls from it, the image and a
    spec whose one task (``pulled``) runs in it."""
    with fake_registry("unused") as registry:
        registry.release.clear()
        osmo = container_osmo(tmp_path / "home", {
            **podman_env, "CONTAINERS_REGISTRIES_CONF": str(registry.registries_conf(tmp_path))})
        image = f"{registry.host}/team/pulled:1"
        spec = write(tmp_path / "pull.yaml", f"""
workflow:
  name: pull
  tasks:
  - name: pulled
    image: {image}
    command: ["true"]
""")
        try:
            yield registry, osmo, image, spec
        finally:
            registry.release.set()
            osmo.stop_server()


def test_pull_progress_streams_into_the_task_log_while_it_pulls(
        podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    with _held_pull(podman_env, tmp_path) as (registry, osmo, image, spec):
        wf = osmo.submit(spec)
        deadline = time.monotonic() + 45
        while not any(f"Trying to pull {image}" in line
                      for line in osmo_lines(osmo, wf, "pulled")):
            assert time.monotonic() < deadline, osmo("logs", wf).out
            assert not registry.release.is_set()
            time.sleep(0.2)
        assert tasks(osmo, wf)["pulled"]["status"] == "INITIALIZING"
        registry.release.set()  # the pull goes on, and fails: the image is not there
        info = osmo.wait_for(wf, ended, timeout=120)
        row = tasks(osmo, wf)["pulled"]
        lines = osmo_lines(osmo, wf, "pulled")
    assert info["status"] == "FAILED"
    assert row["status"] == "FAILED_START_ERROR"
    assert row["message"].startswith(f"image '{image}' not found: ")
    assert "manifest unknown" in row["message"]
    assert any(line.startswith("pull: ") and "manifest unknown" in line for line in lines)
    assert leftovers(engine, owner_labels(osmo)) == ([], [])


def test_submit_wait_on_a_terminal_shows_the_pull_while_it_pulls(
        podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    with _held_pull(podman_env, tmp_path) as (registry, osmo, image, spec):
        held: list[str] = []

        def seen(out: str) -> None:  # the live table shows the pull, then let it go on
            plain = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out)  # colours and cursor moves
            if not registry.release.is_set() and re.search(
                    rf"pulled +0 +INITIALIZING .*pulling \(\d+s\): Trying to pull {image}", plain):
                held.append(out)
                registry.release.set()

        code, out = in_pty("submit", str(spec), "--wait", env=osmo.env, seen=seen)
    assert held, out  # seen while the registry still held the pull
    assert code == 1 and "FAILED_START_ERROR" in out, out
    assert leftovers(engine, owner_labels(osmo)) == ([], [])
