"""Typed tasks in their image, started warm from a runner container, through the real CLI.

A server with ``--runtime container`` runs a custom type (``warmtypes:probe``, the probe of
``tests/hostile/test_warm_runners.py``) in the Python test image: two attempts in a row
share one runner container (``osmo resource list`` counts them) and nothing else: the
second sees none of the first's environment, credentials, module state, threads or
descriptors. ``osmo workflow exec`` into a warm attempt sees its files. A kill -9 of the
server mid-attempt leaves no runner container, and the restarted server finishes the
workflow. ``warm: false`` starts cold.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from osmo.runtime.container import ContainerEngine
from tests.conftest import Osmo, ended, wait_gone, write
from tests.containers.submitting import leftovers, owner_labels, tasks
from tests.hostile.test_warm_runners import TYPES

TWO_IN_A_ROW = """
workflow:
  name: warm-in-image
  tasks:
  - name: dirty
    type: warmtypes:probe
    image: {image}
    params: {{mode: dirty}}
    environment: {{OWN: dirty-own}}
    credentials: {{api: {{TOKEN: token}}}}
  - name: probe
    type: warmtypes:probe
    image: {image}
    inputs: [{{task: dirty}}]
  - name: cold
    type: warmtypes:probe
    image: {image}
    warm: false
    inputs: [{{task: probe}}]
"""

GATED = """
workflow:
  name: warm-gated-in-image
  tasks:
  - name: first
    type: warmtypes:probe
    image: {image}
    params: {{mode: wait, gate: /osmo/data/output/gate}}
"""


def _project(tmp_path: Path, spec: str) -> Path:
    folder = tmp_path / "project"
    write(folder / "warmtypes.py", TYPES)
    return write(folder / "wf.yaml", spec)


def _seen(osmo: Osmo, wf_id: str, task: str) -> dict:
    found = next((Path(osmo.home) / "runs" / wf_id / task).glob("*/output/seen.json"))
    return json.loads(found.read_text())


def _runners(osmo: Osmo) -> list[dict]:
    listed = json.loads(osmo("resource", "list", "--format", "json", check=True).out)
    rows = listed if isinstance(listed, list) else listed.get("resources", listed)
    return [w for row in rows for w in row.get("warm") or []]


def test_two_attempts_in_one_runner_container_share_nothing(
        cosmo: Osmo, python_image: str, engine: ContainerEngine, tmp_path: Path) -> None:
    cosmo("credential", "set", "api", "--payload", "token=warm-S3CRET", check=True)
    wf = cosmo.submit(_project(tmp_path, TWO_IN_A_ROW.format(image=python_image)), "--wait")
    rows = tasks(cosmo, wf)
    assert all(r["status"] == "COMPLETED" for r in rows.values()), rows
    dirty, probe, cold = (_seen(cosmo, wf, name) for name in ("dirty", "probe", "cold"))
    assert dirty["secret"] == "warm-S3CRET" and dirty["own"] == "dirty-own"
    assert dirty["leaked"] == "1" and dirty["touched"] and dirty["patched"]
    assert probe["secret"] is None and probe["own"] is None, probe  # its own environment
    assert probe["leaked"] is None and not probe["touched"] and not probe["patched"], probe
    assert probe["threads"] == 1, probe  # dirty's thread died with dirty's process
    assert not any("held.txt" in fd for fd in probe["fds"]), probe["fds"]
    assert not any(fd.startswith("socket:") for fd in probe["fds"]), probe["fds"]  # no runner
    assert probe["cwd"] == dirty["cwd"] == "/osmo/run/work"
    assert (dirty["pid"], probe["pid"]) == (2, 2), (dirty, probe)  # each its own pid namespace
    runners = _runners(cosmo)
    assert [(w["type"], w["started"]) for w in runners] == [("warmtypes:probe@1", 2)], runners
    environ = Path(f"/proc/{runners[0]['pid']}/environ").read_bytes()
    assert b"warm-S3CRET" not in environ and b"dirty-own" not in environ  # it never had them
    (runner,) = engine.containers({**owner_labels(cosmo), "osmo.warm": "1"})
    assert "warm-S3CRET" not in engine.call("inspect", runner)
    said = {name: cosmo("logs", wf, "-t", name, check=True).out for name in rows}
    mark = "warm start: forked from a runner of warmtypes:probe in a container of its image"
    assert [name for name, text in said.items() if mark in text] == ["dirty", "probe"], said


def test_kill_9_of_the_server_leaves_no_runner_container_and_the_rerun_completes(
        cosmo: Osmo, python_image: str, engine: ContainerEngine, tmp_path: Path) -> None:
    wf = cosmo.submit(_project(tmp_path, GATED.format(image=python_image)))
    runs = Path(cosmo.home) / "runs" / wf / "first"
    deadline = time.monotonic() + 120
    while not (gates := list(runs.glob("*/output.partial/gate"))):
        assert time.monotonic() < deadline, "the attempt never started"
        time.sleep(0.1)
    labels = {**owner_labels(cosmo), "osmo.warm": "1"}
    assert len(engine.containers(labels)) == 1
    # exec: a new container over the attempt's view (its files, environment and user)
    r = cosmo("workflow", "exec", wf, "first", "--", "sh", "-c",
              "cat /osmo/data/output/gate; echo $OSMO_TASK; id -u", timeout=120)
    assert r.code == 0 and r.out.split() == ["2", "first", str(os.getuid())], (r.out, r.err)
    server = cosmo.server_pid()
    assert server is not None
    os.kill(server, signal.SIGKILL)
    wait_gone(server)
    assert leftovers(engine, labels) == ([], []), "the runner container outlived its server"
    gates[0].unlink()
    cosmo("server", "start", check=True)
    deadline = time.monotonic() + 120
    while not (again := list(runs.glob("*/output.partial/gate"))):
        assert time.monotonic() < deadline, "the lost attempt never ran again"
        time.sleep(0.1)
    again[0].unlink()
    info = cosmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", info


def _gate(cosmo: Osmo, wf: str, task: str = "first", timeout: float = 120) -> Path:
    """The gate file the running attempt of ``task`` wrote in its output folder."""
    runs = Path(cosmo.home) / "runs" / wf / task
    deadline = time.monotonic() + timeout
    while not (gates := list(runs.glob("*/output.partial/gate"))):
        assert time.monotonic() < deadline, f"no attempt of {task} is waiting"
        time.sleep(0.1)
    return gates[0]


def test_cancel_and_timeout_end_warm_attempts_in_their_runner_container(
        cosmo: Osmo, python_image: str, engine: ContainerEngine, tmp_path: Path) -> None:
    wf = cosmo.submit(_project(tmp_path, GATED.format(image=python_image)))
    _gate(cosmo, wf)
    (runner,) = _runners(cosmo)
    assert runner["running"] == 1, runner
    cosmo("cancel", wf, check=True)
    assert cosmo.wait_for(wf, ended)["status"] != "COMPLETED"
    deadline = time.monotonic() + 30
    while (now := _runners(cosmo)) and now[0]["running"]:
        assert time.monotonic() < deadline, now  # the attempt ended, the runner lives
        time.sleep(0.2)
    assert [w["pid"] for w in now] == [runner["pid"]], now
    timed = GATED.format(image=python_image).replace(
        "  name: warm-gated-in-image\n",
        "  name: warm-timed-in-image\n  timeout: {exec_timeout: 3s}\n")
    wf = cosmo.submit(write(tmp_path / "project" / "timed.yaml", timed))
    info = cosmo.wait_for(wf, ended, timeout=120)  # its timeout killed it; the gate stays
    assert info["status"].startswith("FAILED"), info
    assert _gate(cosmo, wf).exists()


def test_a_runner_container_killed_under_its_attempt_is_replaced(
        cosmo: Osmo, python_image: str, engine: ContainerEngine, tmp_path: Path) -> None:
    """SIGKILL of the runner: its attempt is lost (not failed) and runs again, forked from
    a new runner container."""
    wf = cosmo.submit(_project(tmp_path, GATED.format(image=python_image)))
    gate = _gate(cosmo, wf)
    (runner,) = _runners(cosmo)
    gate.unlink()
    os.kill(runner["pid"], signal.SIGKILL)
    wait_gone(runner["pid"])
    _gate(cosmo, wf).unlink()  # rescheduled, on a new runner
    info = cosmo.wait_for(wf, ended, timeout=120)
    assert info["status"] == "COMPLETED", info
    assert info["tasks"][0]["retry"] == 1, info["tasks"]
    said = cosmo("logs", wf, "-t", "first", check=True).out
    assert [w["pid"] for w in _runners(cosmo)] not in ([], [runner["pid"]]), said


def test_a_file_the_image_lacks_starts_cold_and_leaves_nothing_for_the_next_attempt(
        cosmo: Osmo, python_image: str, tmp_path: Path) -> None:
    """A ``files:`` path the image does not have would be made on the runner container's
    root, which every later attempt shares: that attempt starts cold instead, and the next
    warm one does not see it."""
    spec = f"""
workflow:
  name: warm-files
  tasks:
  - name: planter
    type: warmtypes:probe
    image: {python_image}
    files:
    - path: /usr/lib/planted/conf.txt
      contents: from the planter
  - name: after
    type: warmtypes:probe
    image: {python_image}
    inputs: [{{task: planter}}]
    files:
    - path: /etc/hostname
      contents: its own
"""
    wf = cosmo.submit(_project(tmp_path, spec), "--wait")
    rows = tasks(cosmo, wf)
    assert all(r["status"] == "COMPLETED" for r in rows.values()), rows
    said = {name: cosmo("logs", wf, "-t", name, check=True).out for name in rows}
    mark = "warm start: forked from a runner"
    assert mark not in said["planter"] and mark in said["after"], said
    (runner,) = _runners(cosmo)
    assert not Path(f"/proc/{runner['pid']}/root/usr/lib/planted").exists()
