"""No task outlives its cancel, its worker or its server (end to end, real processes).

A sandboxed task's pids are its own, so ``$$`` means nothing outside: the tests find a task's
processes by a unique argument (``sleep 4001.25``) in ``/proc/<pid>/cmdline`` (a scan, never
a kill by name).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from tests.conftest import Osmo, ended, unique_sleep, wait_no_process, write
from tests.e2e.cluster import Cluster


def pids_with(marker: str) -> list[int]:
    """Live (non-zombie) processes whose command line holds ``marker`` as one argument."""
    found = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            args = Path(f"/proc/{name}/cmdline").read_bytes().split(b"\0")
            state = Path(f"/proc/{name}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if marker.encode() in args and state != "Z":
            found.append(int(name))
    return found


def wait_for(condition, timeout: float = 30.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.05)


def spec(tmp_path: Path, marker: str, name: str = "long") -> Path:
    # the main process, a child in its group, and a child that left the group (setsid)
    return write(tmp_path / f"{name}.yaml", f"""
workflow:
  name: {name}
  tasks:
  - name: t
    command: [sh, -c, 'sleep {marker} & setsid sleep {marker} & sleep {marker}']
""")


def test_cancel_kills_every_process_of_a_sandboxed_task(osmo: Osmo, tmp_path: Path) -> None:
    marker = "4001.25"
    wf = osmo.submit(spec(tmp_path, marker))
    wait_for(lambda: len(pids_with(marker)) == 3)
    osmo("cancel", wf, check=True)
    osmo.wait_for(wf, ended)
    wait_for(lambda: not pids_with(marker), timeout=10)  # the setsid one too


def test_server_killed_takes_its_tasks_with_it(osmo: Osmo, tmp_path: Path) -> None:
    marker = "4002.25"
    osmo.submit(spec(tmp_path, marker))
    wait_for(lambda: len(pids_with(marker)) == 3)
    pid = osmo.server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    time.sleep(1.0)
    assert pids_with(marker) == []


def test_worker_killed_takes_its_tasks_with_it(tmp_path: Path) -> None:
    marker = "4003.25"
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1")
        cluster.osmo.submit(spec(tmp_path, marker))
        wait_for(lambda: len(pids_with(marker)) == 3)
        cluster.signal("w1", signal.SIGKILL)
        time.sleep(1.0)
        assert pids_with(marker) == []
    finally:
        cluster.stop()


def test_restarted_worker_kills_what_its_previous_life_left(tmp_path: Path) -> None:
    """Unsandboxed, only the main process dies with the worker; its group is found by the
    pid and start time the worker recorded, and killed before the worker comes back."""
    marker = "4004.25"
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1", "--sandbox", "off")
        wf = cluster.osmo.submit(write(tmp_path / "bg.yaml", f"""
workflow:
  name: bg
  tasks:
  - name: t
    command: [sh, -c, 'sleep {marker} & sleep 300']
"""))
        wait_for(lambda: len(pids_with(marker)) == 1)
        cluster.signal("w1", signal.SIGKILL)
        cluster.workers["w1"].wait(timeout=30)
        time.sleep(0.5)
        left = pids_with(marker)
        assert len(left) == 1  # a leftover: the parent-death signal reaches the main only
        cluster.start_worker("w1", "--sandbox", "off", wait=False)
        cluster.wait_online("w1")  # (the task is then run again: a new process)
        assert not set(left) & set(pids_with(marker))
        cluster.osmo("cancel", wf, check=True)  # the run it started again ends too
        cluster.osmo.wait_for(wf, ended)
        wait_for(lambda: not pids_with(marker), timeout=10)
    finally:
        cluster.stop()


def test_no_sandbox_is_said_in_pool_list_and_task_log(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", "--sandbox", "off", check=True)
    pools = osmo("pool", "list", "--format", "json", check=True).json()
    assert [p["sandbox"] for p in pools] == ["none"]
    assert "none" in osmo("resource", "list", check=True).out.split()
    wf = osmo.submit(write(tmp_path / "one.yaml", """
workflow:
  name: one
  tasks:
  - name: t
    command: [sh, -c, "true"]
"""))
    assert osmo.wait_for(wf, ended)["status"] == "COMPLETED"
    assert "no sandbox: this task sees the host" in osmo("logs", wf, check=True).out


def test_sandbox_is_said_in_pool_list(osmo: Osmo) -> None:
    osmo("server", "start", check=True)
    pools = osmo("pool", "list", "--format", "json", check=True).json()
    assert [p["sandbox"] for p in pools] == ["bwrap"]
    assert "bwrap" in osmo("pool", "list", check=True).out.split()


def test_unsandboxed_main_process_dies_with_its_server(osmo: Osmo, tmp_path: Path) -> None:
    """Without a sandbox only the parent-death signal (``PR_SET_PDEATHSIG``) ends a task's
    main process when its server is SIGKILLed (bwrap's --die-with-parent does it in one)."""
    marker = unique_sleep()
    osmo("server", "start", "--sandbox", "off", check=True)
    osmo.submit(write(tmp_path / "main.yaml", f"""
workflow:
  name: main
  tasks:
  - name: t
    command: [sleep, "{marker}"]
"""))
    wait_for(lambda: len(pids_with(marker)) == 1)
    pid = osmo.server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    wait_no_process(marker, timeout=10)


def test_unsandboxed_main_process_dies_with_its_worker(tmp_path: Path) -> None:
    marker = unique_sleep()
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1", "--sandbox", "off")
        cluster.osmo.submit(write(tmp_path / "main.yaml", f"""
workflow:
  name: main
  tasks:
  - name: t
    command: [sleep, "{marker}"]
"""))
        wait_for(lambda: len(pids_with(marker)) == 1)
        cluster.signal("w1", signal.SIGKILL)
        wait_no_process(marker, timeout=10)
    finally:
        cluster.stop()
