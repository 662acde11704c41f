"""Theta through the authority critic Q(s, beta): its Eq. 19 gradient, the direction it moves
theta, its warm-up on the two partners' recorded returns, and the warm-up's episode bookkeeping."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from test_modules import dropout_net  # the module tests' fixtures, shared
from torch import nn
from torchrl.data import Bounded, OneHot

from dcsc_torchrl.arbiters import (
    CentredConfidenceArbiter,
    ConfidenceArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
)
from dcsc_torchrl.episodes import concat_runs
from dcsc_torchrl.losses import AuthorityThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import SeparableAuthorityValue, authority_critic
from dcsc_torchrl.online import AuthorityOnlineLearner, make_online_learner, returns_to_go
from dcsc_torchrl.policy import SharedPolicyModule

SETTINGS = {"theta_lr": 0.5, "critic_lr": 0.0, "gamma": 0.9, "tau": 1e-3}


def discrete_policy(arbiter) -> SharedPolicyModule:
    return SharedPolicyModule(MCDropoutPolicy(dropout_net(9)), arbiter, OneHot(4))


def frames_of(policy: SharedPolicyModule, n: int, g: torch.Generator) -> TensorDict:
    td = TensorDict({"observation": torch.randn(n, 9, generator=g),
                     "human_action": nn.functional.one_hot(torch.randint(4, (n,), generator=g), 4),
                     "human_confidence": torch.rand(n, 1, generator=g)}, [n])
    return policy(td)


class _Slope(nn.Module):
    """A scripted authority critic: ``Q(s, beta) = slope * sum(beta)`` (every state alike)."""

    def __init__(self, slope: float) -> None:
        super().__init__()
        self.slope = slope
        self.bias = nn.Parameter(torch.zeros(()))

    def forward(self, observation: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
        return self.slope * beta.sum(-1, keepdim=True) + 0 * self.bias


@pytest.mark.parametrize("separable", [True, False])
def test_authority_theta_gradient_is_dbeta_dtheta_times_dq_dbeta(separable):
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    arbiter = CentredConfidenceArbiter(0.3, gain=2.0)
    policy = discrete_policy(arbiter)
    net = authority_critic(9, 1, [16], separable=separable)
    loss = AuthorityThetaLoss(arbiter, TensorDictModule(net, ["observation", "beta"], ["state_value"]))
    batch = frames_of(policy, 32, g)
    loss(batch)["loss_theta"].backward()
    with torch.no_grad():
        beta = torch.sigmoid(arbiter.theta + 2.0 * (2 * batch["confidence_ratio"] - 1))
    b = beta.clone().requires_grad_(True)
    (dq_db,) = torch.autograd.grad(net(batch["observation"], b).sum(), b)
    expected = -(beta * (1 - beta) * dq_db).mean(0)
    torch.testing.assert_close(arbiter.theta.grad, expected)
    assert arbiter.theta.grad.abs().item() > 0
    assert all(p.grad is None for p in net.parameters())  # the critic is held: theta's loss never trains it


@pytest.mark.parametrize("arbiter", [lambda: ConfidenceArbiter(1.0), lambda: CentredConfidenceArbiter(0.0)])
@pytest.mark.parametrize(("slope", "towards"), [(1.0, "machine"), (-1.0, "human")])
def test_theta_follows_the_authority_critics_slope(arbiter, slope, towards):
    """A critic that says more machine authority is worth more (slope > 0) moves theta up, and down for slope < 0."""
    policy = discrete_policy(arbiter())
    learner = make_online_learner(policy, _Slope(slope), theta_critic="authority", **SETTINGS, updates_per_batch=4)
    before = policy["arbiter"].theta.item()
    learner(frames_of(policy, 64, torch.Generator().manual_seed(1)))
    after = policy["arbiter"].theta.item()
    assert len(learner.history) == 4
    assert (after > before) if towards == "machine" else (after < before)


def partner_run(arbiter, reward: float, n_envs: int = 4, steps: int = 6) -> TensorDict:
    """One recorded run of ``n_envs`` scenarios of ``steps`` frames, a constant reward per frame."""
    policy = discrete_policy(arbiter)
    g = torch.Generator().manual_seed(2)
    frames = frames_of(policy, n_envs * steps, g)
    frames["env_index"] = torch.arange(n_envs).repeat_interleave(steps)
    frames["frame_index"] = torch.arange(steps).repeat(n_envs)
    frames["next"] = TensorDict({"reward": torch.full((n_envs * steps, 1), reward)}, [n_envs * steps])
    return frames


def test_warmed_up_authority_critic_prefers_the_partner_with_the_higher_returns_and_theta_follows():
    torch.manual_seed(0)
    operator, machine = partner_run(HumanOnlyArbiter(), 1.0), partner_run(MachineOnlyArbiter(), -1.0)
    policy = discrete_policy(CentredConfidenceArbiter(0.0))
    learner = make_online_learner(policy, authority_critic(9, 1, [16]), theta_critic="authority", **SETTINGS)
    learner.warm_up(concat_runs(operator, machine), target="return", updates=300, batch_size=48, lr=1e-2, seed=0)
    assert learner.action_gap(operator).mean() < -1.0  # Q(s, 1) - Q(s, 0): the machine's runs returned less
    before = policy["arbiter"].theta.item()
    learner(frames_of(policy, 64, torch.Generator().manual_seed(3)))
    assert policy["arbiter"].theta.item() < before


def test_concat_runs_keeps_each_runs_episodes_apart():
    a, b = partner_run(HumanOnlyArbiter(), 1.0, n_envs=2, steps=3), partner_run(MachineOnlyArbiter(), -1.0, n_envs=2,
                                                                                steps=3)
    joined = concat_runs(a, b)
    assert joined["env_index"].tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3]
    g = returns_to_go(joined, gamma=0.5)
    torch.testing.assert_close(g[:3], torch.tensor([1.75, 1.5, 1.0]))
    torch.testing.assert_close(g[6:9], -torch.tensor([1.75, 1.5, 1.0]))
    with pytest.raises(ValueError, match="share an \\(env_index, frame_index\\)"):
        returns_to_go(torch.cat([a, b]), gamma=0.5)


def test_authority_learner_refuses_an_online_critic_step_a_td_warm_up_and_unknown_critics():
    policy = discrete_policy(CentredConfidenceArbiter(0.0))
    with pytest.raises(ValueError, match="online.critic_lr must be 0 .* got 0.0001"):
        AuthorityOnlineLearner(policy, authority_critic(9, 1, [8]), **{**SETTINGS, "critic_lr": 1e-4})
    learner = make_online_learner(policy, authority_critic(9, 1, [8]), theta_critic="authority", **SETTINGS)
    with pytest.raises(ValueError, match="warm-up target must be 'return', got 'td'"):
        learner.warm_up(partner_run(HumanOnlyArbiter(), 1.0), target="td", updates=1, batch_size=4, lr=1e-3, seed=0)
    with pytest.raises(ValueError, match="theta_critic must be one of action, authority, got 'beta'"):
        make_online_learner(policy, authority_critic(9, 1, [8]), theta_critic="beta", **SETTINGS)


def test_authority_critic_on_a_continuous_policy_has_one_beta_per_action_dim():
    machine_net = nn.Sequential(nn.Linear(9, 16), nn.Tanh(), nn.Dropout(0.05), nn.Linear(16, 3), nn.Sigmoid())
    arbiter = CentredConfidenceArbiter(0.0, dims=3)
    policy = SharedPolicyModule(MCDropoutPolicy(machine_net, output="action"), arbiter, Bounded(0.0, 3.0, shape=(3,)))
    net = authority_critic(9, 3, [8])
    assert isinstance(net, SeparableAuthorityValue)
    learner = make_online_learner(policy, net, theta_critic="authority", **SETTINGS)
    td = TensorDict({"observation": torch.randn(16, 9), "human_action": torch.rand(16, 3),
                     "human_confidence": torch.rand(16, 1)}, [16])
    learner(policy(td))
    assert learner.action_gap(td).shape == (16,)
    assert arbiter.theta.grad is not None and arbiter.theta.grad.shape == (3,)
