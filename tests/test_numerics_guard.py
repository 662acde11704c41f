"""Nothing silently wrong (issue #37): a bad value is refused where it enters, on every frame.

The five cases of the issue: a NaN observation after the first frame, an observation of
another width, a discrete human action that is not one-hot, an arbiter's state saved and
loaded (into another form, for another task), and a Ctrl-C inside a loss's critic call.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import OneHot, Unbounded
from torchrl.envs import GymWrapper, TransformedEnv

from dcsc_torchrl.arbiters import (
    CentredConfidenceArbiter,
    ConfidenceArbiter,
    ConstantArbiter,
    FrozenConfidenceArbiter,
    HULAArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
    load_arbiter,
    save_arbiter,
)
from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.checkpoint import CheckpointError
from dcsc_torchrl.checks import _DeferredChecks, check_values
from dcsc_torchrl.config import UsageError
from dcsc_torchrl.losses import AuthorityThetaLoss, QCriticLoss, ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import lunar_actor
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.transforms import HumanOperatorTransform

NAN_FROM = 100


def net(n_in: int = 9, n_out: int = 4) -> nn.Module:
    return nn.Sequential(nn.Linear(n_in, 16), nn.Tanh(), nn.Dropout(0.1), nn.Linear(16, n_out))


class NaNFrom(gym.ObservationWrapper):
    """LunarLander whose observations are NaN from the ``start``-th one on (resets included)."""

    def __init__(self, env: gym.Env, start: int) -> None:
        super().__init__(env)
        self.start = start
        self.seen = 0

    def observation(self, observation: np.ndarray) -> np.ndarray:
        self.seen += 1
        return np.full_like(observation, np.nan) if self.seen > self.start else observation


class KeyOne:
    """An operator that always holds key 1 (RT 0.3 s)."""

    def reset(self, seed: int | None) -> None:
        pass

    def __call__(self, td: TensorDict) -> TensorDict:
        batch = td.batch_size
        return TensorDict({"human_action": torch.eye(4)[1].expand(*batch, 4).clone(),
                           "human_rt": torch.full((*batch, 1), 0.3),
                           "human_decided": torch.ones(*batch, 1, dtype=torch.bool)}, batch)


def policy_frame(obs: torch.Tensor, human_action: torch.Tensor | None = None) -> TensorDict:
    return TensorDict({"observation": obs, "human_action": torch.eye(4)[2] if human_action is None else human_action,
                       "human_confidence": torch.tensor([0.3])}, [])


# ---------------------------------------------------------------- 1. a NaN after the first frame


def test_a_nan_observation_from_frame_100_of_a_rollout_is_refused_at_the_transform_naming_it():
    wrapper = NaNFrom(gym.make(LUNAR_ID), NAN_FROM)
    env = TransformedEnv(GymWrapper(wrapper), HumanOperatorTransform(KeyOne(), seed=0))
    env.set_seed(0)
    with pytest.raises(ValueError, match=r"the env's 'observation' \(before the operator saw it\) has 9 non-finite"):
        env.rollout(3 * NAN_FROM, break_when_any_done=False)
    assert wrapper.seen == NAN_FROM + 1  # refused on the first NaN frame


def test_a_nan_observation_after_100_good_frames_is_refused_by_the_shared_policy_naming_it():
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    g = torch.Generator().manual_seed(0)
    for _ in range(NAN_FROM):
        policy(policy_frame(torch.randn(9, generator=g)))
    with pytest.raises(ValueError, match=r"^observation has 1 non-finite value\(s\) of 9: nan at index \(2,\)"):
        policy(policy_frame(torch.randn(9, generator=g).index_fill(0, torch.tensor([2]), math.nan)))


@pytest.mark.parametrize("key", ["machine_confidence", "human_confidence"])
def test_a_nan_confidence_after_the_first_frame_is_refused_by_the_arbiter(key):
    arbiter = ConfidenceArbiter()
    good = TensorDict({"machine_confidence": torch.full((2, 1), 0.5), "human_confidence": torch.full((2, 1), 0.5)}, [2])
    arbiter(good.clone())
    with pytest.raises(ValueError, match=rf"^{key} must be in \[0.0, 1.0\], got nan \(1 of 2 elements out of range\)$"):
        arbiter(good.clone().set(key, torch.tensor([[0.5], [math.nan]])))


@pytest.mark.parametrize("form", [ConfidenceArbiter, CentredConfidenceArbiter])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_theta_set_to_nan_or_inf_is_refused_naming_theta(form, bad):
    arbiter = form()
    td = TensorDict({"machine_confidence": torch.zeros(1, 1), "human_confidence": torch.ones(1, 1)}, [1])
    arbiter(td.clone())
    with torch.no_grad():
        arbiter.theta.fill_(bad)
    with pytest.raises(ValueError, match=rf"^theta \({form.__name__}\) has 1 non-finite value"):
        arbiter(td.clone())


# ---------------------------------------------------------------- 2. an observation of another width


def test_the_lunar_actor_knows_its_observation_width_and_refuses_another_naming_both():
    machine = MCDropoutPolicy(lunar_actor([16], 0.1))  # no observation_size passed (the README's example)
    assert machine.observation_size == 9
    machine(TensorDict({"observation": torch.zeros(2, 9)}, [2]))
    with pytest.raises(ValueError, match=r"^'observation' has 20 values per frame but the machine network was built "
                                         r"for 9 \(observation_size\)"):
        machine(TensorDict({"observation": torch.zeros(2, 20)}, [2]))
    with pytest.raises(ValueError, match=r"^the network's input has 20 values per frame but it was built for 9 "
                                         r"\(FirstDims\(8, in_dims=9\)\)$"):
        lunar_actor([16], 0.1)(torch.zeros(2, 20))
    with pytest.raises(ValueError, match=r"'observation' has 20 values but the machine network was built for 9"):
        SharedPolicyModule(MCDropoutPolicy(lunar_actor([16], 0.1)), ConfidenceArbiter(), OneHot(4),
                           observation_spec=Unbounded(shape=(20,)))


# ---------------------------------------------------------------- 3. a human action that is not one-hot


@pytest.mark.parametrize(
    ("human_action", "message"),
    [([1, 1, 0, 0], r"human_action's sum per frame \(one-hot or probabilities\) must be in \[1.0, 1.0\], got 2"),
     ([0.0, 0.0, 0.0, 0.0], r"human_action's sum per frame .* got 0.0"),
     ([1.5, -0.5, 0.0, 0.0], r"human_action must be in \[0.0, 1.0\], got 1.5"),
     ([math.nan, 1.0, 0.0, 0.0], r"human_action must be in \[0.0, 1.0\], got nan")],
)
def test_a_discrete_human_action_that_is_not_one_hot_is_refused_by_the_policy(human_action, message):
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    with pytest.raises(ValueError, match=message):
        policy(policy_frame(torch.zeros(9), torch.tensor(human_action)))


def test_a_one_hot_human_action_gives_probabilities_summing_to_one():
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    probs = policy(policy_frame(torch.zeros(9), torch.tensor([0, 1, 0, 0])))["probs"]
    assert probs.sum().item() == pytest.approx(1.0)


# ---------------------------------------------------------------- 4. arbiters saved and loaded

ARBITERS = {
    "paper": lambda: ConfidenceArbiter(theta_init=0.7, dims=3),
    "centred": lambda: CentredConfidenceArbiter(theta_init=-0.4, gain=2.5),
    "hula": lambda: HULAArbiter(0.35, dims=3),
    "constant": lambda: ConstantArbiter(0.3),
    "machine": lambda: MachineOnlyArbiter(dims=3),
    "operator": lambda: HumanOnlyArbiter(),
    "frozen": lambda: FrozenConfidenceArbiter(CentredConfidenceArbiter(0.2, gain=1.5), 0.6, 0.2),
}


def arbiter_batch() -> TensorDict:
    g = torch.Generator().manual_seed(5)
    return TensorDict({key: torch.rand(16, 1, generator=g)
                       for key in ("machine_confidence", "human_confidence", "machine_uncertainty")}, [16])


@pytest.mark.parametrize("name", list(ARBITERS))
def test_a_saved_arbiter_loads_back_with_the_same_beta(tmp_path, name):
    arbiter = ARBITERS[name]()
    if hasattr(arbiter, "theta"):
        with torch.no_grad():
            arbiter.theta.add_(0.125)  # trained away from its start
    path = save_arbiter(arbiter, tmp_path / "arbiter.pt", task="lunarlander")
    loaded = load_arbiter(path, task="lunarlander")
    assert type(loaded) is type(arbiter) and loaded.dims == arbiter.dims
    assert torch.equal(loaded(arbiter_batch())["beta"], arbiter(arbiter_batch())["beta"])


def test_the_state_dict_holds_the_whole_arbiter_and_restores_it():
    state = CentredConfidenceArbiter(0.1, gain=2.5).state_dict()
    assert state["_extra_state"] == {"form": "CentredConfidenceArbiter", "dims": 1, "arguments": {"gain": 2.5}}
    other = CentredConfidenceArbiter()
    other.load_state_dict(state)
    assert other.gain == 2.5 and other.theta.item() == pytest.approx(0.1)


def test_a_centred_file_into_a_paper_arbiter_is_refused_naming_both_forms(tmp_path):
    path = save_arbiter(CentredConfidenceArbiter(), tmp_path / "arbiter.pt", task="lunarlander")
    paper = ConfidenceArbiter(theta_init=0.7)
    with pytest.raises(CheckpointError, match=r"a CentredConfidenceArbiter's state cannot be loaded into a "
                                              r"ConfidenceArbiter \(another arbiter form\)$"):
        load_arbiter(path, task="lunarlander", into=paper)
    assert paper.theta.item() == pytest.approx(0.7)  # refused before anything was loaded


@pytest.mark.parametrize(
    ("source", "target", "message"),
    [(ConfidenceArbiter, CentredConfidenceArbiter, "a ConfidenceArbiter's state cannot be loaded into a "
                                                   "CentredConfidenceArbiter"),
     (CentredConfidenceArbiter, ConfidenceArbiter, "a CentredConfidenceArbiter's state cannot be loaded into a "
                                                   "ConfidenceArbiter")],
)
def test_load_state_dict_of_another_form_fails_with_one_line(source, target, message):
    with pytest.raises(UsageError, match=message) as raised:
        target().load_state_dict(source().state_dict())
    assert "\n" not in str(raised.value)


def test_an_arbiter_file_of_another_task_is_refused_naming_both(tmp_path):
    path = save_arbiter(ConfidenceArbiter(), tmp_path / "arbiter.pt", task="uav")
    with pytest.raises(CheckpointError, match=r"was written for task 'uav', but this run is for task 'lunarlander'"):
        load_arbiter(path, task="lunarlander")


def test_an_arbiter_file_is_plain_data_written_atomically(tmp_path):
    path = save_arbiter(ConfidenceArbiter(), tmp_path / "arbiter.pt", task="uav")
    data = torch.load(path, weights_only=True)
    assert data["task"] == "uav" and data["arbiter"]["_extra_state"]["form"] == "ConfidenceArbiter"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arbiter.pt"]  # no temporary file left


# ---------------------------------------------------------------- 5. Ctrl-C inside a loss's critic call


class Interrupting(nn.Module):
    """A critic whose forward raises ``error`` once armed (a Ctrl-C arriving there), on its ``on``-th call from then."""

    def __init__(self, n_in: int, n_out: int) -> None:
        super().__init__()
        self.linear = nn.Linear(n_in, n_out)
        self.error: type[BaseException] | None = None
        self.on = 1

    def arm(self, error: type[BaseException], on: int = 1) -> None:
        self.error, self.on = error, on

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if self.error is not None:
            self.on -= 1
            if self.on == 0:
                raise self.error
        return self.linear(torch.cat(inputs, -1))


def discrete_batch(n: int = 4) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    return TensorDict(
        {"observation": torch.randn(n, 9, generator=g), "action": torch.eye(4)[torch.arange(n) % 4].long(),
         "human_action": torch.eye(4)[torch.arange(n) % 4].long(), "machine_probs": torch.full((n, 4), 0.25),
         "machine_confidence": torch.rand(n, 1, generator=g), "human_confidence": torch.rand(n, 1, generator=g),
         "beta": torch.rand(n, 1, generator=g),
         "next": {"observation": torch.randn(n, 9, generator=g), "reward": torch.randn(n, 1, generator=g),
                  "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.zeros(n, 1, dtype=torch.bool)}},
        [n],
    )


def q_loss() -> tuple[QCriticLoss, Interrupting]:
    critic = Interrupting(9, 4)
    return QCriticLoss(TensorDictModule(critic, ["observation"], ["action_value"])), critic


def theta_loss() -> tuple[ThetaLoss, Interrupting]:
    critic = Interrupting(9, 4)
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    return ThetaLoss(policy, TensorDictModule(critic, ["observation"], ["action_value"])), critic


def authority_loss() -> tuple[AuthorityThetaLoss, Interrupting]:
    critic = Interrupting(10, 1)
    return AuthorityThetaLoss(CentredConfidenceArbiter(),
                              TensorDictModule(critic, ["observation", "beta"], ["state_value"])), critic


@pytest.mark.parametrize("make", [q_loss, theta_loss, authority_loss], ids=["QCriticLoss", "ThetaLoss", "Authority"])
def test_a_ctrl_c_inside_a_loss_critic_propagates_as_keyboard_interrupt(make):
    loss, critic = make()
    own = critic.linear.weight
    loss(discrete_batch())  # runs
    critic.arm(KeyboardInterrupt)
    with pytest.raises(KeyboardInterrupt):
        loss(discrete_batch())
    assert critic.linear.weight is own  # the critic got its own parameters back


def test_an_error_inside_the_target_critic_call_leaves_the_critic_its_own_parameters():
    loss, critic = q_loss()
    own = critic.linear.weight
    critic.arm(ArithmeticError, on=2)  # the second call: Q'(s', .) with the target parameters
    with pytest.raises(ArithmeticError):
        loss(discrete_batch())
    assert critic.linear.weight is own


# ---------------------------------------------------------------- the check itself


def test_check_values_costs_one_reduction_and_names_the_key():
    ok = torch.rand(3, 4)
    assert check_values("b", ok, 0.0, 1.0) is ok
    assert check_values("empty", torch.empty(0, 4), 0.0, 1.0).numel() == 0
    assert check_values("ints", torch.tensor([3, 4])) is not None  # integers are finite
    with pytest.raises(ValueError, match=r"^b must be in \[0.0, 1.0\], got 2.0"):
        check_values("b", torch.tensor([0.5, 2.0]), 0.0, 1.0)
    with pytest.raises(ValueError, match=r"^rt has 1 non-finite value\(s\) of 2: -inf"):
        check_values("rt", torch.tensor([0.5, -math.inf]))


class FakeEvent:
    """Stands in for a CUDA event (this host may have none): done once the device got there."""

    def __init__(self) -> None:
        self.done = False

    def query(self) -> bool:
        return self.done

    def synchronize(self) -> None:
        self.done = True


def test_a_device_verdict_is_read_once_landed_oldest_first_and_raised_once():
    checks = _DeferredChecks()
    first, second = FakeEvent(), FakeEvent()
    checks.pending.extend([("beta must be in [0.0, 1.0]", torch.tensor(True), first),
                           ("observation must be finite", torch.tensor(False), second)])
    checks.read(wait=False)  # nothing landed: no waiting, nothing read
    assert len(checks.pending) == 2
    first.done = True
    checks.read(wait=False)  # the good verdict is read and dropped
    assert len(checks.pending) == 1
    with pytest.raises(ValueError, match="^observation must be finite$"):
        checks.read(wait=True)  # the flush waits for the last one
    assert not checks.pending
    checks.read(wait=True)  # raised once, then forgotten
