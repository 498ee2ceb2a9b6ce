"""osmo/ReacherVision-v0: the target is in the pixels only, the expert reaches it, random
does not; the IK expert also solves gymnasium's own Reacher-v5."""

from __future__ import annotations

import pytest

np = pytest.importorskip("numpy")
pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from osmo_plugins.sim.envs import make_env, run_episodes  # noqa: E402
from osmo_plugins.sim.policies import has_expert, make_policy  # noqa: E402
from osmo_plugins.sim.reacher import ENV_ID  # noqa: E402


def _red_centre(frame: np.ndarray) -> np.ndarray:
    """Mean (row, column) of the red target's pixels (lit: about (170, 55, 55))."""
    rgb = frame.astype(int)
    red = rgb[..., 0] - (rgb[..., 1] + rgb[..., 2]) / 2 > 60
    assert red.sum() >= 4, "the target is not visible"
    return np.argwhere(red).mean(axis=0)


def test_the_target_is_in_the_pixels_only() -> None:
    env = make_env(ENV_ID, render=True, size=64)
    base = env.unwrapped
    assert env.observation_space.shape == (6,)
    seen = []
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        target = base.data.qpos[2:4].copy()
        # the same arm state with the target elsewhere gives the same observation
        qpos = base.data.qpos.copy()
        qpos[2:4] = -target
        base.set_state(qpos, base.data.qvel.copy())
        assert np.array_equal(base._get_obs(), obs)
        qpos[2:4] = target
        base.set_state(qpos, base.data.qvel.copy())
        row, col = _red_centre(env.render())
        seen.append((target, row, col))
    # seen from above: the target's x runs along the image's columns, y up its rows
    xs, cols = [t[0] for t, _, _ in seen], [c for _, _, c in seen]
    ys, rows = [t[1] for t, _, _ in seen], [r for _, r, _ in seen]
    assert np.corrcoef(xs, cols)[0, 1] > 0.95 and np.corrcoef(ys, rows)[0, 1] < -0.95


def test_the_expert_reaches_and_random_does_not() -> None:
    env = make_env(ENV_ID)
    assert has_expert(ENV_ID)
    expert = run_episodes(env, make_policy("expert", env, env_id=ENV_ID), range(100, 110))
    rand = run_episodes(env, make_policy("random", env, env_id=ENV_ID), range(100, 130))
    assert all(r.success for r in expert) and all(r.length == 50 for r in expert)
    assert sum(bool(r.success) for r in rand) <= 3  # reached and held by chance: rare
    assert {r.signal for r in expert + rand} == {"is_success"}
    assert min(r.total_reward for r in expert) > max(r.total_reward for r in rand)


def test_the_expert_solves_gymnasiums_reacher_too() -> None:
    env = make_env("Reacher-v5")
    policy = make_policy("expert", env, env_id="Reacher-v5")
    results = run_episodes(env, policy, range(5))
    assert np.mean([r.total_reward for r in results]) > -7  # random: about -43
    # the last distance to the target (obs[-2:] is fingertip - target)
    env.reset(seed=7)
    policy.reset(7)
    obs = None
    for _ in range(50):
        obs, *_ = env.step(policy.act(obs))
    assert np.linalg.norm(obs[-2:]) < 0.01
