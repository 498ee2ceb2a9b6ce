"""bench_sim.py's pieces: the shipped types timed as osmo's runner times them, the ideal.

The whole script runs in test_run.py's quick run (osmo side only; Ray is not installed here).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path[:0] = [str(BENCH), str(BENCH / "workloads")]

import bench_sim  # noqa: E402
import osmo_bench_timed  # noqa: E402
from osmo_plugins.lerobot.dataset import DATASET  # noqa: E402
from osmo_plugins.lerobot.train import TRAIN  # noqa: E402
from osmo_plugins.sim.eval import EVAL  # noqa: E402
from osmo_plugins.sim.rollout import ROLLOUT  # noqa: E402

from osmo.spec import load_spec  # noqa: E402
from osmo.tasktypes.runner import TIMING_MARK  # noqa: E402

SIM = importlib.util.find_spec("gymnasium") is not None and \
    importlib.util.find_spec("mujoco") is not None


def test_both_systems_run_the_shipped_types_themselves() -> None:
    assert osmo_bench_timed.TYPES == {"sim.rollout": ROLLOUT, "sim.eval": EVAL,
                                      "lerobot.dataset": DATASET, "lerobot.train": TRAIN}


def test_the_compute_line_is_osmo_s_runners_own() -> None:
    lines = ["shard 1/1: ...", f"{TIMING_MARK}1.250000", "done"]
    assert osmo_bench_timed.compute_of(lines) == 1.25
    assert osmo_bench_timed.compute_of(["no mark here"]) is None


@pytest.mark.skipif(not SIM, reason="needs osmo[sim]")
def test_call_runs_the_shipped_rollout_and_times_it(tmp_path: Path) -> None:
    seconds = osmo_bench_timed.call("sim.rollout", {"episodes": 1, "max_steps": 5}, [],
                                    str(tmp_path / "out"), "r0")
    assert 0 < seconds < 60
    assert (tmp_path / "out" / "episodes-shard000.mcap").stat().st_size > 0


def test_the_ideal_makespan_packs_each_level_on_two_slots() -> None:
    sweep = [{"name": f"t{i}", "inputs": []} for i in range(4)]
    assert bench_sim.ideal(sweep, {"t0": 1, "t1": 1, "t2": 1, "t3": 3}) == 3  # longest task
    assert bench_sim.ideal(sweep, {"t0": 1, "t1": 1, "t2": 1, "t3": 1}) == 2  # Σ ÷ 2
    # a sweep's overhead is makespan × 2 ÷ tasks − the mean compute
    assert bench_sim.overhead(sweep, 3.0, {"t0": 1, "t1": 1, "t2": 1, "t3": 1}) == 0.5
    dag = [{"name": "a", "inputs": []}, {"name": "b", "inputs": []},
           {"name": "c", "inputs": [{"task": "a"}, {"task": "b"}]},
           {"name": "d", "inputs": [{"task": "c"}, {"name": "policy", "path": "/x"}]}]
    assert bench_sim.ideal(dag, {"a": 2, "b": 2, "c": 5, "d": 1}) == 2 + 5 + 1


def test_every_task_of_the_workloads_is_timed_by_osmo_s_runner(tmp_path: Path) -> None:
    specs = {"rollout": (bench_sim.rollout_yaml(3), 3), "eval": (bench_sim.eval_yaml(2, 1), 2),
             "pipeline": (bench_sim.pipeline_yaml(), 10)}
    for name, (text, count) in specs.items():
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        tasks = load_spec(path).all_tasks()
        assert len(tasks) == count, name
        for task in tasks:
            assert task.type in osmo_bench_timed.TYPES, (name, task.name, task.type)
            assert task.environment == {"OSMO_TASK_TIMING": "1"}, (name, task.name)
