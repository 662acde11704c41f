"""A person flies the UAV at the keyboard, headless: scripted events, a fake clock, SDL's dummy driver."""

from __future__ import annotations

import numpy as np
import pygame
import pytest
import torch
from tensordict import TensorDict
from test_keyboard import FakeClock, RecordingScreen, Script, dummy_display, key  # noqa: F401  (shared)
from torchrl.envs.utils import check_env_specs, step_mdp

from dcsc_torchrl.batched_envs import make_uav_env
from dcsc_torchrl.envs.iifds import iifds_step
from dcsc_torchrl.envs.uav import N_OBSTACLE_PARAMS, ObstacleParam
from dcsc_torchrl.humans import (
    NoDisplayError,
    UAVCommand,
    UAVKeyboardOperator,
    operator_only_policy,
)
from dcsc_torchrl.humans.uav_keyboard import (
    DEFAULT_COMMAND,
    FRAME_SIZE,
    MARGINS,
    WAYS,
    map_pixel,
    uav_frame,
)
from dcsc_torchrl.humans.uav_operator import DEFAULT_GRID
from dcsc_torchrl.transforms import HumanOperatorTransform

FPS = 10  # the env's own time: 1 / DT


def uav_td(
    position: tuple[float, float, float] = (0.0, 0.0, 5.0),
    obstacles: tuple[tuple[float, ...], ...] = ((5.3, 5.3, 5.0, 1.5, 0.0),),
    time: float = 0.0,
    is_init: bool = False,
    batch: tuple[int, ...] = (1,),
) -> TensorDict:
    """One UAV frame by hand: obstacles ``(x, y, z, radius, drift_x)``, each at ``(x, y, z)`` at time 0."""
    params = torch.zeros(len(obstacles), N_OBSTACLE_PARAMS)
    for k, (x, y, z, radius, drift_x) in enumerate(obstacles):
        params[k, [ObstacleParam.CENTRE_X, ObstacleParam.CENTRE_Y, ObstacleParam.CENTRE_Z]] = torch.tensor([x, y, z])
        params[k, ObstacleParam.RADIUS] = radius
        params[k, ObstacleParam.DRIFT_X] = drift_x
    return TensorDict(
        {
            "position": torch.tensor(position).expand(*batch, 3),
            "goal": torch.tensor([10.0, 10.0, 5.5]).expand(*batch, 3),
            "time": torch.full((*batch, 1), time),
            "obstacle_params": params.expand(*batch, *params.shape),
            "is_init": torch.full((*batch, 1), is_init),
        },
        batch,
    )


def scripted_operator(t_d: float = 1.0) -> tuple[UAVKeyboardOperator, RecordingScreen, Script]:
    clock, screen, script = FakeClock(FPS), RecordingScreen(), Script()
    operator = UAVKeyboardOperator(t_d=t_d, screen=screen, clock=clock, time_source=clock.now, events=script,
                                   joystick=False)
    return operator, screen, script


def step(operator: UAVKeyboardOperator, script: Script, *events: pygame.event.Event) -> tuple[list, float, bool]:
    """One frame with ``events``; returns (action, rt, decided)."""
    script.push(*events)
    out = operator(uav_td())
    assert out["human_action"].dtype == torch.float32
    return out["human_action"][0].tolist(), out["human_rt"].item(), bool(out["human_decided"])


def down(code: int) -> pygame.event.Event:
    return key(pygame.KEYDOWN, code)


# --- commands -----------------------------------------------------------------------------


def test_the_nine_commands_are_points_of_the_simulated_operators_grid():
    actions = {UAVCommand(way, margin).action for way in WAYS for margin in MARGINS}
    assert len(actions) == 9 and actions <= set(DEFAULT_GRID)
    assert UAVCommand("right", "tight").action == (0.5, 0.5, 0.0)
    assert UAVCommand("left", "wide").action == (2.5, 2.5, 3.0)
    assert DEFAULT_COMMAND.action == (1.5, 1.5, 1.5)
    with pytest.raises(ValueError, match="way must be one of"):
        UAVCommand("under")


@pytest.mark.parametrize("way", ["left", "over", "right"])
def test_each_way_round_passes_a_static_obstacle_on_its_side(way):
    """Flying +x (left is +y), the command's tau takes the UAV past the obstacle on the side it names."""
    position, goal = torch.tensor([0.0, 0.0, 5.0]), torch.tensor([10.0, 0.0, 5.0])
    centre, radius = torch.tensor([[5.0, 0.0, 5.0]]), torch.tensor([1.5])
    rho0, sigma0, tau = torch.tensor(UAVCommand(way, "medium").action).unbind()
    abeam = position
    for _ in range(200):
        position = iifds_step(position, goal, centre, radius, torch.zeros(1, 3), rho0, sigma0, tau)
        if abs(position[0] - 5.0) < abs(abeam[0] - 5.0):
            abeam = position  # where the UAV passes the obstacle
    lateral, climb = float(abeam[1]), float(abeam[2] - 5.0)
    expected = {"left": lateral > radius and abs(climb) < 1, "right": lateral < -radius and abs(climb) < 1,
                "over": climb > radius and abs(lateral) < 0.5}
    assert expected[way], (lateral, climb)


def test_keys_command_the_way_round_and_the_margin_and_commands_persist():
    operator, _, script = scripted_operator()
    operator(uav_td(is_init=True))
    sequence = [
        ((), "over", "medium", False),  # the default
        ((down(pygame.K_LEFT),), "left", "medium", True),
        ((key(pygame.KEYUP, pygame.K_LEFT),), "left", "medium", False),  # released: it persists
        ((down(pygame.K_3),), "left", "wide", True),
        ((down(pygame.K_DOWN),), "left", "tight", True),  # Down steps the margin on: wide -> tight
        ((down(pygame.K_s),), "left", "medium", True),
        ((down(pygame.K_d), down(pygame.K_KP3)), "right", "wide", True),
        ((down(pygame.K_w),), "over", "wide", True),
        ((down(pygame.K_UP),), "over", "wide", True),  # commanding it again is an answer too
        ((down(pygame.K_SPACE), down(pygame.K_x)), "over", "wide", False),  # not controls
        ((down(pygame.K_a), down(pygame.K_1)), "left", "tight", True),
    ]
    for events, way, margin, decided in sequence:
        action, _, was_decided = step(operator, script, *events)
        assert operator.command == UAVCommand(way, margin)
        assert action == list(UAVCommand(way, margin).action)
        assert was_decided == decided, events


def test_a_joystick_hat_picks_the_way_round_and_steps_the_margin():
    operator, _, script = scripted_operator()
    operator(uav_td(is_init=True))
    hat = [((-1, 0), "left", "medium", True), ((0, 0), "left", "medium", False), ((1, 0), "right", "medium", True),
           ((0, 1), "over", "medium", True), ((0, -1), "over", "wide", True), ((0, -1), "over", "tight", True)]
    for value, way, margin, decided in hat:
        _, _, was_decided = step(operator, script, pygame.event.Event(pygame.JOYHATMOTION, value=value))
        assert (operator.command, was_decided) == (UAVCommand(way, margin), decided)


# --- timing -------------------------------------------------------------------------------


def test_rts_are_timed_from_the_frame_shown_and_t_d_makes_a_slow_decision():
    operator, _, script = scripted_operator(t_d=0.95)
    operator(uav_td(is_init=True))  # frame 1 shown at 0.1 s: the timing starts
    assert [step(operator, script)[2] for _ in range(2)] == [False, False]
    _, rt, decided = step(operator, script, down(pygame.K_RIGHT))
    assert decided and rt == pytest.approx(3 / FPS)  # frame 4 - frame 1
    _, rt, decided = step(operator, script, down(pygame.K_3))
    assert decided and rt == pytest.approx(1 / FPS)
    idle = [step(operator, script) for _ in range(10)]
    assert [decided for _, _, decided in idle] == [False] * 9 + [True]  # 1.0 s > t_d after frame 5
    assert [rt for _, rt, _ in idle] == pytest.approx([1 / FPS] * 9 + [1.0])  # between decisions: the last RT


def test_an_episode_starts_from_the_default_command_with_a_fresh_path():
    operator, screen, script = scripted_operator()
    operator.status = ["b_h (you): 0.90"]
    operator(uav_td(is_init=True))
    step(operator, script, down(pygame.K_LEFT), down(pygame.K_3))
    step(operator, script)
    start = (1.0, 2.0, 5.0)
    script.push(down(pygame.K_RIGHT))  # read after the episode's start: it counts
    out = operator(uav_td(start, is_init=True))
    assert operator.command == UAVCommand("right", "medium") and not out["human_decided"].item()
    frame, lines = screen.shown[-1]
    assert np.array_equal(frame, uav_frame(uav_td(start), np.array([start])))  # the path restarted
    assert lines[0] == "b_h (you): 0.90" and lines[1] == f"you: {UAVCommand('right', 'medium').describe()}"


def test_a_command_given_during_the_prompt_gives_way_to_the_episodes_default():
    operator, _, script = scripted_operator()
    script.push(down(pygame.K_LEFT), down(pygame.K_SPACE))
    assert operator.prompt(["Episode 1 of 2 — press Space to start"]) is True
    operator(uav_td(is_init=True))
    assert operator.command == DEFAULT_COMMAND


def test_one_person_flies_one_uav():
    operator, _, _ = scripted_operator()
    assert operator(uav_td(is_init=True, batch=()))["human_action"].shape == (3,)
    assert operator(uav_td(is_init=True, batch=(1,)))["human_action"].shape == (1, 3)
    with pytest.raises(ValueError, match=r"one person flies one UAV: .* needs a batch of one env .* got \(2,\)"):
        operator(uav_td(is_init=True, batch=(2,)))


# --- the frame ----------------------------------------------------------------------------


def pixel(frame: np.ndarray, x: float, y: float) -> tuple[int, ...]:
    column, row = map_pixel(x, y)
    return tuple(frame[row, column])


def test_the_frame_shows_the_uav_and_fills_an_obstacle_only_where_it_cuts_the_uavs_altitude():
    level = uav_frame(uav_td((0.0, 0.0, 5.0)))
    above = uav_frame(uav_td((0.0, 0.0, 7.0)))  # 2 above the centre, radius 1.5: flies over it
    assert level.shape == (FRAME_SIZE[1], FRAME_SIZE[0], 3) and level.dtype == np.uint8
    assert pixel(level, 0.0, 0.0) == (255, 255, 255)  # the UAV
    empty = pixel(level, 11.3, 1.3)
    assert pixel(level, 5.3, 5.3) != empty  # the slice at its altitude, filled
    assert pixel(above, 5.3, 5.3) == empty and pixel(above, 5.3 + 1.44, 5.3) != empty  # the ring only (2 px)


def test_the_frame_changes_when_an_obstacle_moves_and_only_then():
    moving = ((5.3, 5.3, 5.0, 1.5, 1.0),)
    assert not np.array_equal(uav_frame(uav_td(obstacles=moving)), uav_frame(uav_td(obstacles=moving, time=1.0)))
    assert np.array_equal(uav_frame(uav_td()), uav_frame(uav_td(time=1.0)))  # a static one
    path = np.array([[0.0, 0.0, 5.0], [3.0, 0.0, 5.0]])
    assert pixel(uav_frame(uav_td(), path), 1.5, 0.0) != pixel(uav_frame(uav_td()), 1.5, 0.0)  # the path drawn


# --- in the env ---------------------------------------------------------------------------


@pytest.mark.usefixtures("dummy_display")
def test_a_person_flies_the_uav_env_in_a_window():
    clock = FakeClock(FPS)
    operator = UAVKeyboardOperator(clock=clock, time_source=clock.now, joystick=False)  # a pygame window
    env = make_uav_env(1, scenario_seeds=[0], transforms=[HumanOperatorTransform(operator, seed=0)])
    policy = operator_only_policy()
    td = env.reset()
    start = td["position"][0].clone()
    presses = {2: pygame.K_LEFT, 5: pygame.K_3}
    actions = []
    for frame in range(8):
        if frame in presses:
            pygame.event.post(down(presses[frame]))
        td = env.step(policy(td))
        actions.append(td["action"][0].tolist())
        td = step_mdp(td)
    # a key read on frame i commands the action of step i + 1
    assert actions == [[1.5, 1.5, 1.5]] * 3 + [[1.5, 1.5, 3.0]] * 3 + [[2.5, 2.5, 3.0]] * 2
    assert (td["position"][0] - start).norm() > 0.5
    window = pygame.surfarray.array3d(pygame.display.get_surface()).swapaxes(0, 1)
    assert pixel(window, *td["position"][0, :2].tolist()) == (255, 255, 255)  # the UAV, where it is now
    operator.close()


def test_the_uav_keyboard_operator_passes_check_env_specs():
    clock = FakeClock(FPS)
    operator = UAVKeyboardOperator(screen=RecordingScreen(), clock=clock, time_source=clock.now, events=list,
                                   joystick=False)
    check_env_specs(make_uav_env(1, scenario_seeds=[0], transforms=[HumanOperatorTransform(operator, seed=0)]))


def test_no_display_points_to_the_simulated_uav_operator(monkeypatch):
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(NoDisplayError, match=r"SimulatedOperator\.from_preset\('expert'\)"):
        UAVKeyboardOperator()
