"""IDA's intervention (:class:`InterventionArbiter`): the machine acts exactly where the Q
function rates its action above the operator's, the operator keeps a tie."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from dcsc_torchrl.arbiters import InterventionArbiter, save_arbiter
from dcsc_torchrl.methods import make_arbiter
from dcsc_torchrl.networks import ConcatInputs


def frames(n: int, **keys: torch.Tensor) -> TensorDict:
    return TensorDict({"machine_confidence": torch.rand(n, 1), "human_confidence": torch.rand(n, 1), **keys}, [n])


def test_the_machine_acts_exactly_where_its_key_has_the_higher_q():
    torch.manual_seed(0)
    n, keys = 500, 4
    table = torch.randint(0, 3, (n, keys)).float()  # small integers: many ties
    observation = torch.arange(n).float().unsqueeze(-1)
    machine_probs = torch.softmax(torch.randn(n, keys), -1)
    human = torch.nn.functional.one_hot(torch.randint(0, keys, (n,)), keys).float()
    arbiter = InterventionArbiter(lambda obs: table[obs.squeeze(-1).long()], discrete=True)
    beta = arbiter(frames(n, observation=observation, machine_probs=machine_probs, human_action=human))["beta"]
    q_machine = table.gather(-1, machine_probs.argmax(-1, keepdim=True))
    q_human = table.gather(-1, human.argmax(-1, keepdim=True))
    assert torch.equal(beta, (q_machine > q_human).float())
    ties = q_machine == q_human
    assert ties.any() and (beta[ties] == 0).all()  # on a tie the operator keeps control
    assert 0 < beta.mean() < 1


def test_continuous_actions_compare_q_of_the_two_actions_and_hand_over_every_dimension():
    q = ConcatInputs(torch.nn.Linear(9 + 3, 1))
    n = 64
    td = frames(n, observation=torch.randn(n, 9), machine_action=torch.rand(n, 3), human_action=torch.rand(n, 3))
    beta = InterventionArbiter(q, 3, discrete=False)(td)["beta"]
    with torch.no_grad():
        expected = (q(td["observation"], td["machine_action"]) > q(td["observation"], td["human_action"])).float()
    assert beta.shape == (n, 3) and torch.equal(beta, expected.expand(n, 3))


def test_the_method_acts_on_a_frozen_copy_of_the_critic():
    critic = torch.nn.Linear(9, 4)
    arbiter = make_arbiter("ida", 1, q_value=critic)
    assert arbiter.q_value is not critic and not any(p.requires_grad for p in arbiter.q_value.parameters())
    with torch.no_grad():
        critic.weight.add_(1.0)  # the cell's critic learning on does not move IDA's
    assert not torch.equal(arbiter.q_value.weight, critic.weight)
    with pytest.raises(ValueError, match="the ida arbiter needs a Q network"):
        make_arbiter("ida", 1)


def test_an_intervention_arbiter_is_not_saved_as_if_it_had_state(tmp_path):
    with pytest.raises(ValueError, match="save its q_value network"):
        save_arbiter(InterventionArbiter(torch.nn.Linear(9, 4), discrete=True), tmp_path / "a.pt", task="lunarlander")


def test_a_non_finite_q_is_refused_naming_it():
    arbiter = InterventionArbiter(lambda obs: torch.full((2, 4), float("nan")), discrete=True)
    td = frames(2, observation=torch.zeros(2, 9), machine_probs=torch.full((2, 4), 0.25),
                human_action=torch.eye(4)[:2])
    with pytest.raises(ValueError, match="the intervention's Q"):
        arbiter(td)


def test_a_cell_asked_for_ida_with_an_authority_critic_is_refused_before_its_first_frame():
    from dcsc_torchrl.protocol import run_cell
    from dcsc_torchrl.tasks import get_task

    with pytest.raises(ValueError, match="method ida reads Q\\(s, a\\).*theta_critic=authority"):
        run_cell(get_task("lunarlander"), None, None, None, operator_name="x", pretrain_seed=0, human={}, machine=None,
                 arbiter=None, online={"theta_critic": "authority"}, warmup=None, methods=["operator", "ida"])


def test_ida_expert_acts_on_a_frozen_copy_of_the_expert_not_the_cells_critic():
    cell_critic, expert = torch.nn.Linear(9, 4), torch.nn.Linear(9, 4)
    arbiter = make_arbiter("ida_expert", 1, q_value=cell_critic, expert_q=expert)
    assert torch.equal(arbiter.q_value.weight, expert.weight) and arbiter.q_value is not expert
    assert not any(p.requires_grad for p in arbiter.q_value.parameters())
    with pytest.raises(ValueError, match="the ida_expert arbiter needs a Q network: an expert's"):
        make_arbiter("ida_expert", 1, q_value=cell_critic)


def test_a_cell_asked_for_ida_expert_without_an_expert_is_refused_before_its_first_frame():
    from dcsc_torchrl.protocol import run_cell
    from dcsc_torchrl.tasks import get_task

    with pytest.raises(ValueError, match="method ida_expert reads an expert's Q: pass expert_q"):
        run_cell(get_task("lunarlander"), None, None, None, operator_name="x", pretrain_seed=0, human={}, machine=None,
                 arbiter=None, online={}, warmup=None, methods=["operator", "ida_expert"])


def test_dcsc_run_with_ida_expert_reads_the_experts_checkpoint_and_needs_it_at_the_door(tmp_path):
    """Named, ida_expert runs beside the others on the critic of ``ida.expert`` (here the shipped
    machine's); without ``ida.expert`` it is refused before any cell runs; by default it does not run."""
    import pandas as pd

    from dcsc_torchrl.config import ConfigError
    from dcsc_torchrl.recipes.shared_control import run_task
    from dcsc_torchrl.shipped import shipped_path
    from dcsc_torchrl.tasks import get_task

    common = ["pretrain.shipped=true", "pretrain.seeds=[0]", "protocol.max_steps=40", "scenarios.operator_runs=2",
              "scenarios.machine_alone_runs=2", "scenarios.collaboration_runs=2", "scenarios.validation_scenarios=2",
              "protocol.group_size=1"]
    with pytest.raises(ConfigError, match="method ida_expert needs ida.expert"):
        run_task("lunarlander", out=tmp_path / "refused", operators=["expert"], methods=["operator", "ida_expert"],
                 overrides=common)
    assert not (tmp_path / "refused" / "lunarlander" / "cells").exists()
    expert = shipped_path(get_task("lunarlander"), "blind")
    out = run_task("lunarlander", out=tmp_path / "run", operators=["expert"], methods=["operator", "ida", "ida_expert"],
                   overrides=[*common, f"ida.expert={expert}"])
    validation = pd.read_csv(out / "episodes.csv").query("phase == 'validation'")
    assert set(validation["method"]) == {"operator", "ida", "ida_expert"}
    assert validation["mean_beta"].between(0, 1).all()


def test_the_grid_gives_its_cells_the_experts_absolute_path(tmp_path, monkeypatch):
    """Cells may run in other processes or nodes (dcsc sweep): a relative ida.expert is resolved."""
    from pathlib import Path

    from dcsc_torchrl.recipes.grid import make_grid
    from dcsc_torchrl.recipes.settings import task_config
    from dcsc_torchrl.tasks import get_task

    monkeypatch.chdir(tmp_path)
    cfg = task_config(get_task("lunarlander"), ["ida.expert=experts/seed0/checkpoint.pt"], quick=True)
    grid = make_grid("lunarlander", cfg, ["expert"], [0], quick=True)
    assert grid.cfg.ida.expert == str(tmp_path.resolve() / "experts" / "seed0" / "checkpoint.pt")
    assert Path(grid.cfg.pretrain.out_dir).is_absolute()
