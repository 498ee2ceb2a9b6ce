"""sim.eval: metrics over fixed seeds, eval MCAP and .rrd; the confidence interval."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("numpy")
pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from osmo_plugins.episodes import read_episodes  # noqa: E402
from osmo_plugins.sim._eval import ci95  # noqa: E402
from osmo_plugins.sim.eval import EVAL  # noqa: E402

from tests.plugins.fakectx import make_ctx  # noqa: E402


def test_ci95() -> None:
    assert ci95([5.0]) == (5.0, 5.0)
    lo, hi = ci95([1.0, 2.0, 3.0])  # mean 2, sd 1, t(2) = 4.303
    assert lo == pytest.approx(2 - 4.303 / 3**0.5) and hi == pytest.approx(2 + 4.303 / 3**0.5)


def test_baselines_on_two_envs(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", envs=["InvertedPendulum-v5", "Hopper-v5"],
                   policies=["expert", "random"], episodes=3, max_steps=100, rrd=False)
    EVAL.run(ctx)
    metrics = json.loads((ctx.output / "metrics.json").read_text())
    rows = {(r["policy"], r["env"]): r for r in metrics["results"]}
    assert set(rows) == {("expert", "InvertedPendulum-v5"), ("random", "InvertedPendulum-v5"),
                         ("random", "Hopper-v5")}  # no expert for Hopper: skipped
    assert rows["expert", "InvertedPendulum-v5"]["success_rate"] == 1.0
    assert rows["expert", "InvertedPendulum-v5"]["mean_return"] == 100.0
    assert rows["random", "InvertedPendulum-v5"]["success_rate"] == 0.0
    assert metrics["suite"]["seeds"] == [10_000, 10_001, 10_002]
    for row in rows.values():
        lo, hi = row["return_ci95"]
        assert lo <= row["mean_return"] <= hi and row["episodes"] == 3
    episodes = list(read_episodes(ctx.output / "rollouts/random--Hopper-v5.mcap"))
    assert [e.seed for e in episodes] == [10_000, 10_001, 10_002]


def test_checkpoint_without_one_in_the_inputs(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", episodes=1)
    with pytest.raises(ValueError, match="no input holds osmo_policy.json"):
        EVAL.run(ctx)


def test_rrd_is_written(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    ctx = make_ctx(EVAL, tmp_path, "eval", policies=["random"], episodes=2, max_steps=20)
    EVAL.run(ctx)
    assert (ctx.output / "eval.rrd").stat().st_size > 1000
