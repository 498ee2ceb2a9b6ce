"""The engine never wedges: one bad event fails its own attempt, everything else goes on;
a server that cannot go on exits non-zero; an attempt that crashed a server is quarantined
(issue 11, item 1). Real servers with one fault injected (``tests/hostile/faulty_server.py``),
driven through the real CLI.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.status import ExitCode
from tests.conftest import REPO, Osmo, wait_gone, write
from tests.hostile.datarun import finished, tasks

# Several tasks finish together, so the culprit's exit shares a batch with innocent ones.
SPEC = """
workflow:
  name: mixed
  tasks:
  - name: gate
    command: [sh, -c, "echo go > {{output}}/go"]
""" + "".join(f"""
  - name: {name}
    inputs: [{{task: gate}}]
    command: [sh, -c, "echo {name} > {{{{output}}}}/out.txt"]
""" for name in ("a", "b", "boom", "c", "d")) + """
  - name: after
    inputs: [{task: a}, {task: b}, {task: c}, {task: d}]
    command: [sh, -c, "cat {{input:a}}/out.txt {{input:d}}/out.txt > {{output}}/all"]
"""

OTHER = """
workflow:
  name: other
  tasks:
  - name: t
    command: [sh, -c, "echo fine > {{output}}/f"]
"""


class Faulty:
    """A server process with ``OSMO_FAULT`` set, started and stopped by this test."""

    def __init__(self, osmo: Osmo, fault: str, *args: str) -> None:
        self.osmo = osmo
        self.log = osmo.home / "faulty.log"
        osmo.home.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "tests.hostile.faulty_server", "--home",
                 str(osmo.home), *args], env={**osmo.env, "OSMO_FAULT": fault}, cwd=REPO,
                stdin=subprocess.DEVNULL, stdout=out, stderr=out, start_new_session=True)
        deadline = time.monotonic() + 60
        while osmo.server_pid() != self.proc.pid:
            assert self.proc.poll() is None, self.log.read_text()
            assert time.monotonic() < deadline, "the faulty server never came up"
            time.sleep(0.05)

    def killed_itself(self, marker: Path) -> None:
        """Wait until the fault SIGKILLed this server (``marker`` made first) and it is gone."""
        assert self.proc.wait(timeout=60) == -9, self.log.read_text()
        assert marker.exists()
        wait_gone(self.proc.pid)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def faulty(osmo: Osmo) -> Iterator[list[Faulty]]:
    started: list[Faulty] = []
    yield started
    for server in started:
        server.stop()


@pytest.mark.parametrize("fault", ["commit:boom", "apply:boom"])
def test_one_bad_event_fails_its_attempt_and_the_rest_goes_on(
        osmo: Osmo, faulty: list[Faulty], tmp_path: Path, fault: str) -> None:
    server = Faulty(osmo, fault)
    faulty.append(server)
    wf = finished(osmo, write(tmp_path / "m.yaml", SPEC), code=1)  # boom failed: so did it
    by_name = tasks(osmo, wf)
    boom = by_name.pop("boom")
    assert boom["status"] == "FAILED" and boom["exit_code"] == ExitCode.OUTPUT_ERROR
    assert "injected" in boom["message"] and "could not apply" in boom["message"]
    assert {name: t["status"] for name, t in by_name.items()} == dict.fromkeys(
        ("gate", "a", "b", "c", "d", "after"), "COMPLETED")
    assert "injected" in server.log.read_text()  # and in the server's log
    # the same server keeps serving: a new workflow, and a cancel (an engine write)
    finished(osmo, write(tmp_path / "o.yaml", OTHER))
    assert osmo("cancel", wf, timeout=30).code == 0
    assert server.proc.poll() is None
    cpu = osmo("resource", "list", "--format", "json", check=True).json()
    assert cpu[0]["used"]["cpu"] == 0  # type: ignore[index]


def test_a_server_whose_store_is_gone_exits_non_zero(osmo: Osmo, faulty: list[Faulty],
                                                      tmp_path: Path) -> None:
    gone = tmp_path / "gone"
    server = Faulty(osmo, f"store:{gone}")
    faulty.append(server)
    wf = osmo.submit(write(tmp_path / "w.yaml", f"""
workflow:
  name: waits
  tasks:
  - name: t
    command: [sh, -c, "while [ ! -e {gone} ]; do sleep 0.05; done"]
"""))
    osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING", timeout=60)
    gone.write_text("")  # the store is gone; the task's exit is the next thing to commit
    # the server must stop (exit 3), not stay up answering "running"
    assert server.proc.wait(timeout=60) == 3
    log = server.log.read_text()
    assert "engine cannot go on" in log and "disk I/O error (injected)" in log
    assert osmo.server_pid() is None  # its address is gone: clients see it is down


def test_a_task_that_crashed_the_server_twice_is_quarantined(osmo: Osmo, faulty: list[Faulty],
                                                              tmp_path: Path) -> None:
    server = Faulty(osmo, "crash:boom")
    faulty.append(server)
    wf = osmo.submit(write(tmp_path / "m.yaml", SPEC))
    assert server.proc.wait(timeout=90) == -9  # it crashed applying boom's exit
    # The next server crashes on boom again (its retry's exit): the second strike.
    again = Faulty(osmo, "crash:boom")
    faulty.append(again)
    assert again.proc.wait(timeout=90) == -9
    # The next server (started by the CLI, no fault) fails boom instead of running it again.
    osmo.wait_for(wf, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"))
    by_name = tasks(osmo, wf)
    boom = by_name["boom"]
    assert boom["status"] == "FAILED" and "quarantined" in boom["message"], boom
    assert boom["retry"] == 1  # run again once after the first crash, never after the second
    assert by_name["a"]["status"] == "COMPLETED" and by_name["after"]["status"] == "COMPLETED"
    assert "quarantined" in osmo("logs", wf, check=True).out + (
        osmo.home / "server.log").read_text()
    assert not os.path.getsize(osmo.home / "applying.json")


def test_one_crash_while_applying_a_report_runs_the_task_again(
        osmo: Osmo, faulty: list[Faulty], tmp_path: Path) -> None:
    """A kill -9 from outside at the instant a report is applied is not the task's fault."""
    server = Faulty(osmo, "crash:boom")
    faulty.append(server)
    wf = osmo.submit(write(tmp_path / "m.yaml", SPEC))
    assert server.proc.wait(timeout=90) == -9
    info = osmo.wait_for(wf, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"))
    assert info["status"] == "COMPLETED", info
    boom = tasks(osmo, wf)["boom"]
    assert boom["status"] == "COMPLETED" and boom["retry"] == 1, boom
    assert "a second such crash quarantines the task" in (osmo.home / "server.log").read_text()
