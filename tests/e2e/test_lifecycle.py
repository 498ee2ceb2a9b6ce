"""Cancel, restart, auto-start and crash recovery, through the real CLI and server processes."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from tests.conftest import Osmo, write


def _wf_id(out: str) -> str:
    return out.splitlines()[0].split(" - ")[1].strip()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]


def _pids_with(text: str) -> set[int]:
    """Live processes whose command line holds ``text``: a sandboxed task's ``$$`` is a pid of
    its own namespace, so the tests find its processes by a unique argument instead."""
    found = set()
    for name in os.listdir("/proc"):
        try:
            if name.isdigit() and text.encode() in Path(f"/proc/{name}/cmdline").read_bytes():
                found.add(int(name))
        except OSError:
            pass
    return {pid for pid in found if _alive(pid)}


def _wait_file(path: Path, timeout: float = 60) -> str:
    deadline = time.monotonic() + timeout
    while not path.exists() or not path.read_text().strip():
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.05)
    return path.read_text().strip()


def test_submit_autostarts_server_and_server_commands(osmo: Osmo, tmp_path: Path) -> None:
    assert osmo("server", "status").code == 3
    spec = write(tmp_path / "a.yaml", "workflow:\n  name: auto\n  tasks:\n"
                 "  - {name: a, command: [echo, up]}\n")
    r = osmo("submit", str(spec))
    assert r.code == 0 and r.out.startswith("Workflow ID - auto-1")
    assert osmo("server", "status", check=True).out.startswith("running: pid")
    assert _wf_id(osmo("submit", str(spec), check=True).out) == "auto-2"
    pid = osmo.server_pid()
    assert pid is not None
    osmo("server", "stop", check=True)
    assert not _alive(pid)
    assert osmo("server", "status").code == 3


def test_unreachable_server_exit_code(osmo: Osmo) -> None:
    r = osmo("--server", "tcp/127.0.0.1:9", "list")
    assert r.code == 3
    assert "cannot connect to an osmo server" in r.err and "Traceback" not in r.err


def test_cancel_kills_the_process_group(osmo: Osmo, tmp_path: Path) -> None:
    pidfile = tmp_path / "pid"
    marker = f"600.{os.getpid()}{time.monotonic_ns() % 10**6}"  # a unique `sleep` argument
    spec = write(tmp_path / "c.yaml", f"""
workflow:
  name: cancelme
  tasks:
  - name: long
    command: [sh, -c, "sleep {marker} & echo $! > {pidfile}; wait"]
  - name: next
    command: ["true"]
    inputs: [{{task: long}}]
""")
    wf_id = osmo.submit(spec)
    _wait_file(pidfile)
    task = _pids_with(marker)  # the task's shell, its `sleep` child (and a sandbox's bwrap)
    assert task
    r = osmo("cancel", wf_id, check=True)
    assert "FAILED_CANCELED" in r.out
    info = osmo.wait_for(wf_id, lambda i: i["status"] == "FAILED_CANCELED")
    assert {t["name"]: t["status"] for t in info["tasks"]} == {
        "long": "FAILED_CANCELED", "next": "FAILED_CANCELED"}
    deadline = time.monotonic() + 30
    while any(map(_alive, task)):  # the grandchild `sleep` dies with the process group
        assert time.monotonic() < deadline, "task's child process survived cancel"
        time.sleep(0.05)


def test_restart_reruns_only_what_did_not_complete(osmo: Osmo, tmp_path: Path) -> None:
    runs, flag = tmp_path / "runs", tmp_path / "fixed"
    spec = write(tmp_path / "r.yaml", f"""
workflow:
  name: again
  tasks:
  - name: prep
    command: [sh, -c, "echo prep >> {runs}; echo data > {{{{output}}}}/d.txt"]
  - name: use
    command: [sh, -c, "test -e {flag} && cat {{{{input:prep}}}}/d.txt > {{{{output}}}}/u.txt"]
    inputs: [{{task: prep}}]
""")
    r = osmo("submit", str(spec), "--wait")
    assert r.code == 1
    first = _wf_id(r.out)
    flag.write_text("ok")
    r = osmo("restart", first, "--wait")
    assert r.code == 0, r.out + r.err
    second = _wf_id(r.out)
    assert second != first
    info = osmo.query(second)
    prep = [t for t in info["tasks"] if t["name"] == "prep"][0]
    use = [t for t in info["tasks"] if t["name"] == "use"][0]
    assert prep["reused"] and prep["status"] == "COMPLETED"
    assert runs.read_text().count("prep") == 1  # not re-run
    assert (Path(use["output"]) / "u.txt").read_text().strip() == "data"


def test_server_kill9_mid_run_recovers_and_completes(osmo: Osmo, tmp_path: Path) -> None:
    runs, release, started = tmp_path / "runs", tmp_path / "release", tmp_path / "started"
    spec = write(tmp_path / "k.yaml", f"""
workflow:
  name: survive
  tasks:
  - name: first
    command: [sh, -c, "echo first >> {runs}; echo 41 > {{{{output}}}}/n"]
  - name: second
    command: [sh, -c, "echo second >> {runs}; echo $$ > {started}; while [ ! -e {release} ]; do sleep 0.05; done; echo $(( $(cat {{{{input:first}}}}/n) + 1 )) > {{{{output}}}}/n"]
    inputs: [{{task: first}}]
  - name: third
    command: [sh, -c, "echo third >> {runs}; cat {{{{input:second}}}}/n"]
    inputs: [{{task: second}}]
""")
    wf_id = osmo.submit(spec)
    _wait_file(started)
    old_task = _pids_with(str(release))
    assert old_task
    server = osmo.server_pid()
    assert server is not None
    os.kill(server, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while _alive(server):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    started.unlink()
    # Any CLI call starts a new server, which recovers the workflow.
    assert osmo("query", wf_id, check=True).code == 0
    _wait_file(started)
    deadline = time.monotonic() + 30
    while any(map(_alive, old_task)):  # the orphaned attempt was killed, not left running
        assert time.monotonic() < deadline, "the lost attempt's process was left running"
        time.sleep(0.05)
    release.write_text("go")
    info = osmo.wait_for(wf_id, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"))
    assert info["status"] == "COMPLETED", info
    lines = runs.read_text().split()
    assert lines.count("first") == 1  # completed task not re-run
    assert lines.count("second") == 2 and lines.count("third") == 1
    second = [t for t in info["tasks"] if t["name"] == "second"][0]
    assert second["retry"] == 1
    assert "42" in osmo("logs", wf_id, "-t", "third").out


def test_pool_and_resource_lists_show_capacity_in_use(osmo: Osmo, tmp_path: Path) -> None:
    started, release = tmp_path / "started", tmp_path / "release"
    spec = write(tmp_path / "busy.yaml", f"""
workflow:
  name: busy
  resources:
    default: {{cpu: 1, memory: 1Gi}}
  tasks:
  - name: hold
    command: [sh, -c, "echo up > {started}; while [ ! -e {release} ]; do sleep 0.05; done"]
""")
    wf = osmo.submit(spec)
    _wait_file(started)
    nodes = json.loads(osmo("resource", "list", "--format", "json", check=True).out)
    assert [n["pool"] for n in nodes] == ["local"]
    assert nodes[0]["used"]["cpu"] == 1 and nodes[0]["used"]["memory"] == 2**30
    assert "local" in osmo("pool", "list", check=True).out
    assert osmo("workers", check=True).out.splitlines()[1].startswith("local")
    release.write_text("go")
    osmo.wait_for(wf, lambda i: i["status"] == "COMPLETED")
    nodes = json.loads(osmo("workers", "--format", "json", check=True).out)
    assert nodes[0]["used"]["cpu"] == 0


def test_server_stop_kills_a_server_that_does_not_stop(osmo: Osmo) -> None:
    """A server that does not stop on SIGTERM in time (here: SIGSTOPped) gets SIGKILL."""
    from osmo.sdk.connect import stop_server

    osmo("server", "start", check=True)
    pid = osmo.server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGSTOP)
    assert stop_server(osmo.home, timeout=1.0) == pid
    assert not _alive(pid)
    assert osmo("list", check=True).code == 0  # the next call starts a new server
