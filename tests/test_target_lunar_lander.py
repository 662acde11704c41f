"""TargetLunarLander: the moved pad, its rewards and termination, and target_heuristic."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs import GymEnv, GymWrapper
from torchrl.envs.utils import check_env_specs

import dcsc_torchrl.envs  # noqa: F401  (registers the ids)
from dcsc_torchrl.envs.target_lunar_lander import (
    MAX_PARTICLES,
    PAD_CHUNKS,
    TargetLunarLander,
    pad_x_of_chunk,
    target_heuristic,
)

ENV_ID = "dcsc/TargetLunarLander-v0"
FLAG_YELLOW = np.array([204, 204, 0])


def _episode(env: gym.Env, seed: int, policy) -> tuple[dict, list[float], np.ndarray]:
    obs, _ = env.reset(seed=seed)
    rewards = []
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        rewards.append(reward)
        if terminated or truncated:
            return info, rewards, obs


def _shaping(obs: np.ndarray) -> float:
    x, y, vx, vy, angle, _, leg_l, leg_r, pad_x = obs.astype(float)
    return (
        -100 * math.hypot(x - pad_x, y)
        - 100 * math.hypot(vx, vy)
        - 100 * abs(angle)
        + 10 * leg_l
        + 10 * leg_r
    )


def test_registered_id_passes_gymnasium_check_env():
    env = gym.make(ENV_ID)
    check_env(env.unwrapped)
    assert env.spec.max_episode_steps == 1000


def test_torchrl_gym_env_passes_check_env_specs_and_reads_episode_flags():
    env = GymEnv(ENV_ID)
    env.auto_register_info_dict()
    check_env_specs(env)
    rollout = env.rollout(5)
    assert rollout["next", "success"].dtype == torch.bool
    assert {"crashed", "landed_outside"} <= set(rollout["next"].keys())


def test_gymnasium_vector_env_steps_a_batch_under_torchrl():
    vector = gym.make_vec(
        ENV_ID,
        num_envs=3,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.DISABLED},
    )
    env = GymWrapper(vector)
    check_env_specs(env)
    rollout = env.rollout(120, break_when_any_done=False)
    assert rollout["next", "observation"].shape == (3, 120, 9)


def test_observation_appends_pad_x_and_space_bounds_it():
    env = TargetLunarLander()
    obs, info = env.reset(seed=3)
    assert obs.shape == (9,) and obs.dtype == np.float32
    assert obs[8] == pytest.approx(env.pad_x)
    assert env.observation_space.shape == (9,)
    assert env.observation_space.low[8] == -1.0 and env.observation_space.high[8] == 1.0
    assert env.observation_space.contains(obs)
    assert set(info) == {"success", "crashed", "landed_outside"}
    assert not any(info.values())


def test_same_seed_gives_identical_trajectories():
    actions = np.random.default_rng(0).integers(0, 4, 150)

    def trajectory(seed: int) -> np.ndarray:
        env = TargetLunarLander()
        rows = [env.reset(seed=seed)[0]]
        for action in actions:
            obs, reward, terminated, _, _ = env.step(int(action))
            rows.append(np.append(obs, reward))
            if terminated:
                break
        return np.concatenate(rows)

    np.testing.assert_array_equal(trajectory(11), trajectory(11))
    assert not np.array_equal(trajectory(11), trajectory(12))


def test_pads_take_the_nine_inner_chunk_positions_inside_the_screen():
    env = TargetLunarLander()
    pads = {round(float(env.reset(seed=seed)[0][8]), 6) for seed in range(200)}
    expected = {round(pad_x_of_chunk(chunk), 6) for chunk in PAD_CHUNKS}
    assert pads == expected
    assert np.allclose(sorted(expected), np.linspace(-0.8, 0.8, 9))


def test_random_pad_false_keeps_the_standard_centre_pad():
    env = TargetLunarLander(random_pad=False)
    assert {float(env.reset(seed=seed)[0][8]) for seed in range(20)} == {0.0}


def test_terrain_is_flat_under_the_flags():
    env = TargetLunarLander()
    for seed in range(30):
        env.reset(seed=seed)
        pad_points = {
            point
            for poly in env.sky_polys
            for point in poly[:2]
            if env.helipad_x1 <= point[0] <= env.helipad_x2
        }
        assert len(pad_points) == 3  # flag, pad centre, flag: two flat edges
        assert all(y == pytest.approx(env.helipad_y) for _, y in pad_points)
        centre = (env.helipad_x1 + env.helipad_x2) / 2
        assert (centre - 10.0) / 10.0 == pytest.approx(env.pad_x)


def test_flags_are_drawn_at_the_moved_pad():
    env = TargetLunarLander(render_mode="rgb_array")
    seed = 0
    while env.reset(seed=seed)[0][8] > -0.5:  # a pad far left of the standard one
        seed += 1
    frame = env.render()
    assert frame.shape == (400, 600, 3)
    yellow = np.all(frame == FLAG_YELLOW, axis=-1)
    columns = np.nonzero(yellow.any(axis=0))[0]
    flag_px = [env.helipad_x1 * 30, env.helipad_x2 * 30]
    assert columns.min() >= flag_px[0] - 1 and columns.max() <= flag_px[1] + 26
    assert yellow[:, int(flag_px[0]) : int(flag_px[0]) + 20].any()
    assert yellow[:, int(flag_px[1]) : int(flag_px[1]) + 20].any()
    env.close()


def test_shaping_is_measured_from_the_pad_and_engines_cost_fuel():
    env = TargetLunarLander()
    obs, _ = env.reset(seed=5)
    assert obs[8] != 0.0
    for action, cost in [(0, 0.0), (2, 0.3), (1, 0.03), (3, 0.03)]:
        next_obs, reward, *_ = env.step(action)
        expected = _shaping(next_obs) - _shaping(obs) - cost
        assert reward == pytest.approx(expected, abs=1e-3)
        obs = next_obs


def test_free_fall_crashes_with_minus_100():
    info, rewards, _ = _episode(TargetLunarLander(), 0, lambda obs: 0)
    assert info["crashed"] and not info["success"] and not info["landed_outside"]
    assert rewards[-1] == -100.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_target_heuristic_lands_on_the_moved_pad(seed):
    env = gym.make(ENV_ID)
    info, rewards, obs = _episode(env, seed, target_heuristic)
    assert info["success"] and not info["crashed"] and not info["landed_outside"]
    assert rewards[-1] == 100.0
    assert abs(obs[0] - obs[8]) < 0.2


def test_moved_pads_are_off_centre_for_the_heuristic_seeds():
    env = TargetLunarLander()
    assert sum(env.reset(seed=seed)[0][8] != 0.0 for seed in range(6)) >= 4


@pytest.mark.parametrize("seed", [0, 2, 3, 4])
def test_landing_beside_the_pad_is_not_a_success(seed):
    def aim_left_of_pad(obs: np.ndarray) -> int:
        fake = obs.copy()
        fake[8] = np.clip(obs[8] - 0.3, -0.9, 0.9)
        return target_heuristic(fake)

    info, rewards, obs = _episode(gym.make(ENV_ID), seed, aim_left_of_pad)
    assert info["landed_outside"] and not info["success"] and not info["crashed"]
    assert rewards[-1] != 100.0
    assert abs(obs[0] - obs[8]) > 0.2


def test_render_mode_none_builds_no_flame_particles():
    env = TargetLunarLander()
    env.reset(seed=0)
    for _ in range(100):
        env.step(2)
    assert env.particles == []


def test_rgb_array_without_render_keeps_flame_particles_bounded():
    env = TargetLunarLander(render_mode="rgb_array")
    env.reset(seed=0)
    for step in range(300):
        _, _, terminated, _, _ = env.step(2 if step % 3 else 1)
        if terminated:
            env.reset()
    assert 0 < len(env.particles) <= MAX_PARTICLES


# -- the native batched env (dcsc_torchrl.batched_envs.TargetLunarLanderBatch) ----------
def _gym_vector_reference(num_envs: int, random_pad: bool, max_steps: int):
    """What the batched env replaces: gymnasium's SyncVectorEnv of the id under GymWrapper."""
    from gymnasium.vector import AutoresetMode
    from torchrl.data import Categorical, Composite
    from torchrl.envs.libs.gym import default_info_dict_reader

    keys = ["success", "crashed", "landed_outside"]
    spec = Composite({key: Categorical(2, shape=(num_envs,), dtype=torch.bool) for key in keys}, shape=[num_envs])
    vector = gym.make_vec(ENV_ID, num_envs=num_envs, vectorization_mode="sync",
                          vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
                          random_pad=random_pad, max_episode_steps=max_steps, disable_env_checker=True)
    env = GymWrapper(vector)
    env.set_info_dict_reader(default_info_dict_reader(keys, spec=spec))
    return env


@pytest.mark.parametrize("random_pad", [False, True])
def test_batched_env_plays_the_episodes_of_gymnasiums_vector_env_frame_by_frame(random_pad):
    from dcsc_torchrl.batched_envs import TargetLunarLanderBatch

    frames, num_envs, max_steps = 400, 3, 150  # several episodes per env: crashes, timeouts, resets
    rollouts = []
    for env in (TargetLunarLanderBatch(num_envs, random_pad=random_pad, max_steps=max_steps),
                _gym_vector_reference(num_envs, random_pad, max_steps)):
        env.set_seed(7)
        torch.manual_seed(0)
        rollouts.append(env.rollout(frames, break_when_any_done=False))
        env.close()
    ours, reference = rollouts
    assert reference["next", "done"].sum() >= 2 * num_envs  # the frames cross several resets
    for key in ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                ("next", "terminated"), ("next", "truncated"), ("next", "success"), ("next", "crashed"),
                ("next", "landed_outside")]:
        torch.testing.assert_close(ours[key], reference[key].reshape(ours[key].shape), rtol=0, atol=0,
                                   msg=lambda m, key=key: f"{key}: {m}")


def test_batched_env_passes_check_env_specs_and_refuses_bad_sizes():
    from dcsc_torchrl.batched_envs import TargetLunarLanderBatch

    check_env_specs(TargetLunarLanderBatch(2))
    with pytest.raises(ValueError, match="num_envs must be >= 1, got 0"):
        TargetLunarLanderBatch(0)
    with pytest.raises(ValueError, match="max_steps must be >= 1, got 0"):
        TargetLunarLanderBatch(1, max_steps=0)


def test_target_heuristic_on_a_batch_is_the_heuristic_row_by_row():
    rng = np.random.default_rng(0)
    obs = rng.normal(0.0, 0.5, (2000, 9)).astype(np.float32)
    obs[:, 6:8] = rng.random((2000, 2)) < 0.1
    batch = target_heuristic(obs)
    assert batch.shape == (2000,) and batch.dtype == np.int64
    assert batch.tolist() == [target_heuristic(row) for row in obs]
    assert set(batch.tolist()) == {0, 1, 2, 3}
