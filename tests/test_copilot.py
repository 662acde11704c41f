"""Reddy et al.'s copilot: the tolerance rule on keys and on the UAV's sampled action set, the
copilot as the pipeline's machine, its training (`dcsc copilot TASK`), and a copilot that
refuses the operators it was trained with."""

from __future__ import annotations

import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.copilot import (
    CopilotPolicy,
    ToleranceArbiter,
    TrainedCopilot,
    keeps_pilot,
    load_copilot,
    nearest_action,
    save_copilot,
    tolerant_choice,
)
from dcsc_torchrl.humans.uav_operator import DEFAULT_GRID
from dcsc_torchrl.shipped import shipped_path
from dcsc_torchrl.tasks import get_task

LUNAR, UAV = get_task("lunarlander"), get_task("uav")


class Table(torch.nn.Module):
    """A scripted Q table over ``actions`` (default: one-hot keys): row ``observation[..., 0]``
    whatever the pilot did."""

    def __init__(self, table: torch.Tensor, actions: torch.Tensor | None = None) -> None:
        super().__init__()
        self.table, self.observation_size = table, 9
        self.actions = torch.eye(table.shape[-1]) if actions is None else actions
        self.action_size = self.actions.shape[-1]

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
    kept = keeps_pilot(table, pilot.argmax(-1, keepdim=True), alpha).squeeze(-1)
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
    kept = keeps_pilot(table, pilot.argmax(-1, keepdim=True), 0.5)
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
    net = LUNAR.make_copilot_network([16])
    obs = torch.randn(5, 9)
    moved = obs.clone()
    moved[:, 8] += 1.0  # the pad's x
    pilot = torch.nn.functional.one_hot(torch.tensor([0, 1, 2, 3, 0]), 4).float()
    assert torch.equal(net(obs, pilot), net(moved, pilot))
    assert not torch.equal(net(obs, pilot), net(obs, pilot.roll(1, -1)))
    with pytest.raises(ValueError, match="must have 4 values"):
        net(obs, torch.zeros(5, 3))
    probs = CopilotPolicy(net, 0.5)(frames(obs, pilot))["machine_probs"]
    assert torch.equal(probs.sum(-1), torch.ones(5))


def test_a_copilot_checkpoint_records_its_pool_and_is_no_machine_nor_another_tasks_copilot(tmp_path):
    torch.manual_seed(0)
    net = LUNAR.make_copilot_network([8])
    path = save_copilot(tmp_path / "copilot.pt", LUNAR, TrainedCopilot(net, 0.4, ("surrogate_noisy",)),
                        {"network": {"hidden": [8]}}, frames=10)
    copilot = load_copilot(path, LUNAR)
    assert copilot.alpha == 0.4 and copilot.operators == ("surrogate_noisy",)
    assert not any(p.requires_grad for p in copilot.network.parameters())
    obs, pilot = torch.randn(6, 9), torch.eye(4)[torch.tensor([0, 1, 2, 3, 0, 1])]
    assert torch.equal(copilot.network(obs, pilot), net(obs, pilot))  # save -> load: the same Q
    with pytest.raises(ValueError, match="lunarlander"):
        load_checkpoint(path, task="lunarlander")  # a machine's reader refuses it
    with pytest.raises(ValueError, match="lunarlander"):
        load_copilot(shipped_path(LUNAR, "target"), LUNAR)  # and the other way
    with pytest.raises(ValueError, match="uav-copilot"):
        load_copilot(path, UAV)  # a copilot of another task


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A quick `dcsc copilot` run (its pool: surrogate_noisy)."""
    out = tmp_path_factory.mktemp("copilot")
    assert main(["copilot", "lunarlander", "--quick", "--out", str(out)]) == 0
    return out


def test_dcsc_copilot_trains_chooses_alpha_on_development_scenarios_and_records_its_pool(trained):
    copilot = load_copilot(trained / "copilot.pt", LUNAR)
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


@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_reddy_needs_copilots(task, capsys, tmp_path):
    assert main(["run", task, "--quick", "--methods", "reddy", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "method reddy needs reddy.copilots" in err and f"runs/copilot_{task}/copilot.pt" in err
    copilot = TrainedCopilot(get_task(task).make_copilot_network([8]), 0.5, ("expert",))
    with pytest.raises(ValueError, match="trained with operator 'expert'"):
        copilot.check_evaluated_next_to("expert")


def test_a_task_without_a_copilot_network_has_no_reddy():
    from dataclasses import replace

    from dcsc_torchrl.methods import check_task_methods, task_methods

    assert "reddy" in task_methods(UAV, ["operator", "reddy"])
    bare = replace(UAV, make_copilot_network=None)
    assert task_methods(bare, ["operator", "reddy"]) == ("operator",)
    with pytest.raises(ValueError, match=r"task uav does not define method\(s\) reddy: it has no copilot network"):
        check_task_methods(bare, ["reddy"])


@pytest.mark.parametrize(("argv", "line"), [
    (["copilot", "lunarlander", "pool=[nobody]"], "pool: unknown operator preset(s) ['nobody']"),
    (["copilot", "uav", "dqn.lr=-1"], "dqn.lr: expected a value > 0, got -1"),
    (["copilot", "lunarlander", "alpha.grid=[0.5,2]"], "alpha.grid: expected a value in [0, 1] for every entry"),
    (["copilot", "uav", "task=lunarlander"], "task"),
    (["run", "lunarlander", "--methods", "reddy", "reddy.copilots=[nowhere.pt]"], "reddy.copilots: no copilot at /"),
])
def test_a_bad_copilot_setting_is_refused_at_the_door_in_one_line(argv, line, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--quick"]) == 2
    err = capsys.readouterr().err
    assert line in err and err.count("\n") == 1
    assert not (tmp_path / "runs").exists()


# --- the UAV: Reddy's rule on a sampled action set (the operator's 27 grid points)

GRID = torch.tensor(DEFAULT_GRID)


def uav_scripted(n: int = 300) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A Q table over the 27 grid points (small integers: ties and pilots at the tolerance) and
    pilot actions, half of them grid points (a simulated operator's) and half anywhere in the box."""
    torch.manual_seed(1)
    table = torch.randint(-3, 4, (n, len(GRID))).float()
    observation = torch.zeros(n, 9)
    observation[:, 0] = torch.arange(n)
    pilot = torch.where(torch.arange(n).unsqueeze(-1) % 2 == 0, GRID[torch.randint(0, len(GRID), (n,))],
                        3 * torch.rand(n, 3))
    return table, observation, pilot


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.6, 1.0])
def test_on_the_uav_the_pilot_is_kept_where_its_nearest_grid_point_is_within_alpha_else_the_nearest_feasible(alpha):
    table, _, pilot = uav_scripted()
    choice, kept = tolerant_choice(table, GRID, pilot, alpha)
    for row, action, pick, keep in zip(table.tolist(), pilot, choice.squeeze(-1).tolist(), kept.squeeze(-1).tolist(),
                                       strict=True):
        shifted = [q - min(row) for q in row]
        feasible = [shifted[i] >= (1 - alpha) * max(shifted) for i in range(len(row))]
        distances = [float((action - point).square().sum()) for point in GRID]
        assert keep == feasible[min(range(len(row)), key=lambda i: distances[i])]
        if keep:
            assert row[pick] == max(row)  # the copilot's own best, which the arbiter does not use
        else:  # among the feasible, the nearest the pilot's; ties: the larger Q
            nearest = min(distances[i] for i in range(len(row)) if feasible[i])
            assert feasible[pick] and distances[pick] == nearest
            assert row[pick] == max(row[i] for i in range(len(row)) if feasible[i] and distances[i] == nearest)
    assert kept.all() if alpha == 1.0 else not kept.all()


def test_with_keys_the_nearest_feasible_key_is_the_copilots_best():
    table, _, pilot = scripted()
    choice, kept = tolerant_choice(table, torch.eye(4), pilot, 0.4)
    assert torch.equal(choice.squeeze(-1), table.argmax(-1))
    assert torch.equal(nearest_action(torch.eye(4), pilot), pilot.argmax(-1, keepdim=True))


def test_the_uav_shared_action_is_the_pilots_where_kept_else_the_copilots_in_every_dimension():
    table, observation, pilot = uav_scripted()
    policy = TrainedCopilot(Table(table, GRID), 0.5, ()).policy(Bounded(0.0, 3.0, shape=(3,)))
    with torch.no_grad():
        out = policy(frames(observation, pilot))
    choice, kept = tolerant_choice(table, GRID, pilot, 0.5)
    assert out["beta"].shape == (len(pilot), 3) and torch.equal(out["beta"], (~kept).float().expand(-1, 3))
    assert torch.equal(out["machine_action"], GRID[choice.squeeze(-1)])
    assert torch.equal(out["action"], torch.where(kept, pilot, GRID[choice.squeeze(-1)]))
    assert 0 < out["beta"].mean() < 1


def test_the_uav_copilot_reads_the_whole_state_and_the_pilots_action():
    torch.manual_seed(0)
    net = UAV.make_copilot_network([16])
    obs, pilot = torch.randn(4, 9), GRID[:4]
    assert net(obs, pilot).shape == (4, 27) and torch.equal(net.actions, GRID)
    assert "actions" not in net.state_dict()  # the task rebuilds the action set on load
    moved = obs.clone()
    moved[:, 8] += 1.0
    assert not torch.equal(net(obs, pilot), net(moved, pilot))
    assert not torch.equal(net(obs, pilot), net(obs, pilot.flip(0)))


def test_the_training_run_flies_the_tolerant_action_and_learns_its_index():
    from dcsc_torchrl.recipes.copilot import CHOICE_KEY, ExploringCopilot

    table, observation, pilot = uav_scripted()
    explorer = ExploringCopilot(Table(table, GRID), 0.5)
    explorer.epsilon = 0.0
    out = explorer(frames(observation, pilot))
    choice, kept = tolerant_choice(table, GRID, pilot, 0.5)
    index = torch.where(kept, nearest_action(GRID, pilot), choice).squeeze(-1)
    assert torch.equal(out[CHOICE_KEY].argmax(-1), index) and torch.equal(out["action"], GRID[index])
    explorer.epsilon = 1.0
    assert not torch.equal(explorer(frames(observation, pilot))[CHOICE_KEY].argmax(-1), index)


def test_dcsc_copilot_uav_trains_and_reddy_runs_in_the_uav_protocol(tmp_path):
    assert main(["copilot", "uav", "--quick", "--out", str(tmp_path / "copilot")]) == 0
    copilot = load_copilot(tmp_path / "copilot" / "copilot.pt", UAV)
    assert copilot.operators == ("surrogate_noisy",) and torch.equal(copilot.network.actions, GRID)
    assert main(["run", "uav", "--quick", "--methods", "operator", "reddy", "--operators", "expert", "--out",
                 str(tmp_path), "pretrain.shipped=true", "pretrain.seeds=[0]",
                 f"reddy.copilots=[{tmp_path / 'copilot' / 'copilot.pt'}]"]) == 0
    validation = pd.read_csv(tmp_path / "uav" / "episodes.csv").query("phase == 'validation'")
    assert set(validation["method"]) == {"operator", "reddy"}
    assert validation["mean_beta"].between(0, 1).all()
