"""`dcsc study`: a scripted participant through the paper's protocol, headless (SDL's dummy
driver, posted keys, a fake clock), on both tasks; resume, refusals, counterbalancing."""

from __future__ import annotations

import copy
import json
from collections import Counter
from pathlib import Path

import pandas as pd
import pygame
import pytest
import torch

from dcsc_torchrl.cli import main as dcsc
from dcsc_torchrl.config import ConfigError
from dcsc_torchrl.humans import KeyboardPilot, UAVKeyboardOperator
from dcsc_torchrl.protocol import ProtocolCell, Scenarios
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.recipes.study import (
    PERSON_METHODS,
    first_episode_update,
    gather_participants,
    run_study,
    study_plan,
    validation_order,
)
from dcsc_torchrl.shipped import shipped_machine, shipped_path
from dcsc_torchrl.tasks import get_task

SHIPPED = ["pretrain.shipped=true", "pretrain.seeds=[0]"]
SMALL = ["scenarios.operator_runs=2", "scenarios.collaboration_runs=1", "scenarios.validation_scenarios=2",
         "protocol.group_size=1"]
"""Two practice runs, one collaboration run, two validation scenarios a method."""


class ScriptedParticipant:
    """A participant who starts every episode at once (Space) and then presses the ``keys`` in
    turn, each for ``hold`` frames; with ``quit_after`` frames, presses Escape then.

    Its ``clock`` and ``now`` are the fake clock and time source of the person's controls.
    """

    def __init__(self, keys: list[int], hold: int = 10, quit_after: int | None = None) -> None:
        self.keys, self.hold, self.quit_after = keys, hold, quit_after
        self.calls = 0
        self.frames = 0

    def tick(self, framerate: float) -> int:
        self.frames += 1
        return 0

    def now(self) -> float:
        return self.frames / 50

    def events(self) -> list[pygame.event.Event]:
        self.calls += 1
        if self.quit_after is not None and self.calls >= self.quit_after:
            return [pygame.event.Event(pygame.KEYDOWN, key=pygame.K_ESCAPE)]
        key = self.keys[(self.calls // self.hold) % len(self.keys)]
        events = [pygame.event.Event(pygame.KEYDOWN, key=pygame.K_SPACE)]
        if self.calls % self.hold == 0:
            events.append(pygame.event.Event(pygame.KEYDOWN, key=key))
        return events


class Screen:
    def __init__(self) -> None:
        self.lines: list[list[str]] = []

    def show(self, frame, lines) -> None:
        self.lines.append(list(lines))

    def close(self) -> None:
        pass


def lunar_person(script: ScriptedParticipant) -> KeyboardPilot:
    return KeyboardPilot(screen=Screen(), clock=script, events=script.events, time_source=script.now, joystick=False)


def uav_person(script: ScriptedParticipant) -> UAVKeyboardOperator:
    return UAVKeyboardOperator(screen=Screen(), clock=script, events=script.events, time_source=script.now,
                               joystick=False)


PEOPLE = {"lunarlander": (lunar_person, [pygame.K_UP, pygame.K_LEFT, pygame.K_UP, pygame.K_RIGHT]),
          "uav": (uav_person, [pygame.K_LEFT, pygame.K_RIGHT, pygame.K_UP])}


def study(task: str, out: Path, script: ScriptedParticipant, participant: str = "p1", overrides=()) -> Path:
    make, _ = PEOPLE[task]
    return run_study(get_task(task), participant, out=out, quick=True, person=make(script),
                     overrides=[*SHIPPED, *SMALL, *overrides])


# -- the plan -------------------------------------------------------------------------------
def test_validation_order_is_counterbalanced():
    methods = ["dcsc_centred", "hula", "operator"]
    orders = [validation_order(methods, i, "anna") for i in range(6)]
    assert len({tuple(order) for order in orders}) == 6  # every permutation once in 6 scenarios
    for position in range(3):
        assert Counter(order[position] for order in orders) == dict.fromkeys(methods, 2)
    before = Counter((a, b) for order in orders for i, a in enumerate(order) for b in order[i + 1:])
    assert set(before.values()) == {3}  # each method precedes each other equally often
    assert validation_order(methods, 0, "anna") != validation_order(methods, 0, "bob")  # participants differ


def test_study_plan_flies_every_method_on_the_same_scenarios():
    scenarios = Scenarios.standard(operator_runs=3, collaboration_runs=2, validation_scenarios=4)
    plan = study_plan(scenarios, "dcsc_centred", "p1")
    assert [e.phase for e in plan[:5]] == ["operator_alone"] * 3 + ["collaboration"] * 2
    assert [e.seeds for e in plan[:3]] == [(10_000,), (10_001,), (10_002,)]
    machine = [e for e in plan if e.method == "machine"]
    assert len(machine) == 1 and machine[0].seeds == (0, 1, 2, 3) and not machine[0].person
    for method in ("dcsc_centred", *PERSON_METHODS):
        assert [e.seeds for e in plan if e.phase == "validation" and e.method == method] == [(0,), (1,), (2,), (3,)]


def test_learner_state_dict_continues_exactly():
    task = get_task("lunarlander")
    cfg = task_config(task, SHIPPED, quick=True)
    settings = cell_settings(cfg)
    actor, critic = shipped_machine(task, "blind")
    cell = ProtocolCell(task, task.make_operator("expert"), actor, base={}, pretrain_seed=0,
                        human=settings["human"], machine=settings["machine"], arbiter=settings["arbiter"],
                        online={**settings["online"], "critic_lr": 1e-3}, protocol=settings["protocol"])
    cell.critic = critic
    first = cell.learner(cell.policy("dcsc_centred"))
    batch = cell.play("collaboration", "dcsc_centred", [20_000, 20_001], first.policy, update=first).frames
    second = cell.learner(cell.policy("dcsc_centred"))
    second.load_state_dict(copy.deepcopy(first.state_dict()))
    assert second.history == first.history
    update = batch[:40].unsqueeze(0)
    first(update)
    second(update)
    assert torch.equal(first.policy["arbiter"].theta, second.policy["arbiter"].theta)
    assert first.history[-1] == second.history[-1]


def test_first_episode_update_reads_only_the_episode_flown():
    seen = []
    done = torch.tensor([[False, False, True, False, False]]).unsqueeze(-1)
    batch = torch.arange(5).reshape(1, 5)
    from tensordict import TensorDict

    first_episode_update(seen.append)(TensorDict({"x": batch, ("next", "done"): done}, [1, 5]))
    assert seen[0]["x"].tolist() == [[0, 1, 2]]


# -- a whole study --------------------------------------------------------------------------
@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_quick_study_writes_the_participants_report(task, tmp_path, monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    folder = study(task, tmp_path, ScriptedParticipant(PEOPLE[task][1]))
    episodes = pd.read_csv(folder / "episodes.csv")
    validation = episodes[episodes["phase"] == "validation"]
    methods = ["machine", "dcsc_centred", *PERSON_METHODS]
    assert sorted(validation["method"].unique()) == sorted(methods)
    for method in methods:  # each method once on each validation scenario
        assert sorted(validation.loc[validation["method"] == method, "seed"]) == [0, 1]
    assert set(episodes["phase"]) == {"operator_alone", "machine_alone", "collaboration", "validation"}
    assert set(episodes["operator"]) == {"p1"}
    assert episodes["hula_threshold"].notna().all() and episodes["hula_threshold"].nunique() == 1
    trace = pd.read_csv(folder / "trace.csv")
    assert set(trace["method"]) == set(methods) and set(trace["seed"]) == {0}
    frames = pd.read_csv(folder / "frames.csv")
    person = episodes[episodes["method"] != "machine"]
    assert len(frames) >= person["steps"].sum()  # every frame the person flew (a held env adds none)
    theta = pd.read_csv(folder / "theta.csv")
    assert theta["update"].tolist() == list(range(1, len(theta) + 1))
    assert (folder / "summary.md").read_text().startswith(f"# {task}: validation results")
    assert (folder / "fig_confidence.png").stat().st_size > 0
    assert json.loads((folder / "study.json").read_text())["participant"] == "p1"
    table = gather_participants(get_task(task), tmp_path).read_text()
    assert "| p1 |" in table.splitlines()[4]


def test_machine_rows_are_the_simulated_cells_own(tmp_path, monkeypatch):
    """The study's machine-alone runs are those of `dcsc run` with the same config and seeds."""
    from dcsc_torchrl.protocol import run_cell

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    folder = study("lunarlander", tmp_path, ScriptedParticipant(PEOPLE["lunarlander"][1]))
    task = get_task("lunarlander")
    cfg = task_config(task, [*SHIPPED, *SMALL], quick=True)
    actor, critic = shipped_machine(task, cfg.pretrain.observes)
    settings = cell_settings(cfg)
    cell = run_cell(task, task.make_operator("expert"), actor, critic, operator_name="expert", pretrain_seed=0,
                    methods=("machine",), **settings)
    simulated = pd.DataFrame(cell.episodes)
    ours = pd.read_csv(folder / "episodes.csv")
    for phase in ("machine_alone", "validation"):
        a = simulated[(simulated["method"] == "machine") & (simulated["phase"] == phase)]
        b = ours[(ours["method"] == "machine") & (ours["phase"] == phase)]
        assert a[["seed", "steps", "return", "success"]].values.tolist() == \
            b[["seed", "steps", "return", "success"]].values.tolist()


def test_a_stopped_study_resumes_where_it_stopped(tmp_path, monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    keys = PEOPLE["lunarlander"][1]
    script = ScriptedParticipant(keys, quit_after=700)  # Escape in the middle of an episode
    folder = study("lunarlander", tmp_path, script)
    done = sorted(p.name for p in (folder / "episodes").glob("*/episode.json"))
    first = pd.read_csv(folder / "episodes.csv")
    assert 0 < len(first) < 16
    assert not (folder / "summary.md").exists()
    folder = study("lunarlander", tmp_path, ScriptedParticipant(keys))
    episodes = pd.read_csv(folder / "episodes.csv")
    assert len(episodes) == 2 + 2 + 1 + 2 * 4  # practice, machine alone, collaboration, 4 methods x 2 scenarios
    pd.testing.assert_frame_equal(episodes.iloc[:len(first)].reset_index(drop=True),
                                  first.assign(hula_threshold=episodes["hula_threshold"].iloc[0])[episodes.columns],
                                  check_dtype=False)  # nothing flown before the stop is lost
    assert set(done) <= {p.name for p in (folder / "episodes").glob("*/episode.json")}
    theta = pd.read_csv(folder / "theta.csv")
    assert theta["update"].tolist() == list(range(1, len(theta) + 1))  # the learner went on where it stopped


def test_a_folder_of_another_config_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    keys = PEOPLE["lunarlander"][1]
    study("lunarlander", tmp_path, ScriptedParticipant(keys, quit_after=5))
    with pytest.raises(ConfigError, match="scenarios.validation_scenarios"):
        study("lunarlander", tmp_path, ScriptedParticipant(keys), overrides=["scenarios.validation_scenarios=3"])


def test_a_study_resumed_next_to_another_machine_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    keys = PEOPLE["lunarlander"][1]
    study("lunarlander", tmp_path, ScriptedParticipant(keys, quit_after=5))
    other = tmp_path / "other.pt"
    data = torch.load(shipped_path(get_task("lunarlander"), "target"), weights_only=False)
    data["state"]["actor"] = {k: v + 0.01 for k, v in data["state"]["actor"].items()}
    torch.save(data, other)
    make, _ = PEOPLE["lunarlander"]
    with pytest.raises(ConfigError, match="holds a study of another plan or config \\(machine: "):
        run_study(get_task("lunarlander"), "p1", out=tmp_path, quick=True, person=make(ScriptedParticipant(keys)),
                  overrides=[*SHIPPED, *SMALL], checkpoint=other)


def test_command_line_errors_are_one_line(tmp_path, capsys):
    assert dcsc(["study", "lunarlander"]) == 2
    assert "--participant" in capsys.readouterr().err
    assert dcsc(["study", "uav", "--gather", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no participant of uav" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as stop:  # argparse's own one line
        dcsc(["study", "uav", "--participant", "../up"])
    assert stop.value.code == 2 and "folder name" in capsys.readouterr().err


@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_a_study_without_a_display_is_one_line(task, tmp_path, capsys, monkeypatch):
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
        monkeypatch.delenv(name, raising=False)
    assert dcsc(["study", task, "--participant", "p1", "--out", str(tmp_path), *SHIPPED]) == 2
    err = capsys.readouterr().err
    assert "no display for the window of the person at the keys" in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.rglob("*.json"))  # nothing of a study was written
