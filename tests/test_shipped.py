"""The machines shipped with the package: weights only, the recipe's shapes, their recorded greedy return."""

from __future__ import annotations

import pytest
import torch

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.config import load_config
from dcsc_torchrl.networks import machine_fingerprint, view_recipe_settings
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.machines import PRETRAINING
from dcsc_torchrl.recipes.play import load_play_arbiter
from dcsc_torchrl.shipped import (
    greedy_return,
    load_shipped,
    shipped_arbiter_path,
    shipped_machine,
    shipped_path,
)
from dcsc_torchrl.state_arbiter import (
    load_pretrained_arbiter,
    state_arbiter_task,
)
from dcsc_torchrl.tasks import get_task


def recipe_config(task_name: str, overrides: list[str] = ()):
    return load_config(CONFIGS[task_name].pretrain, list(overrides))


SHIPPED = [("lunarlander", "blind"), ("lunarlander", "target"), ("uav", None)]
"""Every shipped machine: (task, what it observes; ``None``: a task with one machine)."""


def view_settings(observes: str | None) -> list[str]:
    """The recipe settings of a machine that ``observes`` (none for a task with one machine)."""
    return [] if observes is None else view_recipe_settings(observes)


def shipped_command(name: str, observes: str | None) -> str:
    return " ".join(["dcsc pretrain", name, "seed=0", *view_settings(observes)])


@pytest.mark.parametrize(("name", "observes"), SHIPPED)
def test_shipped_weights_are_small_weights_only_files_of_the_recipes_settings(name, observes):
    task = get_task(name)
    path = shipped_path(task, observes)
    assert path.stat().st_size < 2_000_000
    data = load_shipped(task, observes)
    assert set(data["state"]) == set(task.checkpoint_modules)  # no optimiser, no replay buffer
    cfg = recipe_config(name, view_settings(observes))
    # files exported before the A2C recipe's network.init / network.observes keys hold their defaults
    legacy = {"init": "default", "observes": "blind"} if name == "lunarlander" else {}
    assert {**legacy, **data["config"]["network"]} == {**legacy, **dict(cfg.network)}
    assert data["config"]["seed"] == 0
    assert data["episodes"] >= cfg.train.episodes and data["command"] == shipped_command(name, observes)
    assert (path.parent / "README.md").read_text().count(f"`{data['command']}`") == 1


@pytest.mark.parametrize(("name", "observes"), SHIPPED)
def test_shipped_weights_load_into_the_recipe_networks_and_give_their_recorded_return(name, observes):
    task = get_task(name)
    actor, critic = shipped_machine(task, observes)
    fresh_actor, fresh_critic = task.make_networks(recipe_config(name, view_settings(observes)).network)
    for loaded, fresh in ((actor, fresh_actor), (critic, fresh_critic)):
        assert {k: v.shape for k, v in loaded.state_dict().items()} == {
            k: v.shape for k, v in fresh.state_dict().items()}
    assert not actor.training and not critic.training
    assert greedy_return(task, actor) == pytest.approx(load_shipped(task, observes)["greedy_return"], abs=1e-3)


def test_run_with_the_shipped_machine_needs_seed_0_only(capsys):
    assert main(["run", "lunarlander", "--quick", "pretrain.shipped=true", "pretrain.seeds=[0,1]"]) == 2
    err = capsys.readouterr().err
    assert "only pretraining seed 0 ships" in err and "pretrain.seeds=[0]" in err


@pytest.mark.slow
@pytest.mark.parametrize(("name", "observes"), SHIPPED)
def test_the_recorded_command_rederives_the_shipped_weights(name, observes, tmp_path):
    task = get_task(name)
    PRETRAINING[name](recipe_config(name, [*view_settings(observes), "seed=0", f"logger.out_dir={tmp_path}"]))
    shipped = load_shipped(task, observes)["state"]
    retrained = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["state"]
    for module in task.checkpoint_modules:
        for key, value in shipped[module].items():
            torch.testing.assert_close(retrained[module][key], value, rtol=0, atol=0, msg=f"{module}.{key}")


SHIPPED_ARBITERS = [("lunarlander", "target", "dcsc arbiter lunarlander pretrain.shipped=true pretrain.observes=target"),
                    ("uav", None, "dcsc arbiter uav pretrain.shipped=true")]
"""Each shipped arbiter: its task, the view of the shipped machine beside it, its recorded command."""


@pytest.mark.parametrize(("name", "observes", "command"), SHIPPED_ARBITERS)
def test_the_shipped_arbiter_was_pretrained_next_to_the_shipped_machine_against_the_default_pool(name, observes,
                                                                                                command):
    task = get_task(name)
    path = shipped_arbiter_path(task, observes)
    assert path.stat().st_size < 200_000
    data = load_checkpoint(path, task=state_arbiter_task(task))
    assert data["command"] == command
    assert (path.parent / "README.md").read_text().count(f"`{data['command']}`") == 1
    pretrained = load_pretrained_arbiter(path, task)
    machine, _ = shipped_machine(task, observes)
    assert pretrained.machine == machine_fingerprint(machine)
    protocol = load_config(CONFIGS[name].protocol)
    assert list(pretrained.operators) == list(protocol.state.pool)
    assert data["config"]["state"] == dict(protocol.state) | {"arbiters": None}  # the yaml's settings, untuned
    pretrained.check_evaluated_next_to("expert", machine)  # a human-like cell may run it
    with pytest.raises(ValueError, match="surrogate_noisy"):
        pretrained.check_evaluated_next_to("surrogate_noisy", machine)
    if name == "lunarlander":
        assert load_play_arbiter(None, protocol).machine == pretrained.machine  # dcsc play --assist state's default


@pytest.mark.slow
@pytest.mark.parametrize(("name", "observes", "command"), SHIPPED_ARBITERS)
def test_the_recorded_command_rederives_the_shipped_arbiter(tmp_path, name, observes, command):
    task = get_task(name)
    shipped = load_checkpoint(shipped_arbiter_path(task, observes), task=state_arbiter_task(task))
    command = shipped["command"].split()
    assert main([*command[1:], "--out", str(tmp_path)]) == 0
    again = load_checkpoint(tmp_path / "arbiter.pt", task=state_arbiter_task(task))
    for part in ("arbiter", "value"):
        for key, value in shipped["state"][part].items():
            if isinstance(value, torch.Tensor):
                torch.testing.assert_close(again["state"][part][key], value, rtol=0, atol=0, msg=f"{part}.{key}")
