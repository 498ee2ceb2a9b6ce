"""sim.eval: metrics over fixed seeds, eval MCAP and .rrd; success defined per env (issue 20)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

np = pytest.importorskip("numpy")
gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from osmo_plugins.episodes import read_episodes  # noqa: E402
from osmo_plugins.sim.envs import EpisodeResult  # noqa: E402
from osmo_plugins.sim.eval import EVAL  # noqa: E402
from osmo_plugins.sim.metrics import add_normalized, ci95, parse_success  # noqa: E402

from tests.plugins.fakectx import make_ctx  # noqa: E402

SIGNAL_ENV = "OsmoTest/Signal-v0"


class SignalEnv(gym.Env):  # type: ignore[misc]
    """Reward 1 per step for 20 steps; ``info[key]`` turns true at step 3 on even seeds only.

    A return threshold would call every episode a success; the env's own signal says half.
    """

    def __init__(self, key: str = "is_success") -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.key, self.win, self.t = key, False, 0

    def reset(self, *, seed: int | None = None, options: Any = None) -> Any:
        super().reset(seed=seed)
        self.win, self.t = (seed or 0) % 2 == 0, 0
        return np.zeros(2, np.float32), {}

    def step(self, action: Any) -> Any:
        self.t += 1
        return (np.zeros(2, np.float32), 1.0, False, False,
                {self.key: self.win and self.t >= 3})


gym.register(id=SIGNAL_ENV, entry_point=SignalEnv, max_episode_steps=20, reward_threshold=0.5)
gym.register(id="OsmoTest/SignalOld-v0", entry_point=SignalEnv, max_episode_steps=20,
             kwargs={"key": "success"})


def _metrics(ctx: Any) -> dict[str, Any]:
    EVAL.run(ctx)
    return json.loads((ctx.output / "metrics.json").read_text())


def _rows(metrics: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    return {(r["policy"], r["env"]): r for r in metrics["results"]}


def test_ci95() -> None:
    assert ci95([5.0]) == (5.0, 5.0)
    lo, hi = ci95([1.0, 2.0, 3.0])  # mean 2, sd 1, t(2) = 4.303
    assert lo == pytest.approx(2 - 4.303 / 3**0.5) and hi == pytest.approx(2 + 4.303 / 3**0.5)


def test_baselines_on_two_envs(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", envs=["InvertedPendulum-v5", "Hopper-v5"],
                   policies=["expert", "random"], episodes=3, max_steps=100, rrd=False,
                   success={"InvertedPendulum-v5": {"return_at_least": 100}})
    metrics = _metrics(ctx)
    rows = _rows(metrics)
    assert set(rows) == {("expert", "InvertedPendulum-v5"), ("random", "InvertedPendulum-v5"),
                         ("random", "Hopper-v5")}  # no expert for Hopper: skipped
    expert, rand = rows["expert", "InvertedPendulum-v5"], rows["random", "InvertedPendulum-v5"]
    assert (expert["success_rate"], expert["mean_return"]) == (1.0, 100.0)
    assert rand["success_rate"] == 0.0
    assert expert["success_criterion"] == "return >= 100 (workflow params[InvertedPendulum-v5])"
    assert (expert["normalized_score"], rand["normalized_score"]) == (1.0, 0.0)
    assert rows["random", "Hopper-v5"]["normalized_score"] is None  # no expert ran there
    assert metrics["suite"]["seeds"] == [10_000, 10_001, 10_002]
    assert metrics["suite"]["success"]["Hopper-v5"]["kind"] == "none"
    for row in rows.values():
        lo, hi = row["return_ci95"]
        assert lo <= row["mean_return"] <= hi and row["episodes"] == 3
    episodes = list(read_episodes(ctx.output / "rollouts/random--Hopper-v5.mcap"))
    assert [e.seed for e in episodes] == [10_000, 10_001, 10_002]


def test_random_never_gets_a_success_rate_without_a_criterion(tmp_path: Path) -> None:
    """HalfCheetah never terminates: "did not terminate" would call random 100% successful."""
    short = _metrics(make_ctx(EVAL, tmp_path, "short", envs=["HalfCheetah-v5", "Hopper-v5"],
                              policies=["random"], episodes=2, max_steps=50, record=False))
    for row in short["results"]:
        assert row["success_rate"] is None, row
        assert row["success_criterion"].startswith("n/a: no success signal")
        assert "is for 1000-step episodes; this suite runs 50" in row["success_criterion"]
    # At gymnasium's own episode length its reward_threshold applies, and random fails it.
    full = _metrics(make_ctx(EVAL, tmp_path, "full", envs=["HalfCheetah-v5"],
                             policies=["random"], episodes=2, max_steps=1000, record=False))
    (row,) = full["results"]
    assert row["success_rate"] == 0.0 and row["mean_length"] == 1000
    assert row["success_criterion"] == "return >= 4800 (gymnasium reward_threshold)"


def test_threshold_from_params_is_honoured(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", envs=["InvertedPendulum-v5", SIGNAL_ENV],
                   policies=["random"], episodes=4, max_steps=20, record=False,
                   success={"return_at_least": 6})
    rows = _rows(_metrics(ctx))
    row = rows["random", "InvertedPendulum-v5"]
    returns = row["returns"]
    assert 0 < sum(r >= 6 for r in returns) < len(returns), returns  # the threshold splits
    assert row["success_rate"] == sum(r >= 6 for r in returns) / len(returns)
    assert row["success_criterion"] == "return >= 6 (workflow params)"


def test_per_env_threshold_beats_the_default_and_gymnasium(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", envs=["InvertedPendulum-v5"], policies=["expert"],
                   episodes=2, max_steps=1000, record=False,
                   success={"return_at_least": 1, "InvertedPendulum-v5": {"return_at_least": 2000}})
    (row,) = _metrics(ctx)["results"]
    assert row["mean_return"] == 1000.0 and row["success_rate"] == 0.0


@pytest.mark.parametrize(("env_id", "key"), [(SIGNAL_ENV, "is_success"),
                                             ("OsmoTest/SignalOld-v0", "success")])
def test_the_envs_own_success_signal_wins(tmp_path: Path, env_id: str, key: str) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", envs=[env_id], policies=["random"], episodes=4,
                   max_steps=20, record=False, success={"return_at_least": 1})
    metrics = _metrics(ctx)
    (row,) = metrics["results"]
    assert row["mean_return"] == 20.0  # every episode clears the return thresholds ...
    assert row["success_rate"] == 0.5  # ... but the env says only even seeds succeeded
    assert metrics["suite"]["success"][env_id]["key"] == key
    assert row["success_criterion"] == f"info[{key!r}] (the env's own success signal)"


@pytest.mark.parametrize(("value", "message"), [
    ({"return_at_last": 3}, "unknown key 'return_at_last'"),
    ({"return_at_least": "high"}, "must be a number"),
    ({"InvertedPendulum-v5": 5}, "must be {return_at_least: NUMBER}"),
    ({"InvertedPendulum-v5": {"return_at_least": True}}, "must be a number"),
])
def test_bad_success_params(tmp_path: Path, value: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("{", r"\{").replace("}", r"\}")):
        parse_success(value, ["InvertedPendulum-v5"])
    with pytest.raises(ValueError, match="success"):  # before any episode runs
        EVAL.run(make_ctx(EVAL, tmp_path, "eval", policies=["random"], success=value))


def test_normalized_score() -> None:
    def row(kind: str, env: str, ret: float) -> dict[str, Any]:
        return {"kind": kind, "env": env, "mean_return": ret, "return_ci95": [ret - 1, ret + 1],
                "normalized_score": None, "normalized_ci95": None}

    rows = [row("random", "A", 10), row("expert", "A", 110), row("checkpoint", "A", 90),
            row("random", "B", 5), row("checkpoint", "B", 7), row("random", "C", 3),
            row("expert", "C", 3)]
    add_normalized(rows)
    assert [r["normalized_score"] for r in rows] == [0.0, 1.0, 0.8, None, None, None, None]
    assert rows[2]["normalized_ci95"] == pytest.approx([0.79, 0.81])


def test_success_of_an_episode_result_is_optional() -> None:
    assert EpisodeResult(1, 2.0, 3, False, True).success is None


def test_checkpoint_without_one_in_the_inputs(tmp_path: Path) -> None:
    ctx = make_ctx(EVAL, tmp_path, "eval", episodes=1)
    with pytest.raises(ValueError, match="no input holds osmo_policy.json"):
        EVAL.run(ctx)


def test_rrd_is_written(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    ctx = make_ctx(EVAL, tmp_path, "eval", policies=["random"], episodes=2, max_steps=20)
    EVAL.run(ctx)
    assert (ctx.output / "eval.rrd").stat().st_size > 1000
