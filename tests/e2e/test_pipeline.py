"""The robotics pipeline end to end through the real CLI: pendulum-bc and arena-eval, tiny.

These run the plugin task types (``type: sim.rollout`` ...) through osmo's server and
workers, so they need the task-type runner (the plugins-api work) and the extras.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import REPO, Osmo

pytest.importorskip("gymnasium")
pytest.importorskip("rerun")

TINY = ["--set", "shards=2", "--set", "episodes=2", "--set", "max_steps=50",
        "--set", "steps=20", "--set", "eval_episodes=2"]


def test_pendulum_bc_tiny(shared_osmo: Osmo, tmp_path: Path) -> None:
    pytest.importorskip("lerobot")
    wf = shared_osmo.submit(REPO / "workflows/pendulum-bc.yaml", "--wait", *TINY)
    info = shared_osmo.query(wf)
    assert info["status"] == "COMPLETED", shared_osmo("logs", wf).out
    assert {t["name"] for t in info["tasks"]} == {
        "rollout-0", "rollout-1", "dataset", "train", "eval"}

    rows = shared_osmo("eval", "report", wf, "--format", "json", check=True).json()
    assert isinstance(rows, list)
    assert {(r["policy"], r["env"]) for r in rows} == {
        ("train", "InvertedPendulum-v5"), ("random", "InvertedPendulum-v5")}
    table = shared_osmo("eval", "report", wf, check=True).out
    assert "train" in table and "random" in table

    out = tmp_path / "eval.rrd"
    shared_osmo("view", f"{wf}:eval:eval.rrd", "--out", str(out), check=True)
    assert out.stat().st_size > 0
    mcap = tmp_path / "rollout.rrd"
    shared_osmo("view", f"{wf}:rollout-0:episodes-shard000.mcap", "--out", str(mcap),
                check=True)
    assert mcap.stat().st_size > 0

    graph = shared_osmo("lineage", f"{wf}:eval:metrics.json", "--format", "json",
                        check=True).json()
    assert "train" in json.dumps(graph) and "dataset" in json.dumps(graph)


def test_arena_eval_tiny(shared_osmo: Osmo) -> None:
    wf = shared_osmo.submit(REPO / "workflows/arena-eval.yaml", "--wait", "--set", "episodes=2",
                            "--set", "max_steps=30")
    assert shared_osmo.query(wf)["status"] == "COMPLETED", shared_osmo("logs", wf).out
    rows = shared_osmo("eval", "report", wf, "--format", "json", check=True).json()
    assert isinstance(rows, list)
    pairs = {(r["policy"], r["env"]) for r in rows}
    assert ("expert", "InvertedDoublePendulum-v5") in pairs
    assert ("random", "Hopper-v5") in pairs and ("expert", "Hopper-v5") not in pairs


@pytest.mark.parametrize("name", ["pendulum-bc", "arena-eval"])
def test_robotics_workflows_validate(shared_osmo: Osmo, name: str) -> None:
    r = shared_osmo("validate", str(REPO / f"workflows/{name}.yaml"))
    assert r.code == 0, r.out + r.err
