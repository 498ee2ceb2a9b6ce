"""Caching end to end: identical tasks reuse outputs; a change reruns exactly what it affects."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import Osmo, write


def _spec(tmp_path: Path) -> Path:
    # Every task appends its name to runs.log, so the test can count what really ran.
    # cache: true for the workflow: its bare leaf tasks (total, side) would run every time
    # otherwise (the default: tests/e2e/test_reuse.py).
    text = """
default-values: {scale: 2, note: hi}
workflow:
  name: cached
  cache: true
  tasks:
  - name: source
    command: [sh, -c, "echo source >> LOG; seq 1 5 > {{output}}/n.txt"]
  - name: scale
    command: [sh, -c, "echo scale >> LOG; echo {{note}}; for n in $(cat {{input:source}}/n.txt); do echo $((n * {{scale}})); done > {{output}}/s.txt"]
    inputs: [{task: source}]
  - name: total
    command: [sh, -c, "echo total >> LOG; t=0; for n in $(cat {{input:scale}}/s.txt); do t=$((t + n)); done; echo $t > {{output}}/t.txt"]
    inputs: [{task: scale}]
  - name: side
    command: [sh, -c, "echo side >> LOG; echo side > {{output}}/side.txt"]
  - name: fresh
    cache: false
    command: [sh, -c, "echo fresh >> LOG"]
"""
    return write(tmp_path / "c.yaml", text.replace("LOG", str(tmp_path / "runs.log")))


def _submit(osmo: Osmo, spec: Path, *args: str) -> dict:
    r = osmo("submit", str(spec), "--wait", *args)
    assert r.code == 0, r.out + r.err
    return osmo.query(r.out.splitlines()[0].split(" - ")[1])


def _runs(tmp_path: Path) -> list[str]:
    log = tmp_path / "runs.log"
    ran = log.read_text().split() if log.exists() else []
    log.write_text("")
    return sorted(ran)


def test_identical_resubmit_reuses_every_cacheable_task(osmo: Osmo, tmp_path: Path) -> None:
    spec = _spec(tmp_path)
    first = _submit(osmo, spec)
    assert _runs(tmp_path) == ["fresh", "scale", "side", "source", "total"]
    second = _submit(osmo, spec)
    assert _runs(tmp_path) == ["fresh"]  # only the task with cache: false ran again
    a = {t["name"]: t for t in first["tasks"]}
    b = {t["name"]: t for t in second["tasks"]}
    for name in ("source", "scale", "total", "side"):
        assert b[name]["reused"] and b[name]["status"] == "COMPLETED"
        assert b[name]["output"] == a[name]["output"]  # the same outputs
        assert "cached" in b[name]["message"]
    assert not b["fresh"]["reused"]
    out = json.loads(osmo("artifacts", "list", second["id"], "total", "--format", "json").out)
    assert (Path(out[0]["path"]) / "t.txt").read_text().strip() == "30"
    assert "COMPLETED (cached)" in osmo("query", second["id"]).out


def test_a_changed_parameter_reruns_exactly_the_affected_tasks(osmo: Osmo,
                                                               tmp_path: Path) -> None:
    spec = _spec(tmp_path)
    _submit(osmo, spec)
    _runs(tmp_path)
    changed = _submit(osmo, spec, "--set", "scale=3")
    assert _runs(tmp_path) == ["fresh", "scale", "total"]  # source and side reused
    total = {t["name"]: t for t in changed["tasks"]}["total"]
    assert (Path(total["output"]) / "t.txt").read_text().strip() == "45"
    # A change that does not alter scale's output: scale reruns, total is reused
    # because its input's content is identical.
    _submit(osmo, spec, "--set", "scale=3", "--set", "note=bye")
    assert _runs(tmp_path) == ["fresh", "scale"]


def test_no_cache_runs_everything(osmo: Osmo, tmp_path: Path) -> None:
    spec = _spec(tmp_path)
    _submit(osmo, spec)
    _runs(tmp_path)
    again = _submit(osmo, spec, "--no-cache")
    assert _runs(tmp_path) == ["fresh", "scale", "side", "source", "total"]
    assert not any(t["reused"] for t in again["tasks"])


def test_tasks_behind_a_group_barrier_are_not_cached(osmo: Osmo, tmp_path: Path) -> None:
    log = tmp_path / "runs.log"
    # The group ends when its lead does, possibly before the peer's command ran: the lead
    # waits (up to 10 s) until this run's peer has written its line.
    wait_for_peer = (f"echo lead >> {log}; for i in $(seq 200); do "
                     f"[ $(grep -c peer {log}) -ge $(grep -c lead {log}) ] && break; "
                     "sleep 0.05; done")
    spec = write(tmp_path / "g.yaml", f"""
workflow:
  name: gang
  groups:
  - name: pair
    tasks:
    - {{name: lead, lead: true, command: [sh, -c, "{wait_for_peer}"]}}
    - {{name: peer, command: [sh, -c, "echo peer >> {log}"]}}
""")
    _submit(osmo, spec)
    _submit(osmo, spec)
    assert sorted(log.read_text().split()) == ["lead", "lead", "peer", "peer"]
