"""osmo/ReachVision-v1: the target is in the pixels only, the position actuators reach the
commanded angles, the expert reaches every target and random does not; the torque expert
solves gymnasium's own Reacher-v5."""

from __future__ import annotations

import pytest

np = pytest.importorskip("numpy")
pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from osmo_plugins.sim.envs import make_env, run_episodes  # noqa: E402
from osmo_plugins.sim.policies import has_expert, make_policy  # noqa: E402
from osmo_plugins.sim.reach_vision import ENV_ID  # noqa: E402


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


def test_targets_cover_the_three_quarters_in_front_of_the_arm() -> None:
    env = make_env(ENV_ID)
    base = env.unwrapped
    radii, angles = [], []
    for seed in range(300):
        env.reset(seed=seed)
        x, y = base.data.qpos[2:4]
        radii.append(np.hypot(x, y))
        angles.append(np.arctan2(y, x))
    assert 0.05 <= min(radii) and max(radii) <= 0.2 and max(np.abs(angles)) <= 0.75 * np.pi
    assert min(radii) < 0.07 and max(radii) > 0.19  # and all of it
    assert min(angles) < -0.7 * np.pi and max(angles) > 0.7 * np.pi


def test_the_position_actuators_reach_the_commanded_angles() -> None:
    env = make_env(ENV_ID)
    base = env.unwrapped
    low, high = base.model.actuator_ctrlrange.T
    for seed, action in enumerate([(-1.0, -1.0), (1.0, 1.0), (0.3, -0.6), (-0.8, 0.2)]):
        env.reset(seed=seed)
        angles = base.to_ctrl(action)
        assert np.allclose(angles, low + (np.array(action) + 1) / 2 * (high - low))
        assert np.allclose(base.to_action(angles), action, atol=1e-6)
        for _ in range(30):  # 0.6 s: from straight to either end of the range
            env.step(np.array(action, dtype=np.float32))
        assert np.abs(base.data.qpos[:2] - angles).max() < 0.01, (action, base.data.qpos[:2])
        assert np.abs(base.data.qvel[:2]).max() < 0.2  # and all but still
    env.step(np.array([5.0, -5.0]))  # out of range: clipped to the range, not beyond
    assert np.allclose(base.data.ctrl, [high[0], low[1]])


def test_the_expert_reaches_and_random_does_not() -> None:
    env = make_env(ENV_ID)
    assert has_expert(ENV_ID)
    expert = run_episodes(env, make_policy("expert", env, env_id=ENV_ID), range(100, 140))
    rand = run_episodes(env, make_policy("random", env, env_id=ENV_ID), range(100, 140))
    assert all(r.success for r in expert) and all(r.length == 50 for r in expert)
    assert sum(bool(r.success) for r in rand) <= 3  # reached and held by chance: rare
    assert {r.signal for r in expert + rand} == {"is_success"}
    # the reward is minus the distance: random flails about the middle of the arena
    returns = {name: np.mean([r.total_reward for r in rs])
               for name, rs in (("expert", expert), ("random", rand))}
    assert returns["expert"] > 0.5 * returns["random"], returns


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
