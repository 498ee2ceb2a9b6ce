"""The robotics pipeline end to end through the real CLI: pendulum-bc and arena-eval, tiny.

These run the plugin task types (``type: sim.rollout`` ...) through osmo's server and
workers, so they need the task-type runner (the plugins-api work) and the extras.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO, Osmo

pytest.importorskip("gymnasium")
pytest.importorskip("rerun")

PENDULUMS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5")

# 100 training steps on 200 frames is the least that reliably balances the pole for 50 steps
# (measured: 20 steps gave a mean return of 14 against random's 9; 100 steps gave 50 of 50).
TINY = ["--set", "shards=2", "--set", "episodes=2", "--set", "max_steps=50",
        "--set", "steps=100", "--set", "eval_episodes=4"]


def _by_policy(rows: list[dict[str, Any]], env: str) -> dict[str, dict[str, Any]]:
    return {r["policy"]: r for r in rows if r["env"] == env}


def test_pendulum_bc_tiny(shared_osmo: Osmo, tmp_path: Path) -> None:
    pytest.importorskip("lerobot")
    wf = shared_osmo.submit(REPO / "workflows/pendulum-bc.yaml", "--wait", *TINY)
    info = shared_osmo.query(wf)
    assert info["status"] == "COMPLETED", shared_osmo("logs", wf).out
    assert {t["name"] for t in info["tasks"]} == {
        "rollout-0", "rollout-1", "dataset", "train", "eval"}

    rows = shared_osmo("eval", "report", wf, "--format", "json", check=True).json()
    got = _by_policy(rows, "InvertedPendulum-v5")
    assert set(got) == {"train", "expert", "random"} and len(rows) == 3
    train, expert, rand = got["train"], got["expert"], got["random"]
    # The trained policy beats random beyond its confidence interval, and balances the pole
    # (return >= 0.95 x 50 steps) at least as often as 3 of 4 evaluation episodes.
    assert train["mean_return"] > rand["return_ci95"][1], rows
    assert train["success_rate"] >= 0.75 and rand["success_rate"] == 0.0, rows
    assert expert["success_rate"] == 1.0 and expert["normalized_score"] == 1.0
    assert train["normalized_score"] >= 0.75, rows
    assert {r["criterion"] for r in rows} == {"return >= 47.5 (workflow params)"}
    table = shared_osmo("eval", "report", wf, check=True).out
    assert "train" in table and "random" in table and "[1] return >= 47.5" in table

    out = tmp_path / "eval.rrd"
    shared_osmo("view", f"{wf}:eval:eval.rrd", "--out", str(out), check=True)
    assert out.stat().st_size > 0
    mcap = tmp_path / "rollout.rrd"
    shared_osmo("view", f"{wf}:rollout-0:episodes-shard000.mcap", "--out", str(mcap),
                check=True)
    assert mcap.stat().st_size > 0
    _check_shard(shared_osmo, wf, tmp_path)

    graph = shared_osmo("lineage", f"{wf}:eval:metrics.json", "--format", "json",
                        check=True).json()
    assert "train" in json.dumps(graph) and "dataset" in json.dumps(graph)


def _check_shard(osmo: Osmo, wf: str, tmp: Path) -> None:
    """A rollout shard as a task wrote it: Foxglove-native, with the attempt's lineage."""
    from osmo.record import McapFile, read_lineage
    from osmo_plugins.episodes import read_episodes

    osmo("artifacts", "get", f"{wf}:rollout-1:episodes-shard001.mcap", "-o", str(tmp / "s"),
         check=True)
    (path,) = (tmp / "s").rglob("*.mcap")
    with McapFile(path) as f:
        chans = {c.topic: (c.message_encoding, c.schema_name, c.message_count)
                 for c in f.channels()}
    assert chans == {"/episode/step": ("protobuf", "osmo.EpisodeStep", 100)}  # 2 × 50 steps
    lineage = read_lineage(path)
    assert lineage is not None and (lineage.workflow_id, lineage.task) == (wf, "rollout-1")
    assert lineage.plugin == "sim.rollout@2" and lineage.params["shard"] == 1
    assert [e.seed for e in read_episodes(path)] == [2, 3]


def test_arena_eval_tiny(shared_osmo: Osmo) -> None:
    wf = shared_osmo.submit(REPO / "workflows/arena-eval.yaml", "--wait", "--set", "episodes=2",
                            "--set", "max_steps=30")
    assert shared_osmo.query(wf)["status"] == "COMPLETED", shared_osmo("logs", wf).out
    rows = shared_osmo("eval", "report", wf, "--format", "json", check=True).json()
    pairs = {(r["policy"], r["env"]) for r in rows}
    assert pairs == {(p, e) for p in ("expert", "random") for e in PENDULUMS} | {
        ("random", "Hopper-v5"), ("random", "HalfCheetah-v5")}  # no expert for those two
    for env in PENDULUMS:  # the expert beats random wherever both ran
        got = _by_policy(rows, env)
        assert got["expert"]["mean_return"] > got["random"]["mean_return"], rows
        assert (got["expert"]["success_rate"], got["random"]["success_rate"]) == (1.0, 0.0)
        assert (got["expert"]["normalized_score"], got["random"]["normalized_score"]) == (1, 0)
    for env in ("Hopper-v5", "HalfCheetah-v5"):  # no criterion at 30 steps: no rate at all
        (row,) = _by_policy(rows, env).values()
        assert row["success_rate"] is None and row["criterion"].startswith("n/a"), row
    table = shared_osmo("eval", "report", wf, check=True).out
    cheetah = next(line for line in table.splitlines() if line.startswith("HalfCheetah"))
    assert "n/a [" in cheetah and "%" not in cheetah


@pytest.mark.parametrize("name", ["pendulum-bc", "arena-eval"])
def test_robotics_workflows_validate(shared_osmo: Osmo, name: str) -> None:
    r = shared_osmo("validate", str(REPO / f"workflows/{name}.yaml"))
    assert r.code == 0, r.out + r.err
