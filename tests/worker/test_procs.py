"""A worker's record of running commands, and killing what a previous life left (real processes)."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.worker.procs import ProcessRecords, kill_recorded
from tests.runtime.test_process_runtime import alive, wait_until


@pytest.fixture
def group() -> Iterator[subprocess.Popen[bytes]]:
    """A process group: a shell (its leader) and a background child."""
    proc = subprocess.Popen(["sh", "-c", "sleep 300 & echo $!; wait"], stdout=subprocess.PIPE,
                            start_new_session=True)
    yield proc
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # the group this fixture made (its child too)
    except ProcessLookupError:
        pass
    proc.wait()
    assert proc.stdout is not None
    proc.stdout.close()


def test_a_recorded_group_is_killed_and_forgotten(tmp_path: Path,
                                                  group: subprocess.Popen[bytes]) -> None:
    assert group.stdout is not None
    child = int(group.stdout.readline())
    ProcessRecords(tmp_path / "procs").add(group.pid)
    assert kill_recorded(tmp_path / "procs") == 1
    wait_until(lambda: not alive(child))
    assert list((tmp_path / "procs").iterdir()) == []


def test_a_reused_pid_is_not_killed(tmp_path: Path, group: subprocess.Popen[bytes]) -> None:
    folder = tmp_path / "procs"
    folder.mkdir()
    (folder / str(group.pid)).write_text("12.5")  # another process's start time
    assert kill_recorded(folder) == 0
    assert group.poll() is None and not (folder / str(group.pid)).exists()


def test_a_removed_record_is_left_alone(tmp_path: Path, group: subprocess.Popen[bytes]) -> None:
    records = ProcessRecords(tmp_path / "procs")
    records.add(group.pid)
    records.remove(group.pid)
    assert kill_recorded(tmp_path / "procs") == 0
    assert group.poll() is None


def test_garbage_in_the_folder_is_cleared(tmp_path: Path) -> None:
    folder = tmp_path / "procs"
    folder.mkdir()
    (folder / "123").write_text("not a time")
    (folder / "notes").write_text("x")
    assert kill_recorded(folder) == 0
    assert not (folder / "123").exists()
    assert kill_recorded(tmp_path / "missing") == 0


def test_the_record_empties_when_nothing_it_holds_runs(tmp_path: Path,
                                                       group: subprocess.Popen[bytes]) -> None:
    records = ProcessRecords(tmp_path / "procs")
    records.add(group.pid)
    records.add(os.getpid())  # a second one, still running
    records.remove(group.pid)
    assert (tmp_path / "procs" / "running").read_text().count("\n") == 2  # one still runs
    records.remove(os.getpid())
    assert (tmp_path / "procs" / "running").read_text() == ""
    records.close()
