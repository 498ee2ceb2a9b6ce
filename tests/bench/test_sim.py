"""bench_sim.py's pieces: the timed twins run the shipped functions, the overhead's ideal.

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
from osmo_plugins.sim.eval import EVAL  # noqa: E402
from osmo_plugins.sim.rollout import ROLLOUT  # noqa: E402

SIM = importlib.util.find_spec("gymnasium") is not None and \
    importlib.util.find_spec("mujoco") is not None


def test_a_twin_declares_what_the_shipped_type_declares() -> None:
    for twin, shipped in ((osmo_bench_timed.rollout, ROLLOUT), (osmo_bench_timed.evaluate, EVAL)):
        assert (twin.name, twin.version, twin.impl, twin.extra) == (
            shipped.name, shipped.version, shipped.impl, shipped.extra)
        assert twin.params == shipped.params and twin.resources == shipped.resources


def test_the_compute_line_is_found_among_the_log_lines() -> None:
    lines = ["shard 1/1: ...", f"{osmo_bench_timed.MARK}1.250000", "done"]
    assert osmo_bench_timed.compute_of(lines) == 1.25
    assert osmo_bench_timed.compute_of(["no mark here"]) is None


@pytest.mark.skipif(not SIM, reason="needs osmo[sim]")
def test_call_runs_the_shipped_rollout_and_times_it(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    seconds = osmo_bench_timed.call("sim.rollout", {"episodes": 1, "max_steps": 5}, [],
                                    str(tmp_path / "out"), "r0")
    assert seconds > 0
    assert (tmp_path / "out" / "episodes-shard000.mcap").stat().st_size > 0
    assert osmo_bench_timed.compute_of(capsys.readouterr().out.splitlines()) == \
        pytest.approx(seconds, abs=1e-5)


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


def test_the_pipeline_spec_names_only_timed_twins() -> None:
    text = bench_sim.pipeline_yaml()
    for shipped in bench_sim.ATTRS:
        assert f"type: {shipped}\n" not in text
    assert text.count(f"type: {bench_sim.MODULE}:") == 4
