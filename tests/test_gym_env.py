"""The Gymnasium environment opera_taichi/ZX120Dig-v0 (opera_taichi/envs.py) on coarse soil (12 cm grains).

One environment for the module: its first reset builds the simulation (the settled bed comes from the disk cache),
every test starts with a seeded reset, which puts the settled start back.
"""
import warnings

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402

import opera_taichi  # noqa: E402,F401  (registers the environment)
from opera_taichi.errors import DivergenceError  # noqa: E402

ENV_ID = "opera_taichi/ZX120Dig-v0"
BOOM = 1  # action / joint index of boom_joint (swing, boom, arm, bucket)


@pytest.fixture(scope="module")
def env():
    env = gymnasium.make(ENV_ID)
    yield env
    env.close()


def rollout(env, actions):
    return [env.step(np.asarray(a, np.float32)) for a in actions]


def assert_same_obs(a, b):
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key


def test_registered_and_shaped(env):
    u = env.unwrapped
    assert u.joint_names == ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]
    assert env.action_space.dtype == np.float32
    assert np.allclose(env.action_space.high, [1.2, 0.7, 0.75, 1.1])  # the ZX120 actuators' speed limits
    assert np.array_equal(env.action_space.low, -env.action_space.high)
    assert env.observation_space["heightmap"].shape == (16, 16)
    for key, space in env.observation_space.spaces.items():
        assert space.dtype == np.float32, key
        assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high)), key
    assert u.metadata["render_modes"] == [] and u.render_mode is None


def test_check_env_passes_without_determinism_warnings(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
        check_env(env, skip_render_check=True)
    messages = [str(w.message) for w in caught]
    # allowed: the action space is in rad/s, not normalised to [-1, 1]; the second check is on the wrapped env
    unexpected = [m for m in messages if "normalized space" not in m and "different from the unwrapped" not in m]
    assert unexpected == []  # e.g. "observations are not equal although similar": not bit for bit


def test_seeded_reset_restores_the_start_bit_for_bit(env):
    obs_1, info_1 = env.reset(seed=1)
    steps_1 = rollout(env, [[0.3, 0.5, -0.4, 0.6]] * 3)
    obs_2, info_2 = env.reset(seed=1)
    assert_same_obs(obs_1, obs_2)
    assert info_1 == info_2 and info_2["t"] == 0.0
    steps_2 = rollout(env, [[0.3, 0.5, -0.4, 0.6]] * 3)
    for a, b in zip(steps_1, steps_2):
        assert_same_obs(a[0], b[0])
        assert a[1:] == b[1:]  # reward, terminated, truncated, info
    assert not np.array_equal(steps_1[-1][0]["q"], obs_1["q"])  # it did move in between


def test_random_initial_offsets_follow_the_seed(env):
    opts = {"init_noise": 0.05}
    a, _ = env.reset(seed=7, options=opts)
    b, _ = env.reset(seed=7, options=opts)
    c, _ = env.reset(seed=8, options=opts)
    start, _ = env.reset(seed=7)
    assert_same_obs(a, b)
    assert not np.array_equal(a["q"], c["q"])
    offsets = a["q"] - start["q"]
    assert np.all(np.abs(offsets) <= 0.05 + 1e-6) and np.any(offsets != 0.0)
    # the machine is posed there, not only its observation: the tip moves with it, and a zero action holds it
    assert np.linalg.norm(a["tip"] - start["tip"]) > 0.01
    a, _ = env.reset(seed=7, options=opts)
    after, *_ = env.step(np.zeros(4))
    assert np.all(np.abs(after["q"] - a["q"]) < 1e-3) and np.linalg.norm(after["tip"] - a["tip"]) < 0.01


def test_zero_action_holds_the_bucket_in_the_air_with_no_soil_wrench(env):
    obs0, _ = env.reset(seed=0)
    # the premise: at the start the cutting edge is well above the terrain under it
    assert obs0["tip"][2] > obs0["heightmap"].max() + 0.5
    assert np.array_equal(obs0["bucket_wrench"], np.zeros(6, np.float32))
    for obs, reward, terminated, truncated, info in rollout(env, np.zeros((10, 4))):  # 0.5 s
        assert not terminated and not truncated
        assert np.array_equal(obs["bucket_wrench"], np.zeros(6, np.float32))
        assert obs["bucket_mass"][0] == 0.0
        assert np.all(np.abs(obs["q"] - obs0["q"]) < 1e-3)   # rad
        assert np.all(np.abs(obs["qd"]) < 1e-2)              # rad/s
        # default reward: no load gained, minus the (small, non-negative) price of the work done
        assert info["energy"] >= 0.0
        assert reward == pytest.approx(-env.unwrapped.energy_coef * info["energy"], abs=1e-12)


def test_boom_speed_action_moves_the_boom_up_to_its_speed_limit(env):
    obs0, _ = env.reset(seed=0)
    limit = float(env.action_space.high[BOOM])
    action = np.zeros(4, np.float32)
    action[BOOM] = limit
    prev, t_prev = obs0, 0.0
    for obs, _, terminated, _, info in rollout(env, [action] * 6):  # 0.3 s: lowers the boom, the bucket stays up
        assert not terminated
        dq = float(obs["q"][BOOM] - prev["q"][BOOM])
        assert 0.0 < dq <= limit * (info["t"] - t_prev) * 1.001
        assert obs["qd"][BOOM] <= limit * 1.001
        others = [0, 2, 3]
        assert np.all(np.abs(obs["q"][others] - obs0["q"][others]) < 2e-3)
        prev, t_prev = obs, info["t"]
    assert prev["q"][BOOM] - obs0["q"][BOOM] > 0.8 * limit * 0.3  # it got up to speed
    assert prev["tip"][2] < obs0["tip"][2] - 0.3  # a positive boom speed lowers the cutting edge
    assert info["energy"] > 0.0


def test_reward_fn_is_pluggable(env):
    u = env.unwrapped
    calls = []

    def reward_fn(e, prev_obs, obs, action):
        calls.append((prev_obs["q"].copy(), obs["q"].copy(), np.array(action)))
        return 42.0

    default = u.reward_fn
    u.reward_fn = reward_fn
    try:
        obs0, _ = env.reset(seed=0)
        obs1, r1, *_ = env.step(np.array([0, 0.5, 0, 0], np.float32))
        obs2, r2, *_ = env.step(np.array([0, 0.5, 0, 0], np.float32))
    finally:
        u.reward_fn = default
    assert r1 == r2 == 42.0
    assert np.array_equal(calls[0][0], obs0["q"]) and np.array_equal(calls[0][1], obs1["q"])
    assert np.array_equal(calls[1][0], obs1["q"]) and np.array_equal(calls[1][1], obs2["q"])
    assert calls[0][2][BOOM] == pytest.approx(0.5)


def test_divergence_terminates_and_reset_recovers(env, monkeypatch):
    u = env.unwrapped
    obs0, _ = env.reset(seed=0)
    env.step(np.zeros(4, np.float32))

    def diverge(control=None):
        raise DivergenceError("soil particle speed 1e9 m/s beyond the limit")

    monkeypatch.setattr(u.sim, "step", diverge)
    obs, reward, terminated, truncated, info = env.step(np.zeros(4, np.float32))
    assert terminated and not truncated and "beyond the limit" in info["diverged"]
    assert env.observation_space.contains(obs)
    with pytest.raises(RuntimeError, match="reset"):
        u.step(np.zeros(4, np.float32))
    monkeypatch.undo()
    again, _ = env.reset(seed=0)
    assert_same_obs(again, obs0)
    assert env.step(np.zeros(4, np.float32))[2] is False


def test_truncated_at_max_episode_seconds():
    env = gymnasium.make(ENV_ID, control_period=0.02, max_episode_seconds=0.1)
    try:
        env.reset(seed=0)
        flags = [env.step(np.zeros(4, np.float32))[3] for _ in range(5)]
        assert flags == [False, False, False, False, True]
        assert env.unwrapped.sim.t == pytest.approx(0.1)
        with pytest.raises(RuntimeError, match="truncated at max_episode_seconds = 0.1 s; call reset"):
            env.step(np.zeros(4, np.float32))  # the episode is over: no step beyond it
        env.reset(seed=0)
        assert env.step(np.zeros(4, np.float32))[3] is False
    finally:
        env.close()


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="control_period"):
        opera_taichi.ZX120DigEnv(control_period=0.0015)
    with pytest.raises(ValueError, match="render"):
        opera_taichi.ZX120DigEnv(render_mode="human")
    with pytest.raises(ValueError, match="max_episode_seconds: expected at least one control period"):
        opera_taichi.ZX120DigEnv(max_episode_seconds=-1)
    with pytest.raises(ValueError, match="patch_cells, patch_cell"):
        opera_taichi.ZX120DigEnv(patch_cells=0)
    for kw, words in [({"control_period": float("nan")}, "control_period: expected a finite number"),
                      ({"max_episode_seconds": float("inf")}, "max_episode_seconds: expected a finite number"),
                      ({"init_noise": -1.0}, "init_noise: expected a finite number >= 0"),
                      ({"reward_fn": 3}, "reward_fn: expected a function"),
                      ({"machine": "nope"}, "machine: no machine 'nope'")]:
        with pytest.raises(ValueError, match=words):
            opera_taichi.ZX120DigEnv(**kw)


def test_bad_reset_options_and_actions_are_refused_in_one_line(env):
    """A reset noise beyond what the swing's observation bound was sized for would show the agent a clipped swing."""
    for noise in (40.0, -0.1, float("nan"), "abc"):
        with pytest.raises(ValueError, match="reset options: init_noise: expected a number from 0 to 1 rad"):
            env.reset(seed=0, options={"init_noise": noise})
    env.reset(seed=0)
    for action in (["a", "b", "c", "d"], {"boom_joint": 0.1}):
        with pytest.raises(ValueError, match="action: expected 4 finite joint velocities"):
            env.step(action)


def test_an_action_of_another_shape_is_refused(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action: expected 4 finite joint velocities"):
        env.step(np.zeros((1, 4)))
