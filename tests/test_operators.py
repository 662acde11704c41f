"""The simulated operators (docs/operators.md): traits, RT model, decision loop, both tasks."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from internal_model_fit import fit_internal_model
from scipy.stats import exponnorm
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from dcsc_torchrl.batched_envs import make_lunar_env, make_uav_env
from dcsc_torchrl.envs.uav import DT, N_OBSTACLE_PARAMS, ObstacleParam
from dcsc_torchrl.humans import (
    PRESETS,
    OperatorTraits,
    SimulatedOperator,
    SimulatedPilot,
    operator_only_episodes,
    operator_only_policy,
)
from dcsc_torchrl.humans.pilot import INTERNAL_MODEL, predict_frame
from dcsc_torchrl.humans.streams import EnvStreams
from dcsc_torchrl.transforms import HumanOperatorTransform

DOCS = Path(__file__).resolve().parents[1] / "docs" / "operators.md"


def query(observation: torch.Tensor, is_init: bool | torch.Tensor) -> TensorDict:
    """What HumanOperatorTransform hands an operator: the env's keys plus ``is_init``."""
    batch = observation.shape[:-1]
    init = torch.as_tensor(is_init).expand(*batch, 1).clone()
    return TensorDict({"observation": observation, "is_init": init}, batch)


def lunar_rollout(operator, seed: int, steps: int = 60, n_envs: int = 3) -> TensorDict:
    env = make_lunar_env(n_envs, transforms=[HumanOperatorTransform(operator, seed=seed)])
    env.set_seed(0)
    return env.rollout(steps, operator_only_policy(), break_when_any_done=False)


# --- traits -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("decision_interval", -0.1),
        ("eps", 1.5),
        ("lag", 1.0),
        ("rt_tau", -0.1),
        ("lapse_threshold", 0.0),
    ],
)
def test_traits_reject_out_of_range_values_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        OperatorTraits(**{field: value})


def test_presets_are_traits_and_from_preset_applies_overrides():
    assert {"expert", "noisy", "laggy", "distracted"} <= set(PRESETS)
    assert all(isinstance(traits, OperatorTraits) for traits in PRESETS.values())
    assert 0.15 <= PRESETS["noisy"].eps <= 0.3 and PRESETS["laggy"].lag == 0.8
    pilot = SimulatedPilot.from_preset("noisy", eps=0.3)
    assert pilot.traits == dataclasses.replace(PRESETS["noisy"], eps=0.3)
    operator = SimulatedOperator.from_preset("laggy", horizon=3)
    assert operator.traits == PRESETS["laggy"] and operator.horizon == 3
    with pytest.raises(KeyError, match="expert"):
        SimulatedPilot.from_preset("sleepy")


# --- random streams and determinism -------------------------------------------------


def test_env_streams_do_not_depend_on_batch_composition():
    wide = EnvStreams(7, draws=4)
    narrow = EnvStreams(7, draws=4)
    for _ in range(3):
        a, b = wide.uniform(torch.Size([8])), narrow.uniform(torch.Size([3]))
        torch.testing.assert_close(a[:3], b)
    u = EnvStreams(7, draws=4).uniform(torch.Size([4000]))
    assert u.min() >= 0 and u.max() < 1 and abs(u.mean().item() - 0.5) < 0.01
    assert not EnvStreams(8, draws=4).uniform(torch.Size([3])).equal(b)


@pytest.mark.parametrize("make", [lambda: SimulatedPilot.from_preset("noisy")])
def test_simulated_pilot_env_i_behaves_the_same_in_any_batch(make):
    torch.manual_seed(0)
    frames = [torch.randn(8, 9) * 0.5 for _ in range(12)]
    wide, narrow, grid, single = make(), make(), make(), make()
    for op in (wide, narrow, grid, single):
        op.reset(3)
    for t, obs in enumerate(frames):
        a = wide(query(obs, t == 0))
        b = narrow(query(obs[:3], t == 0))
        c = grid(query(obs.reshape(2, 4, 9), t == 0))
        d = single(query(obs[0], t == 0))
        for key in ("human_action", "human_rt", "human_decided"):
            torch.testing.assert_close(a[key][:3], b[key])
            torch.testing.assert_close(a[key], c[key].reshape(a[key].shape))
            torch.testing.assert_close(a[key][0], d[key])


def test_an_env_restarting_is_no_new_frame_for_the_others():
    """A partial reset reaches the operator with ``"_step"`` True for the envs reset only
    (HumanOperatorTransform): env 0 answers exactly as it would alone, while envs 1 and 2
    restart every few frames; the same calls without ``"_step"`` would age env 0 a frame each."""
    torch.manual_seed(0)
    frames = [torch.randn(3, 9) * 0.5 for _ in range(30)]
    batch, unmarked, alone = (SimulatedPilot.from_preset("distracted") for _ in range(3))
    for op in (batch, unmarked, alone):
        op.reset(3)
    restart = torch.tensor([[False], [True], [True]])
    diverged = False
    for t, obs in enumerate(frames):
        a, u, d = batch(query(obs, t == 0)), unmarked(query(obs, t == 0)), alone(query(obs[0], t == 0))
        for key in ("human_action", "human_rt", "human_decided"):
            torch.testing.assert_close(a[key][0], d[key])
        diverged |= not (u["human_action"][0].equal(d["human_action"]) and u["human_rt"][0].equal(d["human_rt"]))
        if t % 4 == 2:  # envs 1 and 2 restart between two frames
            batch(query(obs, restart).set("_step", restart.squeeze(-1)))
            unmarked(query(obs, restart))
    assert diverged


def test_an_env_left_out_of_a_step_stands_still():
    """``"_step"`` False (TorchRL's partial steps): env 1 neither sees the frame nor decides, and
    then goes on exactly as if those calls had not happened."""
    torch.manual_seed(1)
    frames = [torch.randn(2, 9) * 0.5 for _ in range(24)]
    held = {5, 6, 7, 12, 13}
    partly, only_its_frames = SimulatedPilot.from_preset("noisy"), SimulatedPilot.from_preset("noisy")
    partly.reset(4)
    only_its_frames.reset(4)
    answers, expected = [], []
    for t, obs in enumerate(frames):
        stepped = torch.tensor([True, t not in held])
        out = partly(query(obs, t == 0).set("_step", stepped))
        if t in held:
            assert not out["human_decided"][1].item()
            continue
        answers.append(out[1])
        expected.append(only_its_frames(query(obs, t == 0))[1])
    for key in ("human_action", "human_rt", "human_decided"):
        torch.testing.assert_close(torch.stack([a[key] for a in answers]), torch.stack([e[key] for e in expected]))


@pytest.mark.parametrize("preset", ["noisy", "distracted"])
def test_simulated_pilot_is_deterministic_for_a_seed_and_differs_across_seeds(preset):
    first = lunar_rollout(SimulatedPilot.from_preset(preset), seed=1, steps=400)
    again = lunar_rollout(SimulatedPilot.from_preset(preset), seed=1, steps=400)
    other = lunar_rollout(SimulatedPilot.from_preset(preset), seed=2, steps=400)
    for key in ("human_action", "human_rt", "human_decided"):
        assert first[key].equal(again[key])
    assert not first["human_rt"].equal(other["human_rt"])
    assert not first["human_action"].equal(other["human_action"])


def test_simulated_operator_is_deterministic_for_a_seed_and_differs_across_seeds():
    def run(seed):
        operator = SimulatedOperator.from_preset("noisy", horizon=4)
        env = make_uav_env(
            2, scenario_seeds=[0, 1], transforms=[HumanOperatorTransform(operator, seed=seed)]
        )
        return env.rollout(25, operator_only_policy(), break_when_any_done=False)

    first, again, other = run(1), run(1), run(2)
    for key in ("human_action", "human_rt", "human_decided"):
        assert first[key].equal(again[key])
    assert not first["human_rt"].equal(other["human_rt"])
    assert not first["human_action"].equal(other["human_action"])
    assert first["human_action"].dtype == torch.float32
    assert ((first["human_action"] >= 0) & (first["human_action"] <= 3)).all()


# --- reaction times -----------------------------------------------------------------


def draw_rts(traits: OperatorTraits, observation: torch.Tensor, n: int = 20000) -> torch.Tensor:
    """n RTs: one decision of n envs at their episode's first frame."""
    pilot = SimulatedPilot(traits)
    pilot.reset(0)
    out = pilot(query(observation.expand(n, 9), True))
    assert out["human_decided"].all()
    return out["human_rt"].squeeze(-1).double()


@pytest.mark.parametrize("preset", ["expert", "distracted"])
def test_rt_matches_the_configured_ex_gaussian_at_zero_workload(preset):
    traits = PRESETS[preset]
    rt = draw_rts(traits, torch.zeros(9))  # at rest and level: zero workload
    mean, var = traits.rt_mu + traits.rt_tau, traits.rt_sigma**2 + traits.rt_tau**2
    assert rt.mean().item() == pytest.approx(mean, abs=4 * (var / len(rt)) ** 0.5)
    assert rt.var().item() == pytest.approx(var, rel=0.06)
    law = exponnorm(traits.rt_tau / traits.rt_sigma, loc=traits.rt_mu, scale=traits.rt_sigma)
    for q in (0.1, 0.5, 0.9):
        assert torch.quantile(rt, q).item() == pytest.approx(law.ppf(q), abs=0.01)


@pytest.mark.parametrize("speed", [0.0, 1.0])
def test_long_rts_occur_at_the_ex_gaussian_rate_and_grow_with_workload(speed):
    traits = PRESETS["distracted"]
    observation = torch.zeros(9)
    observation[3] = -speed  # falling: workload = speed
    rt = draw_rts(traits, observation)
    mu = traits.rt_mu * (1 + traits.workload_gain * speed)
    law = exponnorm(traits.rt_tau / traits.rt_sigma, loc=mu, scale=traits.rt_sigma)
    expected = law.sf(traits.lapse_threshold)
    rate = (rt > traits.lapse_threshold).double().mean().item()
    assert rate == pytest.approx(expected, abs=4 * (expected * (1 - expected) / len(rt)) ** 0.5)
    assert expected > (0.05 if speed == 0 else 0.1)


def test_expert_rarely_passes_t_d_but_does_under_workload():
    traits = PRESETS["expert"]
    busy = torch.zeros(9)
    busy[2:5] = torch.tensor([1.0, -1.0, 0.4])
    calm_rate = (draw_rts(traits, torch.zeros(9)) > 1.0).double().mean().item()
    busy_rate = (draw_rts(traits, busy) > 1.0).double().mean().item()
    assert calm_rate < 0.01 and busy_rate > calm_rate


# --- the decision loop --------------------------------------------------------------


def test_decision_period_holds_and_the_key_changes_only_at_decisions():
    traits = dataclasses.replace(
        PRESETS["noisy"], decision_interval=0.1, lapse_threshold=100.0, perceive_delayed=False
    )
    pilot = SimulatedPilot(traits)  # undelayed: one key held per decision
    assert pilot.decision_period == 5
    rollout = lunar_rollout(pilot, seed=0, steps=40, n_envs=2)
    first, following = rollout[:, :1], rollout["next"]
    decided = torch.cat([first["human_decided"], following["human_decided"]], 1).squeeze(-1)
    keys = torch.cat([first["human_action"], following["human_action"]], 1).argmax(-1)
    frames = torch.arange(decided.shape[1])
    assert decided.equal((frames % 5 == 0).expand_as(decided))
    changed = keys[:, 1:] != keys[:, :-1]
    assert not (changed & ~decided[:, 1:]).any()
    assert changed.any()


def test_a_delayed_pilot_presses_its_planned_keys_frame_by_frame_and_a_lapse_holds_the_last():
    traits = OperatorTraits(rt_mu=1.1, rt_sigma=0.0, rt_tau=0.0, workload_gain=0.0, decision_interval=0.1)
    pilot = SimulatedPilot(traits)  # every RT is 0.1 s past t_d: a 5-frame lapse after each decision
    pilot.plan = lambda perceived: torch.tensor([[1, 2, 3, 0, 2]]).expand(perceived.batch_size[0], -1)
    pilot.reset(0)
    obs = torch.zeros(2, 9)
    keys = torch.stack([pilot(query(obs, t == 0))["human_action"].argmax(-1) for t in range(20)], 1)
    expected = torch.tensor([1, 2, 3, 0, 2, 2, 2, 2, 2, 2] * 2)
    assert keys.tolist() == [expected.tolist()] * 2


def test_a_lapse_delays_the_next_decision_by_the_rt_past_t_d():
    traits = dataclasses.replace(PRESETS["distracted"], rt_tau=0.5)
    pilot = SimulatedPilot(traits)
    pilot.reset(0)
    obs = torch.zeros(16, 9)
    decisions, rts = [], []
    for t in range(150):
        out = pilot(query(obs, t == 0))
        decisions.append(out["human_decided"].squeeze(-1))
        rts.append(out["human_rt"].squeeze(-1))
    decided, rt = torch.stack(decisions, 1), torch.stack(rts, 1)
    lapses = 0
    for env in range(16):
        frames = decided[env].nonzero().squeeze(-1)
        for now, later in zip(frames[:-1].tolist(), frames[1:].tolist(), strict=True):
            excess = max(rt[env, now].item() - traits.lapse_threshold, 0.0)
            assert later - now == pilot.decision_period + round(excess / pilot.frame_seconds)
            lapses += excess > 0
    assert lapses > 0


def test_is_init_restarts_an_env_mid_period():
    pilot = SimulatedPilot(dataclasses.replace(PRESETS["expert"], decision_interval=0.2))
    pilot.reset(0)
    obs = torch.zeros(2, 9)
    assert pilot(query(obs, True))["human_decided"].all()
    assert not pilot(query(obs, False))["human_decided"].any()
    restart = torch.tensor([[True], [False]])
    assert pilot(query(obs, restart))["human_decided"].squeeze(-1).tolist() == [True, False]


def test_noise_and_lag_happen_at_their_configured_rates():
    obs = torch.zeros(20000, 9)
    planned = 0  # the heuristic's key at rest, level, above the pad
    noisy = SimulatedPilot(OperatorTraits(eps=0.3))
    noisy.reset(0)
    keys = noisy(query(obs, True))["human_action"].argmax(-1)
    assert (keys != planned).double().mean().item() == pytest.approx(0.3 * 3 / 4, abs=0.015)

    lag = 0.8  # with eps = 1 every fresh choice is random: repeats happen with q + (1 - q) / 4
    laggy = SimulatedPilot(OperatorTraits(eps=1.0, lag=lag, decision_interval=0.02))
    laggy.reset(0)
    first = laggy(query(obs, True))["human_action"]
    second = laggy(query(obs, False))["human_action"]
    repeats = (first == second).all(-1).double().mean().item()
    assert repeats == pytest.approx(lag + (1 - lag) / 4, abs=0.015)


# --- the UAV operator ---------------------------------------------------------------


def uav_query(obstacles: list[tuple[tuple[float, float, float], float, float]]) -> TensorDict:
    """One env at (0, 0, 5) heading for (10, 0, 5) among (centre, radius, x drift) spheres."""
    params = torch.zeros(1, len(obstacles), N_OBSTACLE_PARAMS)
    for k, (centre, radius, drift_x) in enumerate(obstacles):
        params[0, k, :3] = torch.tensor(centre)
        params[0, k, ObstacleParam.RADIUS] = radius
        params[0, k, ObstacleParam.DRIFT_X] = drift_x
    return TensorDict(
        {
            "position": torch.tensor([[0.0, 0.0, 5.0]]),
            "goal": torch.tensor([[10.0, 0.0, 5.0]]),
            "time": torch.zeros(1, 1),
            "obstacle_params": params,
            "scenario_seed": torch.zeros(1, 1, dtype=torch.int64),
            "is_init": torch.ones(1, 1, dtype=torch.bool),
        },
        [1],
    )


def test_simulated_operator_avoids_the_candidates_that_collide():
    operator = SimulatedOperator(lookahead_noise=0.0)
    oncoming = uav_query([((3.0, 1.2, 5.0), 0.8, -2.0)])  # a sphere flying at the UAV
    scores = operator.score(oncoming)[0]
    assert (scores < -operator.collision_penalty / 2).any()
    choice = operator.plan(oncoming)
    assert scores[choice] == scores.max() and scores[choice] > 0
    operator.reset(0)
    action = operator(oncoming)["human_action"]
    assert action.equal(operator.grid[choice])


def test_simulated_operator_scores_progress_when_nothing_is_near():
    operator = SimulatedOperator(horizon=10)
    scores = operator.score(uav_query([((5.0, 40.0, 5.0), 1.0, 0.0)]))[0]
    assert (scores > 0.5).all()  # about horizon * DT * V0 = 1 closer, no penalty


def test_simulated_operator_workload_grows_near_obstacles():
    operator = SimulatedOperator()
    far = uav_query([((5.0, 40.0, 5.0), 1.0, 0.0)])
    near = uav_query([((1.5, 0.0, 5.0), 1.0, 0.0)])
    assert operator.workload(far).item() == 0.0
    assert operator.workload(near).item() == pytest.approx(operator.near - 0.5)


def test_simulated_operator_rejects_a_bad_grid():
    with pytest.raises(ValueError, match="grid"):
        SimulatedOperator(grid=[[0.0, 1.0, 4.0]])
    with pytest.raises(ValueError, match="lookahead_noise"):
        SimulatedOperator(lookahead_noise=-0.1)


def test_the_compiled_look_ahead_scores_as_the_torch_rollouts_do():
    """The host's compiled loop (float64) and the device path's torch operations (float32)
    score every candidate of real mid-flight states alike, to float32 rounding, and pick
    the same candidate wherever the best is not a near tie."""
    operator = SimulatedOperator.from_preset("expert")
    operator.reset(3)
    env = make_uav_env(12, scenario_seeds=list(range(12)))
    td = env.reset()
    states = []
    for step in range(60):  # fly toward the goal through the obstacles, keep a state every 5 frames
        td["action"] = torch.full((12, 3), 1.5)
        td = env.step(td)["next"]
        if step % 5 == 0:
            states.append(td.select(*operator.in_keys).clone())
    query = torch.cat(states)
    compiled = operator.score(query)
    centres, velocities, radii = operator.predicted_obstacles(query)
    reference = operator.rollout_scores(query["position"], query["goal"], centres, radii, velocities)
    assert compiled.shape == reference.shape == (len(query), operator.n_choices)
    scale = reference.abs().clamp_min(1.0)
    assert ((compiled - reference).abs() / scale).max() < 1e-4
    top2 = reference.topk(2, dim=-1).values
    clear = (top2[:, 0] - top2[:, 1]) > 1e-3
    assert clear.sum() > len(query) // 2
    assert compiled.argmax(-1)[clear].equal(reference.argmax(-1)[clear])


def test_simulated_operator_look_ahead_error_is_a_velocity_error_of_the_set_size():
    operator = SimulatedOperator(lookahead_noise=0.3)
    operator.reset(0)
    query = uav_query([((5.0, 40.0, 5.0), 1.0, 0.0)] * 4).expand(500).clone()
    query["time"] = DT * torch.arange(500.0).unsqueeze(-1)  # 500 decisions, 500 frames
    error = operator.prediction_error(query)
    assert error.shape == (500, 4, 3)
    assert error.std().item() == pytest.approx(0.3, rel=0.1)
    assert error.mean().abs().item() < 0.05
    # the same frame of the same scenario sees the same error; another frame another one
    assert operator.prediction_error(query[:2]).equal(error[:2])
    assert not error[0].equal(error[1])
    # so a rollout's predicted centres drift off linearly with the look-ahead time
    perfect = SimulatedOperator(lookahead_noise=0.0)
    oncoming = uav_query([((3.0, 1.2, 5.0), 0.8, -2.0)])
    assert not operator.score(oncoming).equal(perfect.score(oncoming))


# --- through the transform, in TorchRL ----------------------------------------------


def test_simulated_pilot_passes_check_env_specs():
    transform = HumanOperatorTransform(SimulatedPilot.from_preset("laggy"), seed=0)
    check_env_specs(make_lunar_env(2, transforms=[transform]))


def test_simulated_operator_passes_check_env_specs():
    operator = SimulatedOperator.from_preset("distracted", horizon=3)
    env = make_uav_env(
        2, scenario_seeds=[0, 1], transforms=[HumanOperatorTransform(operator, seed=0)]
    )
    check_env_specs(env)


def test_an_operator_missing_its_keys_says_which():
    with pytest.raises(KeyError, match="obstacle_params"):
        SimulatedOperator()(query(torch.zeros(2, 9), True))


def success_rates(presets: list[str], n_envs: int) -> dict[str, float]:
    rates = {}
    for preset in presets:
        transform = HumanOperatorTransform(SimulatedPilot.from_preset(preset), seed=0)
        env = make_lunar_env(n_envs, random_pad=True, transforms=[transform])
        env.set_seed(0)
        rates[preset] = operator_only_episodes(env, 1000)["success"].float().mean().item()
    return rates


def test_the_scripted_upper_bound_lands_and_the_internal_model_is_what_lets_a_delayed_pilot_land():
    rates = success_rates(["scripted", "expert"], n_envs=16)
    assert rates["scripted"] >= 0.8
    assert rates["expert"] >= 0.4
    blind = SimulatedPilot.from_preset("expert")
    blind.anticipate = lambda perceived, issued, delay: perceived  # the stale frame taken for the present
    env = make_lunar_env(16, random_pad=True, transforms=[HumanOperatorTransform(blind, seed=0)])
    env.set_seed(0)
    assert operator_only_episodes(env, 1000)["success"].float().mean().item() <= rates["expert"] - 0.3


@pytest.mark.slow
def test_operator_only_success_over_50_seeds_orders_the_presets():
    rates = success_rates(list(PRESETS), n_envs=50)
    assert rates["scripted"] >= 0.85
    assert rates["scripted"] >= max(rates["expert"], rates["noisy"], rates["laggy"], rates["distracted"])
    assert rates["expert"] >= max(rates["noisy"], rates["laggy"], rates["distracted"])


def test_a_delayed_operator_acts_on_the_observation_of_one_rt_before_with_the_keys_it_pressed_since():
    """A scripted observation sequence: the frame index is written into obs[0]; the pilot's
    perceived frame (what :meth:`anticipate` receives) must be the frame of RT seconds ago,
    and ``issued`` the keys the pilot itself pressed on the frames from that one to now."""
    traits = OperatorTraits(rt_mu=0.3, rt_sigma=0.0, rt_tau=0.0, workload_gain=0.0, decision_interval=0.1, eps=0.5)
    pilot = SimulatedPilot(traits)
    pilot.reset(0)
    seen = []
    pilot.anticipate = lambda perceived, issued, delay: seen.append(
        (perceived["observation"][:, 0].clone(), issued.clone(), delay.clone())) or perceived
    pressed = []
    for t in range(60):
        obs = torch.zeros(2, 9)
        obs[:, 0] = float(t)
        pressed.append(pilot(query(obs, t == 0))["human_action"].argmax(-1))
    pressed = torch.stack(pressed, 1)
    delay_frames = round(0.3 / pilot.frame_seconds)  # 15 frames at 50 FPS
    decision_frames = range(0, 60, pilot.decision_period)
    for t, (frame, issued, delay) in zip(decision_frames, seen, strict=True):
        expected = max(t - delay_frames, 0)  # never before the episode's first frame
        assert frame.tolist() == [float(expected)] * 2, t
        assert delay.tolist() == [t - expected] * 2
        assert issued[:, : t - expected].equal(pressed[:, expected:t]), t
    assert pressed.unique().numel() > 1  # eps makes the copy worth checking


def test_the_scripted_preset_acts_on_the_current_frame():
    pilot = SimulatedPilot.from_preset("scripted")
    pilot.reset(0)
    seen = []
    pilot.anticipate = lambda perceived, issued, delay: seen.append(perceived["observation"][0, 0].item()) or perceived
    for t in range(20):
        obs = torch.zeros(1, 9)
        obs[:, 0] = float(t)
        pilot(query(obs, t == 0))
    assert seen == [float(t) for t in range(0, 20, pilot.decision_period)]


def test_the_internal_model_knows_gravity_the_main_engine_and_the_ground():
    obs = np.zeros((3, 9))
    obs[:, 1] = 0.5  # half a screen above the pad, level, at rest
    nxt = predict_frame(obs, np.array([0, 2, 0]))
    assert nxt[0, 3] < 0  # free fall
    assert nxt[1, 3] > 0  # the main engine beats gravity
    assert nxt[0, 6] == nxt[0, 7] == 0
    low = obs.copy()
    low[:, 1], low[:, 3] = 0.001, -0.5
    landed = predict_frame(low, np.zeros(3, dtype=np.int64))
    assert (landed[:, 1] == 0).all() and (landed[:, 3] == 0).all() and (landed[:, 6:8] == 1).all()


def test_the_pilot_anticipates_by_stepping_its_model_with_its_own_keys():
    pilot = SimulatedPilot()
    obs = torch.zeros(2, 9)
    obs[:, 1], obs[:, 2], obs[:, 5] = 0.8, 0.2, 0.1
    issued = torch.tensor([[2, 2, 1, 0], [3, 3, 3, 3]])
    guess = pilot.anticipate(TensorDict({"observation": obs}, [2]), issued, torch.tensor([3, 0]))["observation"]
    expected = obs[0].double().numpy()[None]
    for key in (2, 2, 1):
        expected = predict_frame(expected, np.array([key]))
    torch.testing.assert_close(guess[0], torch.as_tensor(expected[0], dtype=torch.float32))
    assert guess[1].equal(obs[1])  # no delay: the frame seen is the present


def test_the_internal_model_is_the_fit_its_docstring_names():
    np.testing.assert_allclose(fit_internal_model(), INTERNAL_MODEL, atol=1e-6)


# --- docs/operators.md ----------------------------------------------------------------


def test_the_example_operator_in_the_docs_runs():
    text = DOCS.read_text()
    block = re.search(r"<!-- example-operator -->\s*```python\n(.*?)```", text, re.S)
    assert block is not None, "docs/operators.md lost its example-operator code block"
    namespace: dict = {}
    exec(compile(block.group(1), str(DOCS), "exec"), namespace)
    rollout = namespace["rollout"]
    assert rollout["human_action"].shape == (2, 50, 4)
    assert rollout["action"].equal(rollout["human_action"])
    decided = rollout["human_decided"].squeeze(-1)
    assert decided[:, ::10].all() and not decided[:, 1:10].any()
