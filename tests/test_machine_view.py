"""What the LunarLander machine observes is a setting (``pretrain.observes`` / ``network.observes``):
the paper's state with the pad's x (``target``) or the 8 standard values (``blind``)."""

from __future__ import annotations

import pytest
import torch

from dcsc_torchrl.checkpoint import checkpoint_path, save_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.config import load_config
from dcsc_torchrl.networks import LUNAR_MACHINE_VIEWS
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.settings import pretrain_config
from dcsc_torchrl.shipped import shipped_path
from dcsc_torchrl.tasks import get_task

LUNAR = get_task("lunarlander")


def actor_of(observes: str) -> torch.nn.Module:
    torch.manual_seed(0)
    actor, _ = LUNAR.make_networks({"hidden": [16], "actor_dropout": 0.1, "observes": observes})
    return actor.eval()


def test_the_pad_seeing_actor_reads_the_pads_x_and_the_goal_blind_one_does_not():
    obs = torch.randn(32, 9)
    moved = obs.clone()
    moved[:, 8] += 0.5
    sees, blind = actor_of("target"), actor_of("blind")
    assert not torch.allclose(sees(obs), sees(moved))
    assert torch.equal(blind(obs), blind(moved))


def test_a_checkpoint_without_the_setting_loads_as_the_goal_blind_machine():
    torch.manual_seed(0)
    legacy, _ = LUNAR.make_networks({"hidden": [16], "actor_dropout": 0.1})
    assert legacy[0].n == LUNAR_MACHINE_VIEWS["blind"] == actor_of("blind")[0].n


def save_machine(path, observes: str | None) -> None:
    network = {"hidden": [16], "actor_dropout": 0.1, **({"observes": observes} if observes else {})}
    actor, critic = LUNAR.make_networks(network)
    save_checkpoint(path, task="lunarlander", payload={
        "config": {"network": network, "train": {"episodes": 1}}, "finished": True, "episodes": 1,
        "state": {"actor": actor.state_dict(), "qvalue": critic.state_dict()}})


@pytest.mark.parametrize(("saved", "asked"), [("target", "blind"), ("blind", "target"), (None, "target")])
def test_a_checkpoint_of_one_view_is_refused_by_the_other_in_one_line_naming_both(saved, asked, tmp_path, capsys):
    path = checkpoint_path(tmp_path / "pre", 0)
    path.parent.mkdir(parents=True)
    save_machine(path, saved)
    code = main(["run", "lunarlander", "--quick", "--out", str(tmp_path / "res"), f"pretrain.out_dir={tmp_path / 'pre'}",
                 f"pretrain.observes={asked}"])
    assert code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert str(path) in line and f"observes {saved or 'blind'!r}" in line and f"pretrain.observes is {asked!r}" in line
    assert not (tmp_path / "res").exists()


def test_an_unknown_view_is_refused_at_the_door(tmp_path, capsys):
    assert main(["run", "lunarlander", "--out", str(tmp_path / "res"), "pretrain.observes=pad"]) == 2
    assert "pretrain.observes: unknown machine view 'pad'" in capsys.readouterr().err
    assert main(["pretrain", "lunarlander", "--out", str(tmp_path / "pre"), "network.observes=pad"]) == 2
    assert "network.observes: expected one of blind, target, got 'pad'" in capsys.readouterr().err


@pytest.mark.parametrize(("observes", "random_pad"), [("target", True), ("blind", False)])
def test_the_protocols_view_pretrains_a_machine_that_sees_it_on_the_pads_it_needs(observes, random_pad):
    cfg = load_config(CONFIGS["lunarlander"].protocol, [f"pretrain.observes={observes}"])
    recipe = pretrain_config(LUNAR, cfg, 0, quick=False)
    assert recipe.network.observes == observes and recipe.env.random_pad is random_pad
    explicit = load_config(CONFIGS["lunarlander"].protocol,
                           [f"pretrain.observes={observes}", f"pretrain.recipe=[env.random_pad={not random_pad}]"])
    assert pretrain_config(LUNAR, explicit, 0, quick=False).env.random_pad is (not random_pad)


def test_each_view_ships_its_own_file():
    assert shipped_path(LUNAR, "blind").name == "lunarlander_blind_seed0.pt"
    assert shipped_path(LUNAR, "target").name == "lunarlander_target_seed0.pt"
