"""The keyboard pilot and `dcsc play`, headless: SDL's dummy driver, posted keys, a fake clock."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pygame
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import GymWrapper, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs

from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.checkpoint import save_checkpoint
from dcsc_torchrl.cli import main as dcsc
from dcsc_torchrl.humans import KeyboardPilot, NoDisplayError
from dcsc_torchrl.networks import lunar_actor, lunar_critic
from dcsc_torchrl.recipes.play import (
    PlayRecorder,
    load_machine,
    make_learner,
    make_play_env,
    make_policy,
    play,
    play_config,
)
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

FPS = 50


class FakeClock:
    """``tick`` advances a frame counter; the time source reads frames / fps (no sleeping)."""

    def __init__(self, fps: float = FPS) -> None:
        self.fps = fps
        self.frames = 0

    def tick(self, framerate: float) -> int:
        assert framerate == self.fps
        self.frames += 1
        return round(1000 / self.fps)

    def now(self) -> float:
        return self.frames / self.fps


class RecordingScreen:
    """Keeps what the pilot shows."""

    def __init__(self) -> None:
        self.shown: list[tuple[np.ndarray | None, list[str]]] = []

    def show(self, frame: np.ndarray | None, lines) -> None:
        self.shown.append((frame, list(lines)))

    def close(self) -> None:
        self.shown.append((None, ["closed"]))


@pytest.fixture
def dummy_display(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    pygame.display.init()
    pygame.event.clear()
    yield
    pygame.display.quit()


def frame_td(is_init: bool, batch: tuple[int, ...] = ()) -> TensorDict:
    return TensorDict(
        {"observation": torch.zeros(*batch, 9), "is_init": torch.full((*batch, 1), is_init)}, batch
    )


def step(pilot: KeyboardPilot, *events: pygame.event.Event) -> tuple[int, float, bool]:
    """Posts ``events``, runs one frame; returns (action, rt, decided)."""
    for event in events:
        pygame.event.post(event)
    out = pilot(frame_td(False))
    return int(out["human_action"].argmax()), out["human_rt"].item(), bool(out["human_decided"])


def key(kind: int, code: int) -> pygame.event.Event:
    return pygame.event.Event(kind, key=code)


def test_posted_keys_give_their_actions_and_rts_from_the_frame_shown(dummy_display):
    clock = FakeClock()
    frame = np.zeros((400, 600, 3), dtype=np.uint8)
    pilot = KeyboardPilot(frame_source=lambda: frame, clock=clock, time_source=clock.now, t_d=0.99)
    pilot.reset(0)
    pilot(frame_td(True))  # frame 1 shown at 0.02 s: the timing starts
    assert step(pilot)[2] is False
    assert step(pilot)[2] is False
    action, rt, decided = step(pilot, key(pygame.KEYDOWN, pygame.K_UP))
    assert (action, decided) == (2, True) and rt == pytest.approx(3 / FPS)  # frame 4 - frame 1
    action, rt, decided = step(pilot, key(pygame.KEYDOWN, pygame.K_LEFT))  # the last pressed wins
    assert (action, decided) == (1, True) and rt == pytest.approx(1 / FPS)
    action, rt, decided = step(pilot, key(pygame.KEYUP, pygame.K_LEFT))
    assert (action, decided) == (2, True) and rt == pytest.approx(1 / FPS)
    held = [step(pilot) for _ in range(3)]
    assert held == [(2, pytest.approx(1 / FPS), False)] * 3  # between decisions: the last RT
    action, rt, decided = step(
        pilot, key(pygame.KEYUP, pygame.K_UP), key(pygame.KEYDOWN, pygame.K_RIGHT)
    )
    assert (action, decided) == (3, True) and rt == pytest.approx(4 / FPS)


def test_no_change_for_longer_than_t_d_is_a_decision_with_rt_above_t_d(dummy_display):
    clock = FakeClock()
    pilot = KeyboardPilot(clock=clock, time_source=clock.now, t_d=0.99)
    pilot(frame_td(True))
    results = [step(pilot) for _ in range(120)]
    decisions = [i for i, (_, _, decided) in enumerate(results) if decided]
    assert decisions == [49, 99]  # 50 frames (1.0 s > t_d) after each timing start
    assert results[49][1] == pytest.approx(1.0) and results[99][1] == pytest.approx(1.0)
    assert all(action == 0 for action, _, _ in results)


def test_is_init_restarts_the_timing_but_keeps_the_held_keys(dummy_display):
    clock = FakeClock()
    pilot = KeyboardPilot(clock=clock, time_source=clock.now)
    pilot(frame_td(True))
    step(pilot, key(pygame.KEYDOWN, pygame.K_UP))
    for _ in range(10):
        step(pilot)
    out = pilot(frame_td(True))
    assert not out["human_decided"].item() and out["human_action"].argmax().item() == 2
    action, rt, decided = step(pilot, key(pygame.KEYUP, pygame.K_UP))
    assert (action, decided) == (0, True) and rt == pytest.approx(1 / FPS)


def test_joystick_events_steer_like_the_arrow_keys():
    clock = FakeClock()
    queue: list[pygame.event.Event] = []

    def events():
        pending = list(queue)
        queue.clear()
        return pending

    pilot = KeyboardPilot(
        screen=RecordingScreen(), clock=clock, time_source=clock.now, events=events, joystick=False
    )
    pilot(frame_td(True))
    expected = [
        (pygame.event.Event(pygame.JOYHATMOTION, value=(0, 1)), 2),
        (pygame.event.Event(pygame.JOYHATMOTION, value=(-1, 0)), 1),
        (pygame.event.Event(pygame.JOYHATMOTION, value=(0, 0)), 0),
        (pygame.event.Event(pygame.JOYAXISMOTION, axis=0, value=0.9), 3),
        (pygame.event.Event(pygame.JOYAXISMOTION, axis=0, value=0.1), 0),
        (pygame.event.Event(pygame.JOYBUTTONDOWN, button=0), 2),
        (pygame.event.Event(pygame.JOYBUTTONUP, button=0), 0),
    ]
    for event, action in expected:
        queue.append(event)
        out = pilot(frame_td(False))
        assert out["human_action"].argmax().item() == action and out["human_decided"].item()


def test_frames_and_status_lines_are_shown_every_frame_and_quit_is_noticed():
    clock = FakeClock()
    screen = RecordingScreen()
    queue = [pygame.event.Event(pygame.QUIT)]
    pilot = KeyboardPilot(
        frame_source=lambda: np.full((4, 6, 3), clock.frames, dtype=np.uint8),
        screen=screen,
        clock=clock,
        time_source=clock.now,
        events=lambda: [queue.pop()] if queue else [],
        joystick=False,
    )
    pilot.status = ["b_h: 0.10"]
    pilot(frame_td(True))
    pilot(frame_td(False))
    assert [frame[0, 0, 0] for frame, _ in screen.shown] == [1, 2]
    assert all(lines == ["b_h: 0.10"] for _, lines in screen.shown)
    assert pilot.quit_requested


def test_one_person_flies_one_lander():
    pilot = KeyboardPilot(screen=RecordingScreen(), clock=FakeClock(), events=list, joystick=False)
    assert pilot(frame_td(True, (1,)))["human_action"].shape == (1, 4)
    with pytest.raises(ValueError, match="one env"):
        pilot(frame_td(True, (2,)))


def test_no_display_raises_a_clear_error(monkeypatch):
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(NoDisplayError, match=r"SimulatedPilot\.from_preset\('expert'\)"):
        KeyboardPilot()


def test_a_display_that_fails_to_open_raises_a_clear_error(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")

    def fail() -> None:
        raise pygame.error("video driver unavailable")

    monkeypatch.setattr(pygame.display, "init", fail)
    with pytest.raises(RuntimeError, match="video driver unavailable.*simulated operator"):
        KeyboardPilot()


def test_keyboard_pilot_passes_check_env_specs():
    clock = FakeClock()
    pilot = KeyboardPilot(
        screen=RecordingScreen(), clock=clock, time_source=clock.now, events=list, joystick=False
    )
    env = TransformedEnv(GymWrapper(gym.make(LUNAR_ID)), HumanOperatorTransform(pilot, seed=0))
    check_env_specs(env)


# --- the prompt between episodes (PersonAtControls.prompt) ---------------------------


class Script:
    """An event source: returns its batches of events, one per call, then nothing."""

    def __init__(self) -> None:
        self.batches: list[list[pygame.event.Event]] = []

    def push(self, *events: pygame.event.Event) -> None:
        """Queues one call's events."""
        self.batches.append(list(events))

    def __call__(self) -> list[pygame.event.Event]:
        return self.batches.pop(0) if self.batches else []


def prompting_pilot() -> tuple[KeyboardPilot, RecordingScreen, Script]:
    screen, script, clock = RecordingScreen(), Script(), FakeClock()
    pilot = KeyboardPilot(screen=screen, clock=clock, time_source=clock.now, events=script, joystick=False)
    return pilot, screen, script


@pytest.mark.parametrize("start_key", [pygame.K_SPACE, pygame.K_RETURN])
def test_prompt_shows_its_lines_until_space_or_enter(start_key):
    pilot, screen, script = prompting_pilot()
    lines = ["Episode 3 of 10: DC-SC shares control", "press Space to start"]
    script.push()
    script.push(key(pygame.KEYDOWN, pygame.K_UP))
    script.push(key(pygame.KEYDOWN, start_key))
    assert pilot.prompt(lines) is True
    assert screen.shown == [(None, lines)] * 3  # a blank frame with the lines, once per frame waited
    assert pilot.action == 2 and not pilot.quit_requested  # the controls follow the keys meanwhile


@pytest.mark.parametrize("quit_event", [key(pygame.KEYDOWN, pygame.K_ESCAPE), key(pygame.KEYDOWN, pygame.K_q),
                                        pygame.event.Event(pygame.QUIT)], ids=["escape", "q", "close"])
def test_prompt_returns_false_when_the_person_quits(quit_event):
    pilot, screen, script = prompting_pilot()
    script.push(quit_event, key(pygame.KEYDOWN, pygame.K_SPACE))  # a quit wins over a start
    assert pilot.prompt(["press Space"]) is False
    assert pilot.quit_requested and len(screen.shown) == 1
    assert pilot.prompt(["press Space"]) is False and len(screen.shown) == 1  # after a quit: at once


def test_a_key_released_during_the_prompt_is_released():
    pilot, _, script = prompting_pilot()
    pilot(frame_td(True))
    script.push(key(pygame.KEYDOWN, pygame.K_UP))
    pilot(frame_td(False))
    script.push(key(pygame.KEYUP, pygame.K_UP), key(pygame.KEYDOWN, pygame.K_SPACE))
    assert pilot.prompt(["press Space"]) is True and pilot.action == 0


# --- dcsc play ------------------------------------------------------------------------


def play_session(machine, *, critic=None, out=None, episodes=1, events=list, exploration_type=ExplorationType.RANDOM,
                 theta_init=None, ida=False, copilot=None, state=None):
    clock = FakeClock()
    render_env = gym.make(LUNAR_ID, render_mode="rgb_array")
    screen = RecordingScreen()
    pilot = KeyboardPilot(
        frame_source=render_env.render,
        screen=screen,
        clock=clock,
        time_source=clock.now,
        events=events,
        joystick=False,
    )
    env = make_play_env(render_env, pilot, HumanConfidenceTransform(), seed=0)
    cfg = play_config()
    if theta_init is not None:
        cfg.arbiter.centred.theta_init = theta_init
    policy = make_policy(env, machine, cfg, q_value=critic if ida else None, copilot=copilot, state_arbiter=state)
    learner = (state.learner(policy) if state is not None
               else make_learner(policy, critic, cfg) if critic is not None and not ida else None)
    recorder = None
    if out is not None:
        method = ("ida" if ida else "reddy" if copilot is not None else "dcsc_state" if state is not None
                  else "dcsc_centred" if machine is not None else "operator")
        recorder = PlayRecorder(out, method, "tester")
    summaries = play(env, policy, pilot, episodes=episodes, learner=learner, rollout_length=5, recorder=recorder,
                     exploration_type=exploration_type)
    return summaries, screen, policy, learner


def test_play_alone_flies_an_episode_and_shows_every_frame():
    summaries, screen, _, _ = play_session(machine=None)
    assert len(summaries) == 1 and summaries[0]["steps"] > 0
    assert len(screen.shown) == summaries[0]["steps"] + 1  # the reset frame and one per step
    frame, lines = screen.shown[-1]
    assert frame.shape == (400, 600, 3)
    labels = [line.split(":")[0] for line in lines]
    assert "b_h (you)" in labels and "beta (machine share)" not in labels


def tiny_checkpoint(tmp_path):
    hidden, dropout = [16], 0.01
    torch.manual_seed(0)
    state = {
        "actor": lunar_actor(hidden, dropout).state_dict(),
        "qvalue": lunar_critic(hidden, 4, obs_dims=9).state_dict(),
    }
    return save_checkpoint(
        tmp_path / "checkpoint.pt",
        task="lunarlander",
        payload={
            "config": {"network": {"hidden": hidden, "actor_dropout": dropout}},
            "state": state,
        },
    )


def test_play_with_dcsc_loads_the_machine_and_shows_both_confidences(tmp_path):
    actor, _ = load_machine(tiny_checkpoint(tmp_path))
    summaries, screen, _, _ = play_session(machine=actor)
    assert len(summaries) == 1
    labels = [line.split(":")[0] for line in screen.shown[-1][1]]
    assert {"b_h (you)", "b_m (machine)", "beta (machine share)"} <= set(labels)


def test_play_with_dcsc_learns_online_and_writes_the_simulated_runs_files(tmp_path):
    import pandas as pd

    actor, critic = load_machine(tiny_checkpoint(tmp_path))
    critic_before = [p.detach().clone() for p in critic.parameters()]
    out = tmp_path / "study"
    summaries, _, policy, learner = play_session(machine=actor, critic=critic, out=out, episodes=2)
    steps = sum(s["steps"] for s in summaries)
    online = play_config().online
    assert len(summaries) == 2 and len(learner.history) == steps // 5 * online.updates_per_batch  # every 5 frames
    assert any(h["theta"] != [0.0] for h in learner.history)  # theta starts at the yaml's 0 and moves
    critic_moved = any((a != b).any() for a, b in zip(critic_before, critic.parameters(), strict=True))
    assert critic_moved == (online.critic_lr > 0)  # the simulated runs' setting: LunarLander holds its critic
    episodes = pd.read_csv(out / "episodes.csv")
    assert episodes[["method", "phase", "seed", "steps"]].values.tolist() == [
        ["dcsc_centred", "play", 0, summaries[0]["steps"]], ["dcsc_centred", "play", 1, summaries[1]["steps"]]]
    assert episodes["theta"].iloc[-1] == pytest.approx(float(policy["arbiter"].theta.detach()[0]))
    trace = pd.read_csv(out / "trace.csv")
    assert len(trace) == steps
    for column in ("operator_action", "machine_action", "shared_action", "human_rt", "knowledge",
                   "human_confidence", "machine_uncertainty", "machine_confidence", "beta"):
        assert trace[column].notna().all(), column
    assert trace.groupby("episode")["step"].max().tolist() == [s["steps"] for s in summaries]


def test_play_with_ida_hands_over_whole_frames_by_the_machines_q_and_learns_nothing(tmp_path):
    import pandas as pd

    actor, critic = load_machine(tiny_checkpoint(tmp_path))
    critic_before = [p.detach().clone() for p in critic.parameters()]
    summaries, _, policy, learner = play_session(machine=actor, critic=critic, out=tmp_path / "study", ida=True)
    assert learner is None and type(policy["arbiter"]).__name__ == "InterventionArbiter"
    assert all((a == b).all() for a, b in zip(critic_before, critic.parameters(), strict=True))
    trace = pd.read_csv(tmp_path / "study" / "trace.csv")
    assert len(trace) == summaries[0]["steps"] and set(trace["beta"].unique()) <= {0.0, 1.0}
    assert pd.read_csv(tmp_path / "study" / "episodes.csv")["method"].tolist() == ["ida"]


def test_play_with_reddys_copilot_hands_it_exactly_the_frames_outside_the_tolerance(tmp_path):
    import pandas as pd

    from dcsc_torchrl.copilot import TrainedCopilot
    from dcsc_torchrl.tasks import get_task

    torch.manual_seed(0)
    network = get_task("lunarlander").make_copilot_network([8]).requires_grad_(False)
    copilot = TrainedCopilot(network, 0.3, ("surrogate_noisy",))
    summaries, _, policy, learner = play_session(machine=None, out=tmp_path / "study", copilot=copilot,
                                                 exploration_type=ExplorationType.MODE)
    assert learner is None and type(policy["arbiter"]).__name__ == "ToleranceArbiter"
    trace = pd.read_csv(tmp_path / "study" / "trace.csv")
    assert len(trace) == summaries[0]["steps"] and set(trace["beta"].unique()) <= {0.0, 1.0}
    assert pd.read_csv(tmp_path / "study" / "episodes.csv")["method"].tolist() == ["reddy"]


def test_play_with_the_state_dependent_arbiter_fine_tunes_it_and_leaves_the_pretrained_one_alone(tmp_path):
    import pandas as pd

    from dcsc_torchrl.online import PolicyGradientLearner
    from dcsc_torchrl.state_arbiter import (
        PretrainedArbiter,
        StateDependentArbiter,
        state_value_network,
    )

    actor, _ = load_machine(tiny_checkpoint(tmp_path))
    torch.manual_seed(0)
    arbiter = StateDependentArbiter(9, 4, hidden=(8,))
    settings = {"algorithm": "policy_gradient", "lr": 1e-3, "gamma": 0.99, "gae_lambda": 1.0, "entropy_coeff": 0.0,
                "critic_coeff": 0.5, "max_grad_norm": 0.5, "segment_length": 5}
    pretrained = PretrainedArbiter(arbiter, state_value_network(9, (8,)), settings, ("expert",), "machine")
    before = {k: v.clone() for k, v in arbiter.state_dict().items() if isinstance(v, torch.Tensor)}
    summaries, _, policy, learner = play_session(machine=actor, out=tmp_path / "study", state=pretrained)
    assert type(policy["arbiter"]).__name__ == "StateDependentArbiter" and policy["arbiter"] is not arbiter
    assert isinstance(learner, PolicyGradientLearner) and len(learner.history) >= summaries[0]["steps"] // 5
    assert all(torch.equal(before[k], v) for k, v in arbiter.state_dict().items() if k in before)
    assert pd.read_csv(tmp_path / "study" / "episodes.csv")["method"].tolist() == ["dcsc_state"]


def test_play_with_an_arbiter_of_another_machine_or_none_says_so(tmp_path, capsys):
    assert dcsc(["play", "lunarlander", "--assist", "state", "--arbiter", str(tmp_path / "none.pt")]) == 2
    assert "dcsc arbiter lunarlander" in capsys.readouterr().err


def test_play_without_a_copilot_says_how_to_get_one(tmp_path, capsys):
    assert dcsc(["play", "lunarlander", "--assist", "reddy", "--copilot", str(tmp_path / "none.pt")]) == 2
    assert "dcsc copilot" in capsys.readouterr().err


@pytest.mark.parametrize("exploration_type", [ExplorationType.MODE, ExplorationType.RANDOM])
def test_play_takes_the_shared_key_as_protocol_shared_action_says(tmp_path, exploration_type):
    """``mode``: below half the authority the machine never outweighs the person's key; ``sample``: it may."""
    import pandas as pd

    actor, _ = load_machine(tiny_checkpoint(tmp_path))
    # theta -3: beta = sigmoid(-3 + 3 (2 b_t - 1)) < 1/2 on every frame where b_t < 1
    play_session(machine=actor, out=tmp_path / "study", exploration_type=exploration_type, theta_init=-3.0)
    trace = pd.read_csv(tmp_path / "study" / "trace.csv")
    minority = trace[trace["beta"] < 0.5]
    assert len(minority) > 20
    kept = (minority["shared_action"] == minority["operator_action"]).all()
    assert kept == (exploration_type == ExplorationType.MODE)


def test_play_alone_writes_the_files_with_empty_machine_columns(tmp_path):
    import pandas as pd

    summaries, _, _, _ = play_session(machine=None, out=tmp_path)
    trace = pd.read_csv(tmp_path / "trace.csv")
    assert len(trace) == summaries[0]["steps"] and (trace["beta"] == 0).all()
    assert trace["machine_confidence"].isna().all() and trace["machine_action"].isna().all()
    assert pd.read_csv(tmp_path / "episodes.csv")["method"].tolist() == ["operator"]


def test_quitting_mid_episode_keeps_the_frames_flown(tmp_path):
    import pandas as pd

    queue = [pygame.event.Event(pygame.KEYDOWN, key=pygame.K_ESCAPE)]
    frames = {"n": 0}

    def events():  # Esc on the 13th frame
        frames["n"] += 1
        return [queue.pop()] if frames["n"] == 13 and queue else []

    summaries, _, _, _ = play_session(machine=None, out=tmp_path, events=events)
    assert summaries == []
    assert len(pd.read_csv(tmp_path / "trace.csv")) == 12  # the reset frame asks too: 12 steps
    assert not (tmp_path / "episodes.csv").exists()


def test_play_with_a_display_that_does_not_answer_fails_with_one_line(monkeypatch, capsys):
    # SDL falls back to its invisible offscreen driver when DISPLAY's server is not running
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    monkeypatch.setenv("DISPLAY", ":99")
    monkeypatch.setattr(pygame.display, "init", lambda: None)
    monkeypatch.setattr(pygame.display, "set_mode", lambda size: None)
    monkeypatch.setattr(pygame.display, "get_driver", lambda: "offscreen")
    assert dcsc(["play", "lunarlander", "--assist", "none"]) == 2
    err = capsys.readouterr().err
    assert "DISPLAY=:99 is set but no display server answers there" in err and err.count("\n") == 1


def test_play_without_a_checkpoint_says_how_to_get_one(tmp_path, capsys):
    assert dcsc(["play", "lunarlander", "--checkpoint", str(tmp_path / "missing.pt")]) == 2
    assert "dcsc pretrain lunarlander" in capsys.readouterr().err


def test_play_without_a_display_points_to_the_simulated_pilot(monkeypatch, capsys):
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
        monkeypatch.delenv(var, raising=False)
    assert dcsc(["play", "lunarlander", "--assist", "none"]) == 2
    assert "SimulatedPilot" in capsys.readouterr().err


def test_keyboard_pilot_rejects_a_bad_t_d():
    with pytest.raises(ValueError, match="t_d"):
        KeyboardPilot(t_d=0.0, screen=RecordingScreen(), events=list, joystick=False)
