"""The DC-SC modules: MC-dropout machine, arbiters, shared policy, losses (Eqs. 10-19)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, OneHot
from torchrl.objectives import DDPGLoss, SoftUpdate

from dcsc_torchrl.arbiters import (
    ConfidenceArbiter,
    HULAArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
    RuleArbiter,
    confidence_ratio,
)
from dcsc_torchrl.confidence import machine_confidence, mc_dropout_uncertainty
from dcsc_torchrl.losses import QCriticLoss, ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.policy import SharedPolicyModule


def dropout_net(n_in: int = 8, n_out: int = 4, p: float = 0.2) -> nn.Module:
    return nn.Sequential(nn.Linear(n_in, 32), nn.Tanh(), nn.Dropout(p), nn.Linear(32, n_out))


def confidences(batch: int, generator: torch.Generator) -> TensorDict:
    return TensorDict(
        {
            "machine_confidence": torch.rand(batch, 1, generator=generator),
            "human_confidence": torch.rand(batch, 1, generator=generator),
            "machine_uncertainty": torch.rand(batch, 1, generator=generator),
        },
        [batch],
    )


# ---------------------------------------------------------------- MC dropout


def test_mc_dropout_policy_matches_eq10_on_its_own_samples():
    torch.manual_seed(0)
    machine = MCDropoutPolicy(dropout_net(), output="probs", num_samples=16, lam=0.6, delta2=1.05)
    obs = torch.randn(5, 8)
    torch.manual_seed(1)
    samples = machine.sample(obs)
    torch.manual_seed(1)
    td = machine(TensorDict({"observation": obs}, [5]))
    mean, c = mc_dropout_uncertainty(samples)
    torch.testing.assert_close(td["machine_probs"], mean)
    torch.testing.assert_close(td["machine_uncertainty"], c)
    torch.testing.assert_close(td["machine_confidence"], machine_confidence(c, 0.6, 1.05))
    assert samples.shape == (16, 5, 4)
    # each of the M rows got its own dropout mask: the samples differ
    assert (samples.std(0) > 0).any()
    torch.testing.assert_close(td["machine_probs"].sum(-1), torch.ones(5))


def test_mc_dropout_network_stays_in_eval_mode_outside_the_pass():
    net = dropout_net()
    machine = MCDropoutPolicy(net, output="action")
    machine.train()
    assert not net.training and not any(m.training for m in net.modules())
    machine(TensorDict({"observation": torch.randn(3, 8)}, [3]))
    assert not any(m.training for m in net.modules())
    obs = torch.randn(3, 8)
    torch.testing.assert_close(net(obs), net(obs))  # deterministic outside the pass


def test_mc_dropout_more_dropout_means_more_uncertainty():
    torch.manual_seed(0)
    base = dropout_net(p=0.05)
    noisy = dropout_net(p=0.5)
    noisy.load_state_dict(base.state_dict())
    obs = TensorDict({"observation": torch.randn(256, 8)}, [256])
    low = MCDropoutPolicy(base, num_samples=32)(obs.clone())
    high = MCDropoutPolicy(noisy, num_samples=32)(obs.clone())
    assert high["machine_uncertainty"].mean() > low["machine_uncertainty"].mean()
    assert high["machine_confidence"].mean() < low["machine_confidence"].mean()


@pytest.mark.parametrize(
    "kwargs, name",
    [({"num_samples": 0}, "num_samples"), ({"lam": 1.0}, "lam"), ({"delta2": 1.0}, "delta2"),
     ({"tau_inv": -1.0}, "tau_inv"), ({"output": "logits"}, "output")],
)
def test_mc_dropout_rejects_bad_parameters(kwargs, name):
    with pytest.raises(ValueError, match=name):
        MCDropoutPolicy(dropout_net(), **kwargs)


def test_mc_dropout_needs_dropout_and_finite_observations():
    with pytest.raises(ValueError, match="dropout"):
        MCDropoutPolicy(nn.Linear(8, 4))
    machine = MCDropoutPolicy(dropout_net())
    with pytest.raises(ValueError, match="observation"):
        machine(TensorDict({"observation": torch.full((2, 8), float("nan"))}, [2]))


# ---------------------------------------------------------------- arbiters


def test_confidence_ratio_is_eq18_and_defined_at_zero():
    b_m, b_h = torch.tensor([0.9, 0.2, 0.0, 0.0]), torch.tensor([0.1, 0.6, 0.5, 0.0])
    torch.testing.assert_close(confidence_ratio(b_m, b_h), torch.tensor([0.9, 0.25, 0.0, 0.5]))


def test_every_arbiter_gives_the_beta_it_should():
    g = torch.Generator().manual_seed(0)
    td = confidences(64, g)
    ratio = td["machine_confidence"] / (td["machine_confidence"] + td["human_confidence"])
    assert (MachineOnlyArbiter(dims=3)(td.clone())["beta"] == 1).all()
    assert (HumanOnlyArbiter(dims=3)(td.clone())["beta"] == 0).all()
    out = ConfidenceArbiter(theta_init=2.5, dims=1)(td.clone())
    torch.testing.assert_close(out["beta"], 1 / (1 + torch.exp(-2.5 * ratio)))
    torch.testing.assert_close(out["confidence_ratio"], ratio)
    hula = HULAArbiter(threshold=0.5, dims=3)(td.clone())
    expected = (td["machine_uncertainty"] <= 0.5).float().expand(64, 3)
    torch.testing.assert_close(hula["beta"], expected)
    assert hula["beta"].shape == (64, 3)


def test_rule_arbiter_gives_the_machine_the_frames_its_rule_holds_on():
    td = confidences(6, torch.Generator().manual_seed(2)).set("observation", torch.linspace(-1, 1, 6).unsqueeze(-1))
    out = RuleArbiter(lambda obs: obs[..., 0] > 0, dims=3)(td)
    assert out["beta"].tolist() == [[0.0] * 3] * 3 + [[1.0] * 3] * 3
    assert "observation" in RuleArbiter(lambda obs: obs[..., 0] > 0).in_keys


@pytest.mark.parametrize(
    "rule, message",
    [(lambda obs: obs[..., 0] * 2, "rule share must be in"), (lambda obs: obs > 0, "one share per frame")],
)
def test_rule_arbiter_refuses_a_share_out_of_range_or_of_the_wrong_shape(rule, message):
    td = confidences(3, torch.Generator().manual_seed(3)).set("observation", torch.ones(3, 2))
    with pytest.raises(ValueError, match=message):
        RuleArbiter(rule)(td)


def test_confidence_arbiter_keeps_beta_at_least_half_for_nonnegative_theta():
    td = confidences(128, torch.Generator().manual_seed(1))
    beta = ConfidenceArbiter(theta_init=0.7, dims=3)(td)["beta"]
    assert (beta >= 0.5).all() and (beta <= torch.sigmoid(torch.tensor(0.7)) + 1e-6).all()


def test_confidence_arbiter_has_one_theta_per_action_dimension():
    arbiter = ConfidenceArbiter(theta_init=0.0, dims=3)
    assert [p.shape for p in arbiter.parameters()] == [torch.Size([3])]
    with torch.no_grad():
        arbiter.theta.copy_(torch.tensor([-1.0, 0.0, 1.0]))
    td = TensorDict({"machine_confidence": torch.ones(1, 1), "human_confidence": torch.zeros(1, 1)}, [1])
    torch.testing.assert_close(arbiter(td)["beta"], torch.sigmoid(torch.tensor([[-1.0, 0.0, 1.0]])))


@pytest.mark.parametrize(
    "make, name",
    [(lambda: HULAArbiter(threshold=-0.1), "threshold"), (lambda: ConfidenceArbiter(dims=0), "dims"),
     (lambda: ConfidenceArbiter(theta_init=float("nan")), "theta_init")],
)
def test_arbiters_reject_bad_parameters(make, name):
    with pytest.raises(ValueError, match=name):
        make()


def test_arbiter_rejects_nonfinite_confidence():
    td = TensorDict({"machine_confidence": torch.tensor([[float("nan")]]), "human_confidence": torch.zeros(1, 1)}, [1])
    with pytest.raises(ValueError, match="machine_confidence"):
        ConfidenceArbiter()(td)


# ---------------------------------------------------------------- shared policy


def test_discrete_shared_policy_samples_from_the_eq14_mixture():
    torch.manual_seed(0)
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net(), num_samples=8), ConfidenceArbiter(1.0), OneHot(4))
    n = 4000
    human = torch.nn.functional.one_hot(torch.full((n,), 2), 4)
    td = TensorDict({"observation": torch.zeros(n, 8), "human_action": human, "human_confidence": torch.full((n, 1), 0.2)}, [n])
    out = policy(td)
    expected = out["beta"] * out["machine_probs"] + (1 - out["beta"]) * human
    torch.testing.assert_close(out["probs"], expected)
    assert out["action"].shape == (n, 4) and (out["action"].sum(-1) == 1).all()
    freq = out["action"].float().mean(0)
    torch.testing.assert_close(freq, out["probs"].mean(0), atol=0.03, rtol=0)
    assert isinstance(policy["arbiter"], ConfidenceArbiter)


def test_continuous_shared_policy_blends_and_clips_to_the_box():
    spec = Bounded(0.0, 3.0, shape=(3,))
    net = nn.Sequential(nn.Linear(9, 16), nn.Dropout(0.1), nn.Linear(16, 3))
    policy = SharedPolicyModule(MCDropoutPolicy(net, output="action"), HumanOnlyArbiter(dims=3), spec)
    human = torch.tensor([[5.0, -1.0, 1.5]])
    td = TensorDict({"observation": torch.randn(1, 9), "human_action": human, "human_confidence": torch.ones(1, 1)}, [1])
    torch.testing.assert_close(policy(td)["action"], torch.tensor([[3.0, 0.0, 1.5]]))


def test_shared_policy_rejects_mismatched_parts():
    with pytest.raises(ValueError, match="probs"):
        SharedPolicyModule(MCDropoutPolicy(dropout_net(), output="action"), ConfidenceArbiter(), OneHot(4))
    with pytest.raises(TypeError, match="OneHot"):
        SharedPolicyModule(MCDropoutPolicy(dropout_net()), ConfidenceArbiter(), torch.zeros(3))


# ---------------------------------------------------------------- losses and Eq. 19


def discrete_batch(n: int, g: torch.Generator, policy: SharedPolicyModule) -> TensorDict:
    human = torch.nn.functional.one_hot(torch.randint(4, (n,), generator=g), 4)
    td = TensorDict(
        {"observation": torch.randn(n, 8, generator=g), "human_action": human,
         "human_confidence": torch.rand(n, 1, generator=g)},
        [n],
    )
    td = policy(td)
    td["next"] = TensorDict(
        {"observation": torch.randn(n, 8, generator=g), "reward": torch.randn(n, 1, generator=g),
         "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.rand(n, 1, generator=g) < 0.2},
        [n],
    )
    return td


def test_theta_loss_gradient_is_eq19():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net()), ConfidenceArbiter(0.8), OneHot(4))
    qnet = TensorDictModule(nn.Linear(8, 4), ["observation"], ["action_value"])
    loss = ThetaLoss(policy, qnet, gamma=0.99)
    batch = discrete_batch(32, g, policy)
    out = loss(batch)
    out["loss_theta"].backward()
    theta = policy["arbiter"].theta
    with torch.no_grad():
        b = batch["confidence_ratio"]
        beta = torch.sigmoid(theta * b)
        q = qnet(batch.clone())["action_value"]
        grad_j = (b * (beta - beta**2) * ((batch["machine_probs"] - batch["human_action"]) * q).sum(-1, keepdim=True)).mean()
    torch.testing.assert_close(theta.grad, -grad_j.reshape(1))
    assert theta.grad.abs().item() > 0


def test_q_critic_loss_uses_the_max_target_of_algorithm1():
    qnet = TensorDictModule(nn.Linear(8, 4), ["observation"], ["action_value"])
    loss = QCriticLoss(qnet, gamma=0.9)
    g = torch.Generator().manual_seed(3)
    n = 16
    batch = TensorDict(
        {"observation": torch.randn(n, 8, generator=g),
         "action": torch.nn.functional.one_hot(torch.randint(4, (n,), generator=g), 4),
         "next": {"observation": torch.randn(n, 8, generator=g), "reward": torch.randn(n, 1, generator=g),
                  "done": torch.zeros(n, 1, dtype=torch.bool),
                  "terminated": torch.arange(n).reshape(n, 1) % 4 == 0}},
        [n],
    )
    out = loss(batch)
    with torch.no_grad():
        q = qnet(batch.clone())["action_value"]
        pred = (q * batch["action"]).sum(-1, keepdim=True)
        next_max = qnet(batch["next"].clone())["action_value"].max(-1, keepdim=True).values
        y = batch["next", "reward"] + 0.9 * (~batch["next", "terminated"]).float() * next_max
    torch.testing.assert_close(out["loss_qvalue"], ((pred - y) ** 2).mean())
    out["loss_qvalue"].backward()
    assert all(p.grad is not None for p in loss.qvalue_network_params.values(True, True))


def test_soft_update_moves_the_target_critic():
    qnet = TensorDictModule(nn.Linear(8, 4), ["observation"], ["action_value"])
    loss = QCriticLoss(qnet)
    updater = SoftUpdate(loss, tau=0.1)
    with torch.no_grad():
        for p in loss.qvalue_network_params.values(True, True):
            p.add_(1.0)
    before = loss.target_qvalue_network_params.clone()
    updater.step()
    after = loss.target_qvalue_network_params
    for key, value in after.items(True, True):
        source = loss.qvalue_network_params[key]
        torch.testing.assert_close(value, 0.9 * before[key] + 0.1 * source)


def test_theta_loss_rejects_a_continuous_policy_and_bad_gamma():
    spec = Bounded(0.0, 3.0, shape=(3,))
    policy = SharedPolicyModule(MCDropoutPolicy(dropout_net(9, 3), output="action"), ConfidenceArbiter(dims=3), spec)
    qnet = TensorDictModule(nn.Linear(9, 4), ["observation"], ["action_value"])
    with pytest.raises(ValueError, match="DDPGLoss"):
        ThetaLoss(policy, qnet)
    with pytest.raises(ValueError, match="gamma"):
        QCriticLoss(qnet, gamma=1.5)


class _Critic(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(12, 32), nn.Tanh(), nn.Linear(32, 1))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], -1))


def test_ddpg_loss_gives_theta_the_eq19_gradient():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    spec = Bounded(0.0, 3.0, shape=(3,))
    machine_net = nn.Sequential(nn.Linear(9, 32), nn.Tanh(), nn.Dropout(0.05), nn.Linear(32, 3), nn.Sigmoid())
    machine_net.requires_grad_(False)  # the machine is frozen; only theta trains
    arbiter = ConfidenceArbiter(theta_init=0.5, dims=3)
    policy = SharedPolicyModule(MCDropoutPolicy(machine_net, output="action"), arbiter, spec)
    critic = TensorDictModule(_Critic(), ["observation", "action"], ["state_action_value"])
    loss = DDPGLoss(policy, critic)
    n = 24
    batch = TensorDict(
        {"observation": torch.randn(n, 9, generator=g),
         "human_action": 0.5 + torch.rand(n, 3, generator=g),
         "human_confidence": torch.rand(n, 1, generator=g)},
        [n],
    )
    torch.manual_seed(5)
    out = loss.loss_actor(batch)[0]
    theta = loss.actor_network_params["module", "arbiter", "theta"]
    (grad,) = torch.autograd.grad(out, theta)
    # replay the same dropout draw to get a_m, then Eq. 19's closed form
    torch.manual_seed(5)
    td = policy(batch.clone())
    a = td["action"].detach().requires_grad_(True)
    q = critic.module(td["observation"], a)
    (dq_da,) = torch.autograd.grad(q.sum(), a)
    b, beta = td["confidence_ratio"], td["beta"].detach()
    expected = -(b * beta * (1 - beta) * (td["machine_action"] - td["human_action"]) * dq_da).mean(0)
    torch.testing.assert_close(grad, expected)
    assert grad.abs().min() > 0


def _ddpg_loss(seed: int) -> DDPGLoss:
    torch.manual_seed(seed)
    actor = TensorDictModule(nn.Sequential(nn.Linear(4, 16), nn.ReLU(), nn.Linear(16, 2)), ["observation"], ["action"])
    critic = TensorDictModule(nn.Sequential(nn.Linear(6, 16), nn.ReLU(), nn.Linear(16, 1)),
                              ["observation", "action"], ["state_action_value"])
    return DDPGLoss(actor, critic, delay_actor=True, delay_value=True)


def test_the_foreach_soft_update_is_torchrls_to_the_bit_also_after_a_load():
    from dcsc_torchrl.losses import ForeachSoftUpdate

    losses = [_ddpg_loss(0), _ddpg_loss(0)]
    updaters = [SoftUpdate(losses[0], eps=0.99), ForeachSoftUpdate(losses[1], eps=0.99)]
    for step in range(12):
        if step == 6:  # a resumed run loads another state into the same loss
            state = _ddpg_loss(1).state_dict()
            for loss in losses:
                loss.load_state_dict(state)
        for loss, updater in zip(losses, updaters, strict=True):
            generator = torch.Generator().manual_seed(step)
            with torch.no_grad():  # an optimiser's step, the same on both
                for param in loss.parameters():
                    if param.requires_grad:
                        param.add_(torch.randn(param.shape, generator=generator))
            updater.step()
    torchrl, ours = (loss.state_dict() for loss in losses)
    assert ours.keys() == torchrl.keys()
    assert all(torch.equal(ours[key], torchrl[key]) for key in torchrl)
    assert not torch.equal(ours["target_value_network_params.module.0.weight"],
                           ours["value_network_params.module.0.weight"])  # the targets lag, as they should
