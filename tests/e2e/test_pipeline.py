"""The robotics pipeline end to end through the real CLI, tiny: pendulum-bc, arena-eval,
reach-vision (learning from pixels) and the sweep (with its caching).

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

#: a tiny pipeline takes about a minute alone; ample room for a loaded machine, never a hang
WAIT = 480

PENDULUMS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5")

# 100 training steps on 200 frames is the least that reliably balances the pole for 50 steps
# (measured: 20 steps gave a mean return of 14 against random's 9; 100 steps gave 50 of 50).
TINY = ["--set", "shards=2", "--set", "episodes=2", "--set", "max_steps=50",
        "--set", "steps=100", "--set", "eval_episodes=4"]


def _by_policy(rows: list[dict[str, Any]], env: str) -> dict[str, dict[str, Any]]:
    return {r["policy"]: r for r in rows if r["env"] == env}


def test_pendulum_bc_tiny(shared_osmo: Osmo, tmp_path: Path) -> None:
    pytest.importorskip("lerobot")
    wf = shared_osmo.submit(REPO / "workflows/pendulum-bc.yaml", "--wait", *TINY, timeout=WAIT)
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
    from osmo_plugins.episodes import read_episodes

    from osmo.record import McapFile, read_lineage

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
                            "--set", "max_steps=30", timeout=WAIT)
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


def test_reach_vision_tiny(shared_osmo: Osmo, tmp_path: Path) -> None:
    """The vision pipeline's plumbing: 64×64 frames → an image dataset → an ACT policy that
    sees them → evaluated against the expert and random on unseen seeds. Twenty training
    steps teach it nothing; what it learns at full size is measured in bench/ (pipeline row)."""
    pytest.importorskip("lerobot")
    wf = shared_osmo.submit(REPO / "workflows/reach-vision.yaml", "--wait", "--set", "shards=2",
                            "--set", "episodes=2", "--set", "steps=20",
                            "--set", "eval_episodes=2", timeout=WAIT)
    assert shared_osmo.query(wf)["status"] == "COMPLETED", shared_osmo("logs", wf).out
    # a task's log is no terminal: no progress bar of Hugging Face's per episode saved
    # (osmo reports the task's own progress); its own lines are still there
    for task in ("dataset-0", "dataset-1", "train"):
        log = shared_osmo("logs", wf, "--task", task, check=True).out
        assert "%|" not in log and "examples/s" not in log, log
    for task in ("dataset-0", "dataset-1"):  # a dataset per shard, trained on as one
        assert "LeRobotDataset with 2 episodes" in shared_osmo("logs", wf, "--task", task).out
    train = next(t for t in shared_osmo.query(wf)["tasks"] if t["name"] == "train")
    marker = json.loads((Path(train["output"]) / "checkpoint/osmo_policy.json").read_text())
    assert marker["dataset_episodes"] == 4, marker
    rows = shared_osmo("eval", "report", wf, "--format", "json", check=True).json()
    got = _by_policy(rows, "osmo/ReachVision-v1")
    assert set(got) == {"train", "expert", "random"}
    assert {r["criterion"] for r in rows} == {"info['is_success'] (the env's own success signal)"}
    assert got["expert"]["success_rate"] == 1.0 and got["random"]["success_rate"] == 0.0
    assert got["expert"]["mean_return"] > got["random"]["mean_return"]
    assert all(r["mean_length"] == 50 for r in rows)
    shared_osmo("artifacts", "get", f"{wf}:train:checkpoint/osmo_policy.json", "-o",
                str(tmp_path / "ckpt"), check=True)
    (marker,) = (tmp_path / "ckpt").rglob("osmo_policy.json")
    info = json.loads(marker.read_text())
    assert info["images"] and info["image_size"] == 64 and info["obs_dim"] == 6
    shared_osmo("artifacts", "get", f"{wf}:rollout-0:episodes-shard000.mcap", "-o",
                str(tmp_path / "shard"), check=True)
    (shard,) = (tmp_path / "shard").rglob("*.mcap")
    from osmo.record import McapFile

    with McapFile(shard) as f:
        chans = {c.topic: (c.schema_name, c.message_count) for c in f.channels()}
    assert chans == {"/episode/step": ("osmo.EpisodeStep", 50),  # 2 episodes × 25 steps
                     "/camera/rgb": ("foxglove.RawImage", 50)}


SWEEP = ["--set", "lrs=0.003,0.001", "--set", "episodes=2", "--set", "max_steps=50",
         "--set", "steps=10"]


def test_sweep_reruns_only_evaluation_when_only_evaluation_changes(shared_osmo: Osmo) -> None:
    pytest.importorskip("lerobot")
    spec = REPO / "workflows/sweep.yaml"
    first = shared_osmo.submit(spec, "--wait", *SWEEP, "--set", "eval_episodes=2", timeout=WAIT)
    assert shared_osmo.query(first)["status"] == "COMPLETED", shared_osmo("logs", first).out
    trains = {"train-lr0-s0", "train-lr1-s0"}
    second = shared_osmo.submit(spec, "--wait", *SWEEP, "--set", "eval_episodes=3", timeout=WAIT)
    tasks = {t["name"]: t for t in shared_osmo.query(second)["tasks"]}
    assert set(tasks) == {"rollout-0", "rollout-1", "dataset", "eval"} | trains
    for name, task in tasks.items():  # only the evaluation ran again
        assert task["status"] == "COMPLETED" and task["reused"] == (name != "eval"), task
    table = shared_osmo("query", second, check=True).out
    assert sum("cached" in line for line in table.splitlines()) == 5, table

    rows = shared_osmo("eval", "report", second, "--format", "json", check=True).json()
    got = _by_policy(rows, "InvertedPendulum-v5")
    assert set(got) == trains | {"expert", "random"}
    assert all(r["episodes"] == 3 for r in rows)
    ranked = sorted(rows, key=lambda r: r["rank"])
    assert [r["mean_return"] for r in ranked] == sorted(
        (r["mean_return"] for r in rows), reverse=True)
    for r in rows:  # each with its 95% interval
        lo, hi = r["return_ci95"]
        assert lo <= r["mean_return"] <= hi
    best = next(r for r in ranked if r["kind"] == "checkpoint")
    graph = shared_osmo("lineage", f"{second}:{best['policy']}:checkpoint/model.safetensors",
                        "--format", "json", check=True).json()
    text = json.dumps(graph)
    assert all(f'"{name}"' in text for name in ("dataset", "rollout-0", "rollout-1")), text


@pytest.mark.parametrize("name", ["pendulum-bc", "arena-eval", "reach-vision", "sweep"])
def test_robotics_workflows_validate(shared_osmo: Osmo, name: str) -> None:
    r = shared_osmo("validate", str(REPO / f"workflows/{name}.yaml"))
    assert r.code == 0, r.out + r.err
