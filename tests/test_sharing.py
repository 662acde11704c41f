"""What makes shared control share: the centred arbiter and its Eq. 19 gradient, theta moving
towards the better partner, the calibrated machine confidence, the critic that sees the pad,
and a human confidence that falls after a late decision."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from test_modules import _Critic, discrete_batch, dropout_net  # the module tests' fixtures, shared
from torch import nn
from torchrl.data import Bounded, OneHot
from torchrl.objectives import DDPGLoss

from dcsc_torchrl.arbiters import (
    CentredConfidenceArbiter,
    ConfidenceArbiter,
    ConstantArbiter,
    FrozenConfidenceArbiter,
    centred_fusion_weight,
)
from dcsc_torchrl.confidence import machine_confidence
from dcsc_torchrl.losses import ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy, calibrated_uncertainty_scale
from dcsc_torchrl.networks import LUNAR_QVALUE_DIMS, lunar_critic
from dcsc_torchrl.online import DiscreteOnlineLearner
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.transforms import HumanConfidenceTransform


def confidences(b_m: float, b_h: float) -> TensorDict:
    return TensorDict({"machine_confidence": torch.tensor([[b_m]]), "human_confidence": torch.tensor([[b_h]])}, [1])


# --- the centred arbiter ---------------------------------------------------------------


def test_centred_arbiter_gives_equal_authority_at_equal_confidence_and_favours_the_more_confident():
    arbiter = CentredConfidenceArbiter(theta_init=0.0, gain=3.0)
    assert arbiter(confidences(0.4, 0.4))["beta"].item() == pytest.approx(0.5)
    assert arbiter(confidences(0.8, 0.2))["beta"].item() > 0.5
    assert arbiter(confidences(0.2, 0.8))["beta"].item() < 0.5


def test_centred_arbiter_theta_hands_the_majority_either_way():
    equal = confidences(0.5, 0.5)
    assert CentredConfidenceArbiter(theta_init=2.0)(equal)["beta"].item() > 0.8
    assert CentredConfidenceArbiter(theta_init=-2.0)(equal)["beta"].item() < 0.2
    # unlike Eq. 15, whose beta stays >= 1/2 for theta >= 0 and never goes below it at b_t = 1/2 ...
    assert ConfidenceArbiter(theta_init=0.0)(equal)["beta"].item() == pytest.approx(0.5)
    # ... and for theta < 0 gives a more confident machine less authority
    paper = ConfidenceArbiter(theta_init=-2.0)
    assert paper(confidences(0.9, 0.1))["beta"].item() < paper(confidences(0.1, 0.9))["beta"].item()
    centred = CentredConfidenceArbiter(theta_init=-2.0)
    assert centred(confidences(0.9, 0.1))["beta"].item() > centred(confidences(0.1, 0.9))["beta"].item()


@pytest.mark.parametrize("bad", [{"gain": 0.0}, {"gain": float("inf")}, {"theta_init": float("nan")}])
def test_centred_arbiter_rejects_bad_parameters_by_name(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        CentredConfidenceArbiter(**bad)


def test_constant_and_frozen_arbiters_ignore_the_frame_confidences():
    assert ConstantArbiter(0.3)(confidences(0.9, 0.1))["beta"].item() == pytest.approx(0.3)
    with pytest.raises(ValueError, match="value"):
        ConstantArbiter(1.5)
    frozen = FrozenConfidenceArbiter(CentredConfidenceArbiter(theta_init=0.5), 0.6, 0.2)
    expected = centred_fusion_weight(torch.tensor([0.5]), torch.tensor([0.75]), 3.0).item()
    for b_m, b_h in ((0.9, 0.1), (0.0, 1.0)):
        assert frozen(confidences(b_m, b_h))["beta"].item() == pytest.approx(expected)
    assert frozen.theta is frozen.arbiter.theta


def test_theta_loss_gradient_of_the_centred_arbiter_is_its_eq19():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net()), CentredConfidenceArbiter(0.3, gain=2.0), OneHot(4))
    qnet = TensorDictModule(nn.Linear(8, 4), ["observation"], ["action_value"])
    loss = ThetaLoss(policy, qnet, gamma=0.99)
    batch = discrete_batch(32, g, policy)
    loss(batch)["loss_theta"].backward()
    theta = policy["arbiter"].theta
    with torch.no_grad():
        beta = torch.sigmoid(theta + 2.0 * (2 * batch["confidence_ratio"] - 1))
        q = qnet(batch.clone())["action_value"]
        grad_j = ((beta - beta**2) * ((batch["machine_probs"] - batch["human_action"]) * q).sum(-1, keepdim=True)).mean()
    torch.testing.assert_close(theta.grad, -grad_j.reshape(1))
    assert theta.grad.abs().item() > 0


def test_ddpg_loss_gives_the_centred_theta_its_eq19_gradient():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    machine_net = nn.Sequential(nn.Linear(9, 32), nn.Tanh(), nn.Dropout(0.05), nn.Linear(32, 3), nn.Sigmoid())
    machine_net.requires_grad_(False)
    policy = SharedPolicyModule(MCDropoutPolicy(machine_net, output="action"),
                                CentredConfidenceArbiter(theta_init=0.2, dims=3), Bounded(0.0, 3.0, shape=(3,)))
    critic = TensorDictModule(_Critic(), ["observation", "action"], ["state_action_value"])
    loss = DDPGLoss(policy, critic)
    batch = TensorDict({"observation": torch.randn(24, 9, generator=g),
                        "human_action": 0.5 + torch.rand(24, 3, generator=g),
                        "human_confidence": torch.rand(24, 1, generator=g)}, [24])
    torch.manual_seed(5)
    out = loss.loss_actor(batch)[0]
    (grad,) = torch.autograd.grad(out, loss.actor_network_params["module", "arbiter", "theta"])
    torch.manual_seed(5)
    td = policy(batch.clone())
    a = td["action"].detach().requires_grad_(True)
    (dq_da,) = torch.autograd.grad(critic.module(td["observation"], a).sum(), a)
    beta = td["beta"].detach()
    expected = -(beta * (1 - beta) * (td["machine_action"] - td["human_action"]) * dq_da).mean(0)
    torch.testing.assert_close(grad, expected)


# --- theta learns whom to trust ---------------------------------------------------------


class _Scripted(nn.Module):
    """A Q critic that values one fixed key: Q(s, right) = 1, every other key 0."""

    def __init__(self, right: int) -> None:
        super().__init__()
        self.right = right
        self.bias = nn.Parameter(torch.zeros(()))  # something for the critic's optimiser

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(*obs.shape[:-1], 4)
        q[..., self.right] = 1.0
        return q + 0 * self.bias


def scripted_batch(policy: SharedPolicyModule, machine_key: int, human_key: int, n: int = 64) -> TensorDict:
    td = TensorDict({"observation": torch.zeros(n, 8),
                     "human_action": torch.nn.functional.one_hot(torch.full((n,), human_key), 4),
                     "human_confidence": torch.full((n, 1), 0.5)}, [n])
    td = policy(td)
    td["machine_probs"] = torch.nn.functional.one_hot(torch.full((n,), machine_key), 4).float()
    td["next"] = TensorDict({"observation": torch.zeros(n, 8), "reward": torch.zeros(n, 1),
                             "done": torch.ones(n, 1, dtype=torch.bool),
                             "terminated": torch.ones(n, 1, dtype=torch.bool)}, [n])
    return td


@pytest.mark.parametrize("arbiter", [lambda: ConfidenceArbiter(1.0), lambda: CentredConfidenceArbiter(0.0)])
@pytest.mark.parametrize(("right", "towards"), [(0, "machine"), (1, "human")])
def test_theta_moves_towards_the_partner_that_is_right(arbiter, right, towards):
    """The machine always presses key 0, the operator key 1; the critic values only ``right``."""
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net()), arbiter(), OneHot(4))
    learner = DiscreteOnlineLearner(policy, _Scripted(right), theta_lr=0.5, critic_lr=0.0, gamma=0.99, tau=1e-3,
                            updates_per_batch=5)
    before = policy["arbiter"].theta.item()
    batch = scripted_batch(policy, machine_key=0, human_key=1)
    learner(batch)
    after = policy["arbiter"].theta.item()
    assert len(learner.history) == 5
    assert (after > before) if towards == "machine" else (after < before)


def test_a_held_critic_stays_exactly_as_warmed_up_while_theta_learns_from_it():
    """``critic_lr=0.0`` (LunarLander's default): the online steps move theta, not the critic."""
    torch.manual_seed(0)
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net()), CentredConfidenceArbiter(0.0), OneHot(4))
    learner = DiscreteOnlineLearner(policy, lunar_critic([16], 4), theta_lr=0.5, critic_lr=0.0, gamma=0.99, tau=1e-3,
                                    updates_per_batch=3)
    batch = scripted_batch(policy, machine_key=0, human_key=1)
    batch["next", "observation"] = torch.randn(64, 8)
    batch["next", "reward"] = torch.randn(64, 1)
    held = {name: p.detach().clone() for name, p in learner.critic_params.items(True, True)}
    before = policy["arbiter"].theta.item()
    learner(batch)
    assert policy["arbiter"].theta.item() != before
    assert all(torch.equal(p, held[name]) for name, p in learner.critic_params.items(True, True))
    assert all(row["loss_critic"] > 0 for row in learner.history)  # the TD loss is still computed and logged


# --- confidences that carry signal --------------------------------------------------------


def test_calibrated_unit_puts_the_median_uncertainty_at_half_confidence_and_spreads_b_m():
    g = torch.Generator().manual_seed(0)
    uncertainty = torch.exp(torch.randn(2000, generator=g)) * 1e-4  # dropout-sized variances
    raw = machine_confidence(uncertainty.double(), 0.6, 1.05)
    assert torch.quantile(raw, 0.1) > 0.99  # read raw, b_m carries no signal
    scale = calibrated_uncertainty_scale(uncertainty, 0.6, 1.05)
    b_m = machine_confidence(uncertainty.double() / scale, 0.6, 1.05)
    assert torch.quantile(b_m, 0.5).item() == pytest.approx(0.5, abs=1e-3)
    assert torch.quantile(b_m, 0.1) < 0.4 and torch.quantile(b_m, 0.9) > 0.6  # it spans its range


def test_calibration_refuses_a_machine_that_is_always_certain():
    with pytest.raises(ValueError, match="certain"):
        calibrated_uncertainty_scale(torch.zeros(10), 0.6, 1.05)


def test_mc_dropout_policy_reads_uncertainty_in_its_unit():
    torch.manual_seed(0)
    net = dropout_net()
    td = TensorDict({"observation": torch.randn(16, 8)}, [16])
    torch.manual_seed(1)
    raw = MCDropoutPolicy(net)(td.clone())
    torch.manual_seed(1)
    scaled = MCDropoutPolicy(net, uncertainty_scale=0.01)(td.clone())
    torch.testing.assert_close(raw["machine_uncertainty"], scaled["machine_uncertainty"])
    expected = machine_confidence(raw["machine_uncertainty"] / 0.01, 0.6, 1.05)
    torch.testing.assert_close(scaled["machine_confidence"], expected)
    with pytest.raises(ValueError, match="uncertainty_scale"):
        MCDropoutPolicy(net, uncertainty_scale=0.0)


def test_the_q_critic_value_changes_with_the_pads_x():
    torch.manual_seed(0)
    critic = lunar_critic([16, 16], 4, obs_dims=LUNAR_QVALUE_DIMS)
    obs = torch.zeros(2, 9)
    obs[1, 8] = 0.6  # the same lander, the pad moved
    q = critic(obs)
    assert not torch.allclose(q[0], q[1])


def test_human_confidence_falls_after_a_late_decision_once_k_reached_K():
    transform = HumanConfidenceTransform(K=5.0, t_d=1.0, k0=5.0)
    td = TensorDict({"knowledge": torch.full((2, 1), 5.0)}, [2])
    nxt = TensorDict({"human_rt": torch.tensor([[0.3], [1.6]]),
                      "human_decided": torch.ones(2, 1, dtype=torch.bool)}, [2])
    out = transform._step(td, nxt)
    assert out["knowledge"][0].item() == pytest.approx(5.0)
    assert out["knowledge"][1].item() < 5.0
    assert out["human_confidence"][1] != out["human_confidence"][0]
    strict = HumanConfidenceTransform(K=5.0, t_d=1.0, k0=5.0, cap="absorbing")._step(td, nxt.clone())
    assert strict["knowledge"].eq(5.0).all()
