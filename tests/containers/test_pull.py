"""Pulling a missing image through ``osmo submit``: its progress reaches the task's log as the
engine prints it (while the pull is still under way), ``osmo submit --wait`` on a terminal shows
it live, and a failed pull keeps its ``image 'x' not found: …`` message.

The registry is the loopback stand-in of ``tests/containers/registry.py``; it holds the
manifest request until the test has seen the pull's first line in ``osmo logs``.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

from osmo.runtime.container import ContainerEngine
from tests.cli.terminal import in_pty
from tests.conftest import ended, write
from tests.containers.registry import fake_registry
from tests.containers.submitting import container_osmo, leftovers, osmo_lines, owner_labels, tasks


def test_pull_progress_streams_into_the_task_log_while_it_pulls(
        podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    with fake_registry("unused") as registry:
        registry.release.clear()
        osmo = container_osmo(tmp_path / "home", {
            **podman_env, "CONTAINERS_REGISTRIES_CONF": str(registry.registries_conf(tmp_path))})
        image = f"{registry.host}/team/pulled:1"
        try:
            wf = osmo.submit(write(tmp_path / "pull.yaml", f"""
workflow:
  name: pull
  tasks:
  - name: pulled
    image: {image}
    command: ["true"]
"""))
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
        finally:
            osmo.stop_server()
    assert info["status"] == "FAILED"
    assert row["status"] == "FAILED_START_ERROR"
    assert row["message"].startswith(f"image '{image}' not found: ")
    assert "manifest unknown" in row["message"]
    assert any(line.startswith("pull: ") and "manifest unknown" in line for line in lines)
    assert leftovers(engine, owner_labels(osmo)) == ([], [])


def test_submit_wait_on_a_terminal_shows_the_pull_while_it_pulls(
        podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    with fake_registry("unused") as registry:
        registry.release.clear()
        osmo = container_osmo(tmp_path / "home", {
            **podman_env, "CONTAINERS_REGISTRIES_CONF": str(registry.registries_conf(tmp_path))})
        image = f"{registry.host}/team/shown:1"
        spec = write(tmp_path / "pull.yaml", f"""
workflow:
  name: shown
  tasks:
  - name: pulled
    image: {image}
    command: ["true"]
""")
        held: list[str] = []

        def seen(out: str) -> None:  # the live table shows the pull, then let it go on
            plain = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out)  # colours and cursor moves
            if not registry.release.is_set() and re.search(
                    rf"pulled +0 +INITIALIZING .*pulling \(\d+s\): Trying to pull {image}", plain):
                held.append(out)
                registry.release.set()

        try:
            code, out = in_pty("submit", str(spec), "--wait", env=osmo.env, seen=seen)
        finally:
            registry.release.set()
            osmo.stop_server()
    assert held, out  # seen while the registry still held the pull
    assert code == 1 and "FAILED_START_ERROR" in out, out
    assert leftovers(engine, owner_labels(osmo)) == ([], [])
