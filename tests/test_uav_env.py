"""UAV path planning: scenarios, obstacle motions, the batched TorchRL env and its gym id."""

import io
import math

import gymnasium as gym
import matplotlib
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

import dcsc_torchrl.envs  # noqa: F401  (registers the ids)
from dcsc_torchrl.envs.uav import (
    ARENA_HIGH,
    BEST_CONSTANT_ACTION,
    BEST_CONSTANT_SEEDS,
    COLLISION_REWARD,
    DT,
    GOAL,
    GOAL_REWARD,
    HORIZON,
    N_OBSTACLE_PARAMS,
    N_OBSTACLES,
    PROGRESS_REWARD,
    THREAT_COST,
    THREAT_MARGIN,
    TIME_COST,
    ObstacleFamily,
    ObstacleParam,
    UAVPathPlanningEnv,
    UAVScenario,
    best_constant_action,
    constant_action_outcomes,
    obstacle_states,
    sample_scenario,
    sample_scenarios,
    step_reward,
)
from dcsc_torchrl.envs.uav_env import _segment_point_distance
from dcsc_torchrl.envs.uav_plot import plot_uav_episode

ENV_ID = "dcsc/UAVPathPlanning-v0"
START = torch.tensor([0.5, 2.5, 5.5])


def _static_obstacle(centre, radius: float = 1.0) -> torch.Tensor:
    params = torch.zeros(N_OBSTACLE_PARAMS)
    params[ObstacleParam.CENTRE_X : ObstacleParam.CENTRE_Z + 1] = torch.tensor(centre)
    params[ObstacleParam.RADIUS] = radius
    return params


def _far_obstacles() -> list[torch.Tensor]:
    return [_static_obstacle([500.0 + 10 * k, -500.0, 5.0]) for k in range(N_OBSTACLES)]


def _fixed_scenario(obstacles, start=START, goal=GOAL):
    """A ``scenario_fn`` that gives every seed the same hand-made scenario."""
    params = torch.stack(obstacles)

    def scenario_fn(seeds: torch.Tensor) -> UAVScenario:
        n = len(seeds)
        return UAVScenario(
            seed=seeds,
            start=torch.as_tensor(start, dtype=torch.float32).expand(n, 3),
            goal=torch.as_tensor(goal, dtype=torch.float32).expand(n, 3),
            obstacle_params=params.expand(n, *params.shape),
        )

    return scenario_fn


def _fly(env: UAVPathPlanningEnv, action, steps: int = 500) -> TensorDict:
    """Rollout with a constant action until the first env is done."""
    actions = torch.as_tensor(action, dtype=torch.float32).expand(*env.batch_size, 3)
    return env.rollout(steps, lambda td: td.set("action", actions))


@pytest.mark.parametrize("num_envs", [1, 8])
def test_batched_env_passes_check_env_specs(num_envs):
    check_env_specs(UAVPathPlanningEnv(num_envs, seed=0))


def test_validation_scenarios_pass_check_env_specs():
    check_env_specs(UAVPathPlanningEnv(scenario_seeds=range(8)))


@pytest.mark.filterwarnings("ignore:.*(symmetric and normalized|infinity):UserWarning")
@pytest.mark.parametrize("scenario_seed", [None, 3])
def test_gym_id_passes_gymnasium_check_env(scenario_seed):
    env = gym.make(ENV_ID, scenario_seed=scenario_seed)
    check_env(env.unwrapped)


def test_gym_id_under_torchrl_passes_check_env_specs():
    env = GymEnv(ENV_ID, scenario_seed=0)
    env.auto_register_info_dict()
    check_env_specs(env)


def test_gym_id_reports_episode_info():
    env = gym.make(ENV_ID, scenario_seed=1)
    obs, info = env.reset(seed=0)
    assert obs.shape == (9,) and obs.dtype == np.float32
    assert info["scenario_seed"] == 1 and not info["success"]
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(np.array([2.0, 2.0, 2.0]))
    assert set(info) == {"success", "collision", "out_of_bounds", "path_length", "scenario_seed"}
    assert info["success"] or info["collision"] or truncated
    assert info["path_length"] > 1.0


def test_gym_id_draws_reproducible_fresh_scenarios():
    env = gym.make(ENV_ID)
    first = env.reset(seed=5)[1]["scenario_seed"]
    assert env.reset(seed=5)[1]["scenario_seed"] == first
    assert env.reset(seed=6)[1]["scenario_seed"] != first


def test_obstacle_velocity_is_the_time_derivative_of_the_centre():
    params = sample_scenarios(range(20)).obstacle_params.double()
    t = torch.linspace(0.0, 40.0, 20, dtype=torch.float64)
    eps = 1e-5
    ahead, _, _ = obstacle_states(params, t + eps)
    behind, _, _ = obstacle_states(params, t - eps)
    _, velocities, _ = obstacle_states(params, t)
    torch.testing.assert_close(velocities, (ahead - behind) / (2 * eps), atol=1e-5, rtol=1e-5)


def test_obstacle_states_predicts_many_future_times_at_once():
    params = sample_scenarios(range(3)).obstacle_params  # [3, K, P]
    times = torch.arange(0.0, 2.0, DT).expand(3, -1)  # [3, T]
    centres, velocities, radii = obstacle_states(params.unsqueeze(1), times)
    assert centres.shape == velocities.shape == (3, 20, N_OBSTACLES, 3)
    assert radii.shape == (3, 20, N_OBSTACLES)
    one, _, _ = obstacle_states(params[2], times[2, 7])
    torch.testing.assert_close(centres[2, 7], one)


def test_motion_family_covers_circles_passes_and_reversing_arcs():
    circle = _static_obstacle([5.0, 5.0, 5.0])
    circle[ObstacleParam.AXIS_A] = circle[ObstacleParam.AXIS_B] = 2.0
    circle[ObstacleParam.ANGULAR_SPEED] = 0.5
    straight = _static_obstacle([5.0, 5.0, 5.0])
    straight[ObstacleParam.DRIFT_X] = 1.0
    straight[ObstacleParam.CROSS_TIME] = 4.0
    arc = circle.clone()
    arc[ObstacleParam.ANGULAR_SPEED] = 0.0
    arc[ObstacleParam.SWING] = 1.0
    arc[ObstacleParam.SWING_RATE] = 0.5
    arc[ObstacleParam.BOB_AMPLITUDE] = 0.5
    arc[ObstacleParam.BOB_RATE] = 1.0
    t = torch.linspace(0.0, 12.0, 121)
    centres, velocities, _ = obstacle_states(torch.stack([circle, straight, arc]), t)
    radial = (centres[:, 0, :2] - 5.0).norm(dim=-1)
    torch.testing.assert_close(radial, torch.full_like(radial, 2.0))
    torch.testing.assert_close(centres[40, 1], torch.tensor([5.0, 5.0, 5.0]))  # t = 4 s
    torch.testing.assert_close(velocities[:, 1], torch.tensor([1.0, 0.0, 0.0]).expand(121, 3))
    assert (velocities[:, 2, 1] > 0).any() and (velocities[:, 2, 1] < 0).any()  # reverses
    assert centres[:, 2, 2].max() - centres[:, 2, 2].min() > 0.9  # bobs


def test_a_seed_gives_one_scenario_in_any_batch():
    batch = sample_scenarios([7, 3, 11])
    single = sample_scenario(3)
    torch.testing.assert_close(batch.obstacle_params[1], single.obstacle_params, rtol=0, atol=0)
    torch.testing.assert_close(batch.start[1], single.start, rtol=0, atol=0)
    assert int(single.seed) == 3
    assert not torch.equal(batch.obstacle_params[0], batch.obstacle_params[2])


def test_scenarios_start_in_the_start_box_and_fly_to_the_goal():
    scenarios = sample_scenarios(range(50))
    assert (scenarios.start >= torch.tensor([0.0, 2.0, 5.0])).all() and (
        scenarios.start <= torch.tensor([3.0, 5.0, 8.0])
    ).all()
    torch.testing.assert_close(scenarios.goal, torch.tensor(GOAL).expand(50, 3))
    assert scenarios.obstacle_params.shape == (50, N_OBSTACLES, N_OBSTACLE_PARAMS)
    assert len({tuple(row.tolist()) for row in scenarios.start}) == 50
    centres, _, radii = obstacle_states(scenarios.obstacle_params, 0.0)
    assert ((centres - scenarios.start.unsqueeze(1)).norm(dim=-1) - radii).min() >= 1.0


def test_scenario_seeds_are_replayed_at_every_reset():
    env = UAVPathPlanningEnv(scenario_seeds=[4, 9])
    first = env.reset()
    _fly(env, [1.0, 1.0, 1.0], steps=20)
    second = env.reset()
    for key in ("position", "goal", "obstacle_params", "observation", "scenario_seed"):
        torch.testing.assert_close(first[key], second[key], rtol=0, atol=0)
    assert first["scenario_seed"].squeeze(-1).tolist() == [4, 9]
    torch.testing.assert_close(first["position"][1], sample_scenario(9).start)


def test_fresh_scenarios_follow_the_env_seed():
    env = UAVPathPlanningEnv(3)
    env.set_seed(1)
    first = env.reset()["scenario_seed"]
    env.set_seed(1)
    assert torch.equal(env.reset()["scenario_seed"], first)
    env.set_seed(2)
    assert not torch.equal(env.reset()["scenario_seed"], first)
    assert (first >= 2**31).all()  # never a validation seed
    assert len(set(first.flatten().tolist())) == 3


def test_constant_action_reaches_the_goal_when_no_obstacle_is_near():
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario(_far_obstacles()))
    rollout = _fly(env, [1.0, 1.5, 1.5])
    last = rollout[0, -1]["next"]
    assert last["success"].item() and last["terminated"].item() and last["done"].item()
    assert not last["collision"].item() and not last["out_of_bounds"].item()
    straight = float((START - torch.tensor(GOAL)).norm())
    assert last["path_length"].item() == pytest.approx(straight, rel=0.05)
    torch.testing.assert_close(last["position"], torch.tensor(GOAL))
    # the progress terms add up to PROGRESS_REWARD exactly on arrival
    expected = PROGRESS_REWARD + GOAL_REWARD - TIME_COST * rollout.shape[-1]
    assert rollout["next", "reward"].sum().item() == pytest.approx(expected, abs=1e-3)


def test_flying_into_an_obstacle_ends_with_a_collision():
    rammer = _static_obstacle((START + torch.tensor([3.0, 0.0, 0.0])).tolist(), radius=1.0)
    rammer[ObstacleParam.DRIFT_X] = -8.0  # faster than the capped UAV speed, head on
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario([rammer, *_far_obstacles()[1:]]))
    rollout = _fly(env, [0.0, 0.0, 0.0], steps=50)
    last = rollout[0, -1]["next"]
    assert last["collision"].item() and last["terminated"].item()
    assert not last["success"].item()
    assert last["reward"].item() < COLLISION_REWARD + 1.0
    assert rollout.shape[-1] < 10


def test_leaving_the_arena_ends_with_out_of_bounds():
    outside = [ARENA_HIGH[0] + 6.0, 10.0, 5.5]
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario(_far_obstacles(), goal=outside))
    rollout = _fly(env, [1.0, 1.0, 1.0])
    last = rollout[0, -1]["next"]
    assert last["out_of_bounds"].item() and last["terminated"].item()
    assert not last["success"].item() and not last["collision"].item()
    assert last["reward"].item() < COLLISION_REWARD + 1.0
    assert last["position"][0] > ARENA_HIGH[0]


def test_horizon_truncates():
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario(_far_obstacles()), horizon=7)
    rollout = _fly(env, [1.0, 1.0, 1.0])
    assert rollout.shape[-1] == 7
    last = rollout[0, -1]["next"]
    assert last["truncated"].item() and last["done"].item() and not last["terminated"].item()
    assert last["time"].item() == pytest.approx(7 * DT)


def test_reward_adds_threat_and_distance_terms():
    path = torch.tensor(GOAL) - START
    side = torch.tensor([-path[1], path[0], 0.0]) / path[:2].norm()
    centre = START + 1.25 * side  # surface 0.25 from the start: inside the threat zone
    obstacles = [_static_obstacle(centre.tolist()), *_far_obstacles()[1:]]
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario(obstacles))
    env.reset()
    out = env.step(TensorDict({"action": torch.ones(1, 3)}, batch_size=[1]))["next"]
    position = out["position"][0]
    d_surface = float((position - centre).norm()) - 1.0
    assert 0.0 < d_surface < 0.4
    progress = (path.norm() - (position - torch.tensor(GOAL)).norm()) / path.norm()
    expected = (
        PROGRESS_REWARD * float(progress) - TIME_COST - THREAT_COST * (1 - d_surface / 0.4)
    )
    assert out["reward"].item() == pytest.approx(expected, abs=1e-5)
    to_surface = out["observation"][0, :3]
    torch.testing.assert_close(to_surface.norm(), torch.tensor(d_surface), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["observation"][0, 3:6], torch.tensor(GOAL) - position)


def _scripted_return(waypoints: list[list[float]], steps: int, obstacle=None) -> float:
    """Return of a flight along straight segments through ``waypoints`` in ``steps`` steps.

    Scored by :func:`step_reward` as the env scores a step: the flight ends at the first
    point inside ``obstacle`` (a collision) or at the goal (the last waypoint).
    """
    points = torch.tensor(waypoints)
    lengths = (points[1:] - points[:-1]).norm(dim=-1)
    cumulative = torch.cat([torch.zeros(1), lengths.cumsum(0)])
    s = torch.linspace(0, float(cumulative[-1]), steps + 1)
    segment = (torch.searchsorted(cumulative, s, right=True) - 1).clamp(0, len(lengths) - 1)
    frac = ((s - cumulative[segment]) / lengths[segment]).unsqueeze(-1)
    path = points[segment] + frac * (points[segment + 1] - points[segment])
    goal, start = points[-1], points[0]
    total = 0.0
    for p, q in zip(path[:-1], path[1:], strict=True):
        d_surface = torch.tensor([50.0])
        if obstacle is not None:
            d_surface = (q - obstacle[0]).norm(dim=-1, keepdim=True) - obstacle[1]
        failed = bool(d_surface.min() <= 0)
        success = bool((q - goal).norm() < 1e-4) and not failed
        total += step_reward(
            p, q, start, goal, d_surface, torch.tensor(failed), torch.tensor(success)
        ).item()
        if failed or success:
            break
    return total


def test_reward_ranks_crashes_below_arrivals_and_faster_arrivals_higher():
    start, goal = [0.5, 2.5, 5.5], list(GOAL)
    line = torch.tensor(goal) - torch.tensor(start)
    early = (torch.tensor(start) + 0.15 * line, 1.0)  # an obstacle near the start
    late = (torch.tensor(start) + 0.85 * line, 1.0)  # an obstacle near the goal
    detour = [start, [0.5, 10.0, 5.5], goal]
    crash_early = _scripted_return([start, goal], 120, early)
    crash_late = _scripted_return([start, goal], 120, late)
    long_safe = _scripted_return(detour, 400)
    short_safe = _scripted_return([start, goal], 120)
    assert crash_early < crash_late < long_safe < short_safe
    # the worst arrival (the whole horizon inside every threat zone) still beats the best
    # failure (a crash a hair from the goal, with all the progress and no time cost)
    worst_arrival = PROGRESS_REWARD + GOAL_REWARD - HORIZON * (TIME_COST + THREAT_COST)
    best_failure = PROGRESS_REWARD + COLLISION_REWARD
    assert best_failure < worst_arrival
    hover, goal_point = torch.zeros(3), torch.ones(3)  # no progress: only time and threat
    threat = step_reward(
        hover, hover, -goal_point, goal_point,
        torch.tensor([1e-3, THREAT_MARGIN / 2]), torch.tensor(False), torch.tensor(False),
    )
    assert threat.item() == pytest.approx(-TIME_COST - THREAT_COST * (1 - 1e-3 / THREAT_MARGIN))


def test_calibrated_family_keeps_its_difficulty_for_the_best_constant_planner():
    outcomes = constant_action_outcomes([BEST_CONSTANT_ACTION], range(50))
    failure = 1.0 - outcomes["success"].float().mean().item()
    assert failure >= 0.25


@pytest.mark.slow
def test_best_constant_action_is_found_on_its_own_seeds():
    found = best_constant_action(BEST_CONSTANT_SEEDS)
    torch.testing.assert_close(found, torch.tensor(BEST_CONSTANT_ACTION))


def test_goal_counts_when_the_step_passes_it():
    a, b = torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    assert _segment_point_distance(a, b, torch.tensor([[0.5, 0.15, 0.0]])).item() == (
        pytest.approx(0.15)
    )
    assert _segment_point_distance(a, b, torch.tensor([[1.3, 0.0, 0.0]])).item() == (
        pytest.approx(0.3)
    )


def test_uav_straight_above_an_obstacle_centre_gives_no_nan():
    above = START - torch.tensor([0.0, 0.0, 1.6])
    obstacles = [_static_obstacle(above.tolist(), radius=1.0), *_far_obstacles()[1:]]
    env = UAVPathPlanningEnv(scenario_fn=_fixed_scenario(obstacles))
    for action in ([0.0, 0.0, 0.0], [3.0, 3.0, 3.0]):
        rollout = _fly(env, action, steps=40)
        for key in ("observation", "reward", "position", "path_length"):
            assert torch.isfinite(rollout["next", key]).all()


def test_random_actions_on_validation_scenarios_stay_finite():
    env = UAVPathPlanningEnv(scenario_seeds=range(16))
    rollout = env.rollout(150, break_when_any_done=False)
    for key in ("observation", "reward", "position", "path_length", "time"):
        assert torch.isfinite(rollout["next", key]).all()
    assert rollout["next", "done"].any()  # some episodes ended and were reset


def test_partial_reset_restarts_only_the_masked_envs():
    env = UAVPathPlanningEnv(4, seed=0)
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", torch.ones(4, 3)))["next"]
    before = td.clone()
    mask = torch.tensor([[True], [False], [True], [False]])
    after = env.reset(td.clone().set("_reset", mask))
    assert after["time"].squeeze(-1).tolist() == pytest.approx([0.0, 5 * DT, 0.0, 5 * DT])
    for key in ("position", "obstacle_params", "scenario_seed", "path_length"):
        torch.testing.assert_close(after[key][1::2], before[key][1::2], rtol=0, atol=0)
    assert not torch.equal(after["scenario_seed"][0::2], before["scenario_seed"][0::2])
    assert (after["path_length"][0::2] == 0).all()
    stepped = env.step(after.set("action", torch.ones(4, 3)))["next"]
    assert stepped["time"].squeeze(-1).tolist() == pytest.approx([DT, 6 * DT, DT, 6 * DT])


def test_outputs_are_copies_that_later_steps_leave_alone():
    env = UAVPathPlanningEnv(2, seed=0)
    first = env.reset()
    kept = first.clone()
    out = env.step(first.set("action", torch.ones(2, 3)))["next"]
    kept_out = out.clone()
    env.step(out.clone().set("action", torch.ones(2, 3)))
    env.reset(out.clone().set("_reset", torch.tensor([[True], [False]])))
    for key in kept.keys():
        torch.testing.assert_close(first[key], kept[key], rtol=0, atol=0)
    for key in kept_out.keys():
        torch.testing.assert_close(out[key], kept_out[key], rtol=0, atol=0)


def test_batch_of_8_equals_8_single_scenario_envs():
    seeds = list(range(8))
    actions = 3 * torch.rand(60, 8, 3, generator=torch.Generator().manual_seed(0))
    batched = UAVPathPlanningEnv(scenario_seeds=seeds)
    singles = [UAVPathPlanningEnv(scenario_seeds=[seed]) for seed in seeds]
    td = batched.reset()
    single_tds = [env.reset() for env in singles]
    keys = [
        "observation",
        "position",
        "path_length",
        "time",
        "success",
        "collision",
        "out_of_bounds",
        "done",
        "terminated",
        "truncated",
        "scenario_seed",
    ]
    for step in range(60):
        td = batched.step(td.set("action", actions[step]))["next"]
        for i, env in enumerate(singles):
            single_tds[i] = env.step(single_tds[i].set("action", actions[step, i : i + 1]))["next"]
            for key in [*keys, "reward"]:
                torch.testing.assert_close(td[key][i : i + 1], single_tds[i][key], rtol=0, atol=0)


def test_env_lives_on_the_requested_device():
    device = "cuda" if torch.cuda.is_available() else "cpu"
    env = UAVPathPlanningEnv(2, device=device, seed=0)
    td = env.rollout(3)
    assert td.device.type == device and td["next", "observation"].device.type == device


def test_bad_construction_is_rejected():
    with pytest.raises(ValueError, match="num_envs=3"):
        UAVPathPlanningEnv(3, scenario_seeds=[0, 1])
    with pytest.raises(ValueError, match="obstacle_params"):
        UAVPathPlanningEnv(scenario_seeds=[0], scenario_fn=_fixed_scenario(_far_obstacles()[:2]))
    with pytest.raises(ValueError, match="n_obstacles"):
        sample_scenario(0, n_obstacles=0)
    with pytest.raises(ValueError, match="crossing=2"):
        ObstacleFamily(crossing=2)
    with pytest.raises(ValueError, match="speed"):
        ObstacleFamily(speed=(2.0, 1.0))


def test_a_family_is_a_parameter_of_the_scenarios():
    mild = ObstacleFamily(speed=(0.5, 1.5), radius=(0.6, 1.2), lateral=1.5, vertical=1.0,
                          intercept=None, climb=0.0, crossing=0.0)
    radii = sample_scenarios(range(20), n_obstacles=4, family=mild).obstacle_params[
        ..., ObstacleParam.RADIUS
    ]
    assert radii.min() >= 0.6 and radii.max() <= 1.2
    params = sample_scenarios(range(20)).obstacle_params  # the calibrated family
    pairs = params.reshape(20, N_OBSTACLES // 2, 2, N_OBSTACLE_PARAMS)
    # crossing pairs: same anchor and crossing time, drifts from opposite sides
    for field in (ObstacleParam.CENTRE_X, ObstacleParam.CENTRE_Y, ObstacleParam.CROSS_TIME):
        torch.testing.assert_close(pairs[..., 0, field], pairs[..., 1, field])
    drift = pairs[..., ObstacleParam.DRIFT_X : ObstacleParam.DRIFT_Y + 1]
    assert ((drift[..., 0, :] * drift[..., 1, :]).sum(-1) < 0).all()
    assert (params[..., ObstacleParam.DRIFT_Z].abs() > 0).any()


def test_plot_draws_path_obstacle_tracks_start_and_goal():
    matplotlib.use("Agg")
    env = UAVPathPlanningEnv(scenario_seeds=[0])
    rollout = _fly(env, [2.0, 2.0, 2.0])
    path = torch.cat([rollout["position"][0], rollout["next", "position"][0, -1:]])
    fig = plot_uav_episode(
        path, rollout["obstacle_params"][0, 0], rollout["goal"][0, 0], title="seed 0"
    )
    ax = fig.axes[0]
    assert ax.get_title() == "seed 0"
    assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("x", "y", "z")
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert labels[0] == "UAV path" and "start" in labels and "goal" in labels
    assert sum(label.endswith("track") for label in labels) == N_OBSTACLES
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    assert buffer.tell() > 10_000
    assert math.isclose(path.shape[0], rollout.shape[-1] + 1)
