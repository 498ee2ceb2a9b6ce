"""``sim.eval``'s report: the leaderboard's ranking and its success-rate intervals."""

from __future__ import annotations

from osmo_plugins.sim.eval import EVAL
from osmo_plugins.sim.report import LEADERBOARD, leaderboard_rows, wilson95

from osmo.tasktypes.reports import Report


def test_sim_eval_declares_its_leaderboard() -> None:
    assert EVAL.report is LEADERBOARD and isinstance(LEADERBOARD, Report)
    assert LEADERBOARD.file == "metrics.json"
    assert LEADERBOARD.problem({"suite": {}, "results": []}) is None
    assert LEADERBOARD.problem({"results": []}) == "no suite/results"


def test_rows_rank_per_env() -> None:
    sources = [("wf-1", "eval", {"results": [
        {"policy": "random", "kind": "random", "env": "A", "episodes": 2, "success_rate": 0.0,
         "mean_return": 5.0, "return_ci95": [4, 6], "mean_length": 5},
        {"policy": "train", "kind": "checkpoint", "env": "A", "episodes": 2,
         "success_rate": 1.0, "mean_return": 90.0, "return_ci95": [80, 100], "mean_length": 90},
        {"policy": "random", "kind": "random", "env": "B", "episodes": 2, "success_rate": 0.0,
         "mean_return": 1.0, "return_ci95": [0, 2], "mean_length": 1}]})]
    rows = leaderboard_rows(sources)
    assert [(r["env"], r["rank"], r["policy"]) for r in rows] == [
        ("A", 1, "train"), ("A", 2, "random"), ("B", 1, "random")]


def test_success_rates_carry_a_wilson_interval() -> None:
    lo, hi = wilson95(20, 20)
    assert (round(100 * lo), hi) == (84, 1.0)  # 20 of 20 does not prove 100%
    lo, hi = wilson95(0, 20)
    assert (lo, round(100 * hi)) == (0.0, 16)
    lo, hi = wilson95(99, 100)
    assert (round(100 * lo, 1), round(100 * hi, 1)) == (94.6, 99.8)
    assert wilson95(0, 0) is None
