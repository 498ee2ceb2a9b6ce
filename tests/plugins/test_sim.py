"""sim.rollout and the policies, run in-process on MuJoCo InvertedPendulum."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

np = pytest.importorskip("numpy")
gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from osmo_plugins.episodes import episode_files, read_episodes  # noqa: E402
from osmo_plugins.sim._rollout import shard_seeds  # noqa: E402
from osmo_plugins.sim.envs import make_env, run_episodes  # noqa: E402
from osmo_plugins.sim.policies import make_policy  # noqa: E402
from osmo_plugins.sim.rollout import ROLLOUT  # noqa: E402

from tests.plugins.fakectx import make_ctx  # noqa: E402


def _episodes(folder: Path) -> list:
    return [e for f in episode_files([folder]) for e in read_episodes(f)]


def test_expert_balances_and_random_falls(tmp_path: Path) -> None:
    expert = make_ctx(ROLLOUT, tmp_path, "expert", episodes=3, max_steps=300, noise=0.3)
    ROLLOUT.run(expert)
    rand = make_ctx(ROLLOUT, tmp_path, "random", policy="random", episodes=3, max_steps=300)
    ROLLOUT.run(rand)
    assert [(e.length, e.terminated) for e in _episodes(expert.output)] == [(300, False)] * 3
    assert all(e.terminated and e.length < 50 for e in _episodes(rand.output))
    summary = json.loads((expert.output / "summary.json").read_text())
    assert summary["meta"]["env"] == "InvertedPendulum-v5"
    assert [e["seed"] for e in summary["episodes"]] == [0, 1, 2]
    assert expert.progress_calls[-1][:2] == (3, 3)


def test_shards_use_disjoint_seeds_and_name_their_files(tmp_path: Path) -> None:
    seen: set[int] = set()
    for shard in range(3):
        ctx = make_ctx(ROLLOUT, tmp_path, f"s{shard}", policy="random", episodes=2, seed=7,
                       shard=shard, shards=3)
        ROLLOUT.run(ctx)
        assert (ctx.output / f"episodes-shard{shard:03d}.mcap").is_file()
        seeds = {e.seed for e in _episodes(ctx.output)}
        assert seeds == set(shard_seeds(7, shard, 2)) and not seeds & seen
        seen |= seeds


def test_same_seed_same_episodes(tmp_path: Path) -> None:
    runs = []
    for n in range(2):
        ctx = make_ctx(ROLLOUT, tmp_path, f"r{n}", episodes=2, max_steps=40, noise=0.5, seed=3)
        ROLLOUT.run(ctx)
        runs.append(_episodes(ctx.output))
    for a, b in zip(*runs, strict=True):
        assert np.array_equal(a.observations, b.observations)
        assert np.array_equal(a.actions, b.actions)


def test_render_records_frames(tmp_path: Path) -> None:
    ctx = make_ctx(ROLLOUT, tmp_path, "render", episodes=1, max_steps=5, render=True, size=32)
    ROLLOUT.run(ctx)
    (ep,) = _episodes(ctx.output)
    assert ep.frames is not None and ep.frames.shape == (5, 32, 32, 3)
    assert ep.frames.max() > 0  # not a black image


def test_xml_from_an_input_folder(tmp_path: Path) -> None:
    stock = Path(gym.__file__).parent / "envs/mujoco/assets/inverted_pendulum.xml"
    assets = tmp_path / "assets"
    assets.mkdir()
    # A heavier pole: the expert linearises whatever model it is given and still balances.
    xml = stock.read_text().replace('size="0.049 0.3"', 'size="0.07 0.3"')
    (assets / "pendulum.xml").write_text(xml)
    ctx = make_ctx(ROLLOUT, tmp_path, "xml", inputs=[assets], xml="pendulum.xml", episodes=1,
                   max_steps=200)
    ROLLOUT.run(ctx)
    (ep,) = _episodes(ctx.output)
    assert ep.length == 200 and not ep.terminated


def test_expert_for_the_double_pendulum() -> None:
    env = make_env("InvertedDoublePendulum-v5", max_steps=300)
    (result,) = run_episodes(env, make_policy("expert", env, env_id="InvertedDoublePendulum-v5"),
                             [5])
    assert result.length == 300 and not result.terminated


@pytest.mark.parametrize(("policy", "env_id", "message"), [
    ("expert", "Hopper-v5", "no expert policy"),
    ("checkpoint", "InvertedPendulum-v5", "needs a trained checkpoint"),
    ("nope", "InvertedPendulum-v5", "unknown policy"),
])
def test_policy_errors(policy: str, env_id: str, message: str) -> None:
    env = make_env(env_id)
    with pytest.raises(ValueError, match=message):
        make_policy(policy, env, env_id=env_id)


def test_bad_shard_and_env(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="out of range"):
        ROLLOUT.run(make_ctx(ROLLOUT, tmp_path, "a", shard=2, shards=2))
    with pytest.raises(ValueError, match="cannot make env"):
        ROLLOUT.run(make_ctx(ROLLOUT, tmp_path, "b", env="NoSuchEnv-v0"))
