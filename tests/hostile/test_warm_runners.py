"""Warm runners (osmo.runtime.process.warm) under attack, through the real CLI and server.

Two attempts in a row forked from ONE runner (same parent pid, which is not the server's):
the second sees nothing the first left — its environment and credentials, module state it
monkeypatched, threads it started, descriptors it opened. A task that segfaults or whose
runner is SIGKILLed takes down only its own attempt; a runner over its memory limit is
replaced. Cancel, timeout and kill -9 of the server during warm attempts leave nothing
running. The pool runs unsandboxed (``--sandbox off``): warm starts are that path's.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from tests.conftest import Osmo, ended, read_pid, wait_gone, write

TYPES = r'''
import atexit, ctypes, json, os, threading, time
from pathlib import Path
from osmo import Param, task_type

STATE = {"touched": False}


@task_type(version="1", params={"mode": Param(str, default="probe"),
                                "gate": Param(str, default="")})
def probe(ctx):
    """dirty: change everything it can; probe: report what it sees; others: misbehave."""
    mode = ctx.params["mode"]
    out = ctx.output
    if mode == "dirty":
        os.environ["LEAKED_BY_DIRTY"] = "1"
        STATE["touched"] = True
        json.dumps = lambda *a, **k: "patched"
        threading.Thread(target=time.sleep, args=(3600,), daemon=True).start()
        globals()["HELD"] = open(out / "held.txt", "w")
    if mode == "unclosed":  # ends as an interpreter exit would end it: flushed, atexit run
        left = open(out / "unclosed.txt", "w")
        left.write("written, never closed")
        globals()["LEFT"] = left
        atexit.register(lambda: (out / "atexit.txt").write_text("ran"))
    if mode == "segfault":
        ctypes.string_at(0)
    if mode == "wait":  # until the test removes the gate
        gate = Path(ctx.params["gate"])
        gate.write_text(f"{os.getpid()}\n")
        while gate.exists():
            time.sleep(0.2)
    fds = sorted(os.readlink(f"/proc/self/fd/{n}") for n in os.listdir("/proc/self/fd")
                 if os.path.exists(f"/proc/self/fd/{n}"))
    seen = {"ppid": os.getppid(), "pid": os.getpid(), "secret": os.environ.get("TOKEN"),
            "own": os.environ.get("OWN"), "leaked": os.environ.get("LEAKED_BY_DIRTY"),
            "touched": STATE["touched"], "patched": json.dumps({}) == "patched",
            "threads": len(os.listdir("/proc/self/task")), "fds": fds, "cwd": os.getcwd()}
    (out / "seen.json").write_text(json.JSONEncoder().encode(seen))
'''


def _project(tmp_path: Path, spec: str) -> Path:
    folder = tmp_path / "project"
    write(folder / "warmtypes.py", TYPES)
    return write(folder / "wf.yaml", spec)


def _seen(osmo: Osmo, wf_id: str, task: str) -> dict:
    info = {t["name"]: t for t in osmo.query(wf_id)["tasks"]}
    return json.loads((Path(info[task]["output"]) / "seen.json").read_text())


@pytest.fixture
def warm_osmo(osmo: Osmo) -> Osmo:
    osmo("server", "start", "--sandbox", "off", check=True)
    return osmo


TWO_IN_A_ROW = """
workflow:
  name: warm-leaks
  tasks:
  - name: dirty
    type: warmtypes:probe
    params: {mode: dirty}
    environment: {OWN: dirty-own}
    credentials: {api: {TOKEN: token}}
  - name: probe
    type: warmtypes:probe
    inputs: [{task: dirty}]
"""


def test_two_attempts_on_one_runner_share_nothing(warm_osmo: Osmo, tmp_path: Path) -> None:
    warm_osmo("credential", "set", "api", "--payload", "token=warm-S3CRET", check=True)
    wf = warm_osmo.submit(_project(tmp_path, TWO_IN_A_ROW), "--wait")
    dirty, probe = _seen(warm_osmo, wf, "dirty"), _seen(warm_osmo, wf, "probe")
    server = warm_osmo.server_pid()
    assert dirty["ppid"] == probe["ppid"] != server, (dirty, probe, server)  # one runner
    assert dirty["secret"] == "warm-S3CRET" and dirty["own"] == "dirty-own"
    assert dirty["leaked"] == "1" and dirty["touched"] and dirty["patched"]
    assert probe["secret"] is None and probe["own"] is None, probe  # its own environment
    assert probe["leaked"] is None and not probe["touched"] and not probe["patched"], probe
    assert probe["threads"] == 1, probe  # the runner has one thread; dirty's died with it
    assert not any("held.txt" in fd for fd in probe["fds"]), probe["fds"]
    assert probe["cwd"].endswith("/work") and probe["cwd"] != dirty["cwd"]
    runner = Path(f"/proc/{probe['ppid']}/environ").read_bytes()
    assert b"warm-S3CRET" not in runner and b"dirty-own" not in runner  # it never had them
    listed = warm_osmo("resource", "list", check=True).out
    assert "warmtypes:probe@1 x2" in listed, listed
    logs = warm_osmo("logs", wf, "-t", "probe", check=True).out
    assert "warm start: forked from a runner of warmtypes:probe" in logs, logs


UNCLOSED = """
workflow:
  name: warm-unclosed
  tasks:
  - name: warm
    type: warmtypes:probe
    params: {mode: unclosed}
  - name: cold
    type: warmtypes:probe
    params: {mode: unclosed}
    warm: false
  - name: after
    type: warmtypes:probe
    inputs: [{task: warm}]
"""


def test_a_warm_attempt_ends_as_a_cold_one_files_flushed_and_atexit_run(
        warm_osmo: Osmo, tmp_path: Path) -> None:
    """A warm attempt leaves its process with ``os._exit``: what an interpreter's exit does
    for a cold one is done first (the files the task left open flushed, its ``atexit``
    handlers run). Before: the warm attempt's file was empty, its handler never ran."""
    wf = warm_osmo.submit(_project(tmp_path, UNCLOSED), "--wait")
    info = {t["name"]: t for t in warm_osmo.query(wf)["tasks"]}
    for name in ("warm", "cold"):
        out = Path(info[name]["output"])
        assert (out / "unclosed.txt").read_text() == "written, never closed", name
        assert (out / "atexit.txt").read_text() == "ran", name
    warm = _seen(warm_osmo, wf, "warm")
    assert warm["ppid"] == _seen(warm_osmo, wf, "after")["ppid"] != warm_osmo.server_pid()


CRASH = """
workflow:
  name: warm-crash
  tasks:
  - name: crash
    type: warmtypes:probe
    params: {mode: segfault}
  - name: after
    type: warmtypes:probe
  - name: later
    type: warmtypes:probe
    inputs: [{task: after}]
"""


def test_a_segfault_takes_down_only_its_own_attempt(warm_osmo: Osmo, tmp_path: Path) -> None:
    done = warm_osmo("submit", str(_project(tmp_path, CRASH)), "--wait", timeout=240)
    assert done.code == 1, done
    wf = done.out.split("Workflow ID - ", 1)[1].split()[0]
    tasks = {t["name"]: t for t in warm_osmo.query(wf)["tasks"]}
    assert tasks["crash"]["status"] == "FAILED" and tasks["crash"]["exit_code"] == 139, tasks
    assert tasks["after"]["status"] == tasks["later"]["status"] == "COMPLETED", tasks
    after, later = _seen(warm_osmo, wf, "after"), _seen(warm_osmo, wf, "later")
    assert after["ppid"] == later["ppid"] != warm_osmo.server_pid()


GATED = """
workflow:
  name: warm-gated
  tasks:
  - name: first
    type: warmtypes:probe
    params: {{mode: wait, gate: "{gate}"}}
{more}"""


def test_a_runner_killed_under_its_attempt_is_replaced(warm_osmo: Osmo, tmp_path: Path) -> None:
    """SIGKILL of the runner: its attempt is lost (not failed), runs again on a new runner."""
    gate = tmp_path / "gate"
    wf = warm_osmo.submit(_project(tmp_path, GATED.format(gate=gate, more="")))
    pid = read_pid(gate)
    runner = _parent(pid)
    gate.unlink()
    os.kill(runner, signal.SIGKILL)
    wait_gone(pid)
    again = read_pid(gate, timeout=120)  # rescheduled, forked from a new runner
    assert again != pid and _parent(again) not in (runner, warm_osmo.server_pid())
    gate.unlink()
    info = warm_osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", info
    assert info["tasks"][0]["retry"] == 1, info["tasks"]


def test_cancel_and_timeout_end_warm_attempts(warm_osmo: Osmo, tmp_path: Path) -> None:
    gate, late = tmp_path / "gate", tmp_path / "late"
    wf = warm_osmo.submit(_project(tmp_path, GATED.format(gate=gate, more="")))
    first = read_pid(gate)
    assert _parent(first) != warm_osmo.server_pid()  # forked from a runner
    warm_osmo("cancel", wf, check=True)
    wait_gone(first, timeout=60)
    assert warm_osmo.wait_for(wf, ended)["status"] != "COMPLETED"
    timed = GATED.format(gate=late, more="").replace(
        "  name: warm-gated\n", "  name: warm-timed\n  timeout: {exec_timeout: 3s}\n")
    wf = warm_osmo.submit(write(tmp_path / "project" / "timed.yaml", timed))
    wait_gone(read_pid(late), timeout=60)  # its timeout killed it
    info = warm_osmo.wait_for(wf, ended)
    assert info["status"].startswith("FAILED"), info


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_kill_9_of_the_server_leaves_no_warm_attempt(warm_osmo: Osmo, tmp_path: Path) -> None:
    """Nothing of the server's runners outlives it; restarted, it finishes the workflow."""
    gate = tmp_path / "gate"
    wf = warm_osmo.submit(_project(tmp_path, GATED.format(gate=gate, more="")))
    pid = read_pid(gate)
    runner = _parent(pid)
    server = warm_osmo.server_pid()
    assert server is not None and runner != server
    os.kill(server, signal.SIGKILL)
    wait_gone(server)
    wait_gone(runner)
    wait_gone(pid)
    gate.unlink()
    warm_osmo("server", "start", "--sandbox", "off", check=True)
    again = read_pid(gate, timeout=120)
    assert _parent(again) not in (runner, warm_osmo.server_pid())  # a new server's runner
    gate.unlink()
    info = warm_osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", info


def test_a_runner_over_its_memory_limit_is_replaced(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", "--sandbox", "off", "--warm-max-memory", "1Mi", check=True)
    spec = TWO_IN_A_ROW.replace("    credentials: {api: {TOKEN: token}}\n", "")
    wf = osmo.submit(_project(tmp_path, spec), "--wait")
    dirty, probe = _seen(osmo, wf, "dirty"), _seen(osmo, wf, "probe")
    assert osmo.server_pid() not in (dirty["ppid"], probe["ppid"])
    assert dirty["ppid"] != probe["ppid"], (dirty, probe)  # each over 1Mi: a new runner


def test_warm_off_and_warm_false_start_cold(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", "--sandbox", "off", check=True)
    spec = TWO_IN_A_ROW.replace("    credentials: {api: {TOKEN: token}}\n", "").replace(
        "    inputs: [{task: dirty}]\n", "    inputs: [{task: dirty}]\n    warm: false\n")
    wf = osmo.submit(_project(tmp_path, spec), "--wait")
    assert _seen(osmo, wf, "probe")["ppid"] == osmo.server_pid()  # cold: the server's child
    assert _seen(osmo, wf, "dirty")["ppid"] != osmo.server_pid()
    osmo.stop_server()
    osmo("server", "start", "--sandbox", "off", "--warm", "off", check=True)
    wf = osmo.submit(_project(tmp_path, spec.replace("    warm: false\n", "")), "--wait",
                     "--no-cache")
    assert _seen(osmo, wf, "dirty")["ppid"] == _seen(osmo, wf, "probe")["ppid"] \
        == osmo.server_pid()


def test_warm_on_a_task_without_a_type_is_refused_with_its_place(osmo: Osmo,
                                                                 tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", "workflow:\n  name: w\n  tasks:\n  - name: a\n"
                                       "    command: ['true']\n    warm: nope\n  - name: b\n"
                                       "    command: ['true']\n    warm: false\n")
    done = osmo("submit", str(spec))
    assert done.code == 2, done
    assert f"{spec}:6:11:" in done.err and f"{spec}:9:11:" in done.err, done.err
    assert "'warm' but no 'type'" in done.err, done.err


def _reaped(pid: int, timeout: float = 20) -> bool:
    """Whether ``pid`` is gone from the process table (reaped, not a zombie) within ``timeout``."""
    deadline = time.monotonic() + timeout
    while Path(f"/proc/{pid}").exists():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


def test_runners_that_exit_are_reaped_not_left_zombies(osmo: Osmo, tmp_path: Path) -> None:
    """A runner retired while its attempt ran (over its memory: each attempt a new runner)
    and one that exits idle are both reaped by the server, with nothing more submitted."""
    osmo("server", "start", "--sandbox", "off", "--warm-max-memory", "1Mi", "--warm-idle", "1",
         check=True)
    spec = TWO_IN_A_ROW.replace("    credentials: {api: {TOKEN: token}}\n", "")
    wf = osmo.submit(_project(tmp_path, spec), "--wait")
    runners = {_seen(osmo, wf, "dirty")["ppid"], _seen(osmo, wf, "probe")["ppid"]}
    assert len(runners) == 2 and osmo.server_pid() not in runners, runners
    left = [pid for pid in runners if not _reaped(pid)]
    assert not left, [Path(f"/proc/{pid}/stat").read_text() for pid in left]
