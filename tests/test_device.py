"""The batched UAV env, DC-SC's modules and losses on an explicit device: CPU always, CUDA when present."""

from __future__ import annotations

import pytest
import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import Bounded, OneHot
from torchrl.envs import TransformedEnv

from dcsc_torchrl.arbiters import FrozenConfidenceArbiter
from dcsc_torchrl.batched_envs import make_uav_env
from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.config import load_config
from dcsc_torchrl.methods import METHOD_NAMES as METHODS
from dcsc_torchrl.methods import build_policy, make_arbiter, task_methods
from dcsc_torchrl.networks import (
    lunar_actor,
    lunar_critic,
    machine_from_checkpoint,
    uav_actor,
    uav_critic,
)
from dcsc_torchrl.online import make_online_learner
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.pretrain_ddpg_uav import main as pretrain_uav
from dcsc_torchrl.tasks import get_task
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                   reason="no CUDA device"))]


def all_on(td: TensorDictBase, device: str) -> bool:
    return all(value.device.type == device for value in td.values(True, True))


def uav_env_with_operator(device: str, cfg: DictConfig) -> TransformedEnv:
    """Four UAV scenarios on ``device`` with the expert operator and its confidence, as the protocol builds them."""
    transforms = [HumanOperatorTransform(get_task("uav").make_operator("expert"), seed=0),
                  HumanConfidenceTransform(**cfg.human)]
    return make_uav_env(4, scenario_seeds=[0, 1, 2, 3], device=device, max_steps=40, transforms=transforms)


def action_spec(device: str) -> Bounded:
    """The UAV's action box for one env, which broadcasts over any batch (as ``run_cell`` builds it)."""
    return make_uav_env(1, device=device).full_action_spec["action"]


@pytest.mark.parametrize("device", DEVICES)
def test_batched_uav_env_steps_on_the_device(device):
    env = make_uav_env(4, device=device)
    rollout = env.rollout(10, break_when_any_done=False)
    assert env.device.type == device and all_on(rollout, device)
    assert rollout["next", "reward"].isfinite().all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("method", [m for m in METHODS if m in task_methods(get_task("uav"), METHODS)])
def test_every_arbiter_blends_on_the_device(device, method):
    cfg = load_config(CONFIGS["uav"].protocol, quick=True)
    env = uav_env_with_operator(device, cfg)
    if method == "reddy":  # the copilot brings its own machine: its 27 grid points
        from dcsc_torchrl.copilot import TrainedCopilot

        policy = TrainedCopilot(get_task("uav").make_copilot_network([16]), 0.5, ()).policy(action_spec(device))
        td = policy.to(device)(env.reset())
        assert all_on(td, device) and td["beta"].shape == (4, 3)
        return
    if method == "dcsc_frozen":  # built by the protocol from a learned arbiter
        arbiter = FrozenConfidenceArbiter(make_arbiter("dcsc_centred", 3, theta_init=0.0),
                                          0.5, 0.3)
    elif method == "dcsc_state":  # pretrained outside the cell: beta per action dimension
        from dcsc_torchrl.state_arbiter import StateDependentArbiter

        arbiter = StateDependentArbiter(9, 3, 3, hidden=(8,), machine_key="machine_action")
    else:
        arbiter = make_arbiter(method, 3, theta_init=1.0, hula_threshold=0.01, constant_beta=0.4,
                               rule=lambda obs: obs[..., 0] > 0, q_value=uav_critic([16]), expert_q=uav_critic([16]),
                               discrete=False)
    policy = build_policy(uav_actor([16], 0.05).to(device), arbiter, action_spec(device), discrete=False,
                          **cfg.machine)
    td = policy.to(device)(env.reset())
    assert all_on(td, device)
    assert ((td["action"] >= 0) & (td["action"] <= 3)).all() and td["beta"].shape == (4, 3)


@pytest.mark.parametrize("device", DEVICES)
def test_ddpg_loss_with_the_shared_policy_learns_theta_on_the_device(device):
    cfg = load_config(CONFIGS["uav"].protocol, quick=True)
    env = uav_env_with_operator(device, cfg)
    torch.manual_seed(0)
    policy = build_policy(uav_actor([16], 0.05).to(device), make_arbiter("dcsc", 3, theta_init=1.0),
                          action_spec(device), discrete=False, **cfg.machine).to(device)
    learner = make_online_learner(policy, uav_critic([16]).to(device), theta_lr=0.1, critic_lr=1e-3, gamma=0.99, tau=0.01)
    theta = policy["arbiter"].theta.detach().clone()
    collector = Collector(env, policy, frames_per_batch=20, total_frames=40, auto_register_policy_transforms=False)
    for batch in collector:
        assert all_on(batch, device)
        learner(batch)
    collector.shutdown()
    assert policy["arbiter"].theta.device.type == device
    assert not torch.equal(policy["arbiter"].theta.detach(), theta)
    assert all(torch.tensor([h["loss_theta"], h["loss_critic"]]).isfinite().all() for h in learner.history)


@pytest.mark.parametrize("device", DEVICES)
def test_theta_loss_learns_theta_on_the_device(device):
    cfg = load_config(CONFIGS["lunarlander"].protocol, quick=True)
    torch.manual_seed(0)
    policy = build_policy(lunar_actor([16], 0.1).to(device), make_arbiter("dcsc", 1, theta_init=1.0), OneHot(4),
                          discrete=True, **cfg.machine).to(device)
    n = 8
    batch = TensorDict({
        "observation": torch.randn(n, 9),
        "human_action": torch.nn.functional.one_hot(torch.randint(4, (n,)), 4),
        "human_confidence": torch.rand(n, 1),
        "next": {"observation": torch.randn(n, 9), "reward": torch.randn(n, 1),
                 "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n], device=device)
    batch = policy(batch)
    learner = make_online_learner(policy, lunar_critic([16], 4).to(device), theta_lr=0.1, critic_lr=1e-3, gamma=0.99,
                            tau=0.01)
    theta = policy["arbiter"].theta.detach().clone()
    learner(batch)
    assert all_on(batch, device) and policy["arbiter"].theta.device.type == device
    assert not torch.equal(policy["arbiter"].theta.detach(), theta)
    assert torch.tensor(learner.history[0]["theta_grad"]).isfinite().all()


@pytest.mark.parametrize("device", DEVICES)
def test_ddpg_pretraining_runs_on_the_device(device, tmp_path):
    pretrain_uav(["--quick", "--out", str(tmp_path), f"device={device}", "train.episodes=3"])
    data = load_checkpoint(tmp_path / "checkpoint.pt", task="uav")  # loads on the CPU whatever the device
    assert data["episodes"] == 3 and data["config"]["device"] == device
    machine, _ = machine_from_checkpoint(data, get_task("uav"))
    assert next(machine.parameters()).device.type == "cpu"
