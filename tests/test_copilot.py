"""Reddy et al.'s copilot: the tolerance rule, the copilot as the pipeline's machine, its
training (`dcsc copilot`), and a copilot that refuses the operators it was trained with."""

from __future__ import annotations

import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.copilot import (
    CopilotPolicy,
    CopilotQNetwork,
    ToleranceArbiter,
    TrainedCopilot,
    keeps_pilot,
    load_copilot,
    save_copilot,
)
from dcsc_torchrl.shipped import shipped_path
from dcsc_torchrl.tasks import get_task


class Table(torch.nn.Module):
    """A scripted Q table: row ``observation[..., 0]`` whatever the pilot pressed."""

    def __init__(self, table: torch.Tensor) -> None:
        super().__init__()
        self.table, self.n_actions, self.observation_size = table, table.shape[-1], 9

    def forward(self, observation: torch.Tensor, pilot: torch.Tensor) -> torch.Tensor:
        return self.table[observation[..., 0].long()]


def frames(observation: torch.Tensor, pilot: torch.Tensor) -> TensorDict:
    n = observation.shape[0]
    return TensorDict({"observation": observation, "human_action": pilot, "human_confidence": torch.rand(n, 1)}, [n])


def scripted(n: int = 400, keys: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    torch.manual_seed(0)
    table = torch.randint(-3, 4, (n, keys)).float()  # small integers: pilots exactly at the tolerance
    observation = torch.zeros(n, 9)
    observation[:, 0] = torch.arange(n)
    pilot = torch.nn.functional.one_hot(torch.randint(0, keys, (n,)), keys).float()
    return table, observation, pilot


@pytest.mark.parametrize("alpha", [0.0, 0.25, 0.5, 1.0])
def test_the_pilots_key_is_kept_exactly_when_its_q_is_within_alpha_of_the_best(alpha):
    table, observation, pilot = scripted()
    kept = keeps_pilot(table, pilot, alpha).squeeze(-1)
    for row, key, keep in zip(table.tolist(), pilot.argmax(-1).tolist(), kept.tolist(), strict=True):
        shifted = [q - min(row) for q in row]  # Reddy et al.: values shifted to be non-negative
        assert keep == (shifted[key] >= (1 - alpha) * max(shifted))
    if alpha == 1.0:
        assert kept.all()
    elif alpha == 0.0:  # only the pilot's key that is already a best one
        assert torch.equal(kept, table.gather(-1, pilot.argmax(-1, keepdim=True)).squeeze(-1) == table.max(-1).values)


def test_the_shared_action_is_the_pilots_key_where_kept_else_the_copilots_best():
    table, observation, pilot = scripted()
    q = Table(table)
    policy = TrainedCopilot(q, 0.5, ()).policy(OneHot(4))
    with set_exploration_type(ExplorationType.MODE), torch.no_grad():
        out = policy(frames(observation, pilot))
    kept = keeps_pilot(table, pilot, 0.5)
    assert torch.equal(out["beta"], (~kept).float())
    best = torch.nn.functional.one_hot(table.argmax(-1), 4).float()
    assert torch.equal(out["action"].float(), torch.where(kept, pilot, best))
    assert (out["machine_confidence"] == 1).all() and (out["machine_uncertainty"] == 0).all()
    assert 0 < out["beta"].mean() < 1


def test_the_arbiter_refuses_an_alpha_outside_0_1_naming_it():
    with pytest.raises(ValueError, match="alpha"):
        ToleranceArbiter(Table(torch.zeros(1, 4)), alpha=1.5)


def test_the_copilot_network_masks_the_pad_and_reads_the_pilots_key():
    torch.manual_seed(0)
    net = CopilotQNetwork([16])
    obs = torch.randn(5, 9)
    moved = obs.clone()
    moved[:, 8] += 1.0  # the pad's x
    pilot = torch.nn.functional.one_hot(torch.tensor([0, 1, 2, 3, 0]), 4).float()
    assert torch.equal(net(obs, pilot), net(moved, pilot))
    assert not torch.equal(net(obs, pilot), net(obs, pilot.roll(1, -1)))
    with pytest.raises(ValueError, match="one-hot over 4 keys"):
        net(obs, torch.zeros(5, 3))
    probs = CopilotPolicy(net)(frames(obs, pilot))["machine_probs"]
    assert torch.equal(probs.sum(-1), torch.ones(5))


def test_a_copilot_checkpoint_records_its_pool_and_is_no_machine(tmp_path):
    net = CopilotQNetwork([8])
    path = save_copilot(tmp_path / "copilot.pt", TrainedCopilot(net, 0.4, ("surrogate_noisy",)),
                        {"network": {"hidden": [8]}}, frames=10)
    copilot = load_copilot(path)
    assert copilot.alpha == 0.4 and copilot.operators == ("surrogate_noisy",)
    assert not any(p.requires_grad for p in copilot.network.parameters())
    with pytest.raises(ValueError, match="lunarlander"):
        load_checkpoint(path, task="lunarlander")  # a machine's reader refuses it
    with pytest.raises(ValueError, match="lunarlander"):
        load_copilot(shipped_path(get_task("lunarlander"), "target"))  # and the other way


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A quick `dcsc copilot` run (its pool: surrogate_noisy)."""
    out = tmp_path_factory.mktemp("copilot")
    assert main(["copilot", "--quick", "--out", str(out)]) == 0
    return out


def test_dcsc_copilot_trains_chooses_alpha_on_development_scenarios_and_records_its_pool(trained):
    copilot = load_copilot(trained / "copilot.pt")
    assert copilot.operators == ("surrogate_noisy",)
    alphas = pd.read_csv(trained / "alpha.csv")
    assert set(alphas["alpha"]) == {0.0, 1.0} and set(alphas["pilot"]) == {"surrogate_noisy"}
    best = alphas.groupby("alpha")["success"].mean()
    assert copilot.alpha == best[best == best.max()].index.max()  # ties: the larger alpha
    data = torch.load(trained / "copilot.pt", weights_only=True)
    assert data["config"]["alpha"]["first_seed"] >= 30_000 and data["frames"] >= 400 and data["train_seconds"] > 0
    assert len(pd.read_csv(trained / "train.csv")) >= 1


def test_the_copilot_is_refused_next_to_an_operator_it_was_trained_with(trained, tmp_path, capsys):
    common = ["lunarlander", "--quick", "--methods", "operator", "reddy", "--out", str(tmp_path),
              "pretrain.shipped=true", "pretrain.seeds=[0]", f"reddy.copilots=[{trained / 'copilot.pt'}]"]
    assert main(["run", *common, "--operators", "surrogate_noisy"]) == 2
    err = capsys.readouterr().err
    assert "every copilot was trained with operator 'surrogate_noisy'" in err
    assert not (tmp_path / "lunarlander" / "cells").exists()
    assert main(["run", *common, "--operators", "expert"]) == 0
    validation = pd.read_csv(tmp_path / "lunarlander" / "episodes.csv").query("phase == 'validation'")
    assert set(validation["method"]) == {"operator", "reddy"}
    assert validation["mean_beta"].between(0, 1).all()


def test_reddy_needs_copilots_and_a_discrete_task(capsys, tmp_path):
    assert main(["run", "lunarlander", "--quick", "--methods", "reddy", "--out", str(tmp_path)]) == 2
    assert "method reddy needs reddy.copilots" in capsys.readouterr().err
    assert main(["run", "uav", "--quick", "--methods", "reddy", "--out", str(tmp_path)]) == 2
    assert "task uav does not define method(s) reddy" in capsys.readouterr().err
    copilot = TrainedCopilot(CopilotQNetwork([8]), 0.5, ("expert",))
    with pytest.raises(ValueError, match="trained with operator 'expert'"):
        copilot.check_evaluated_next_to("expert")


@pytest.mark.parametrize(("argv", "line"), [
    (["copilot", "pool=[nobody]"], "pool: unknown operator preset(s) ['nobody']"),
    (["copilot", "dqn.lr=-1"], "dqn.lr: expected a value > 0, got -1"),
    (["copilot", "alpha.grid=[0.5,2]"], "alpha.grid: expected a value in [0, 1] for every entry"),
    (["run", "lunarlander", "--methods", "reddy", "reddy.copilots=[nowhere.pt]"], "reddy.copilots: no copilot at /"),
])
def test_a_bad_copilot_setting_is_refused_at_the_door_in_one_line(argv, line, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--quick"]) == 2
    err = capsys.readouterr().err
    assert line in err and err.count("\n") == 1
    assert not (tmp_path / "runs").exists()
