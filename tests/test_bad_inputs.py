"""Every bad input of the modules (issues #14, #37): where it is refused, the exception, and
that the one-line message names the culprit (the key, the parameter or the network).

Each row: an id, a callable that feeds the bad input, the exception type, and a regex the
message must match. The operator's answers and the env's frames are checked at the
transform that receives them; specs and sizes at construction; the confidences, theta, beta
and the machine's observation and output on every frame of the per-frame modules (one
reduction per tensor, no device sync: ``dcsc_torchrl.checks.check_values``).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, OneHot, Unbounded
from torchrl.envs import GymWrapper, TransformedEnv

from dcsc_torchrl.arbiters import (
    Arbiter,
    ConfidenceArbiter,
    ConstantArbiter,
    FrozenConfidenceArbiter,
    HULAArbiter,
    RuleArbiter,
    load_arbiter,
    save_arbiter,
)
from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.checkpoint import CheckpointError, save_checkpoint
from dcsc_torchrl.checks import flush_frame_checks
from dcsc_torchrl.confidence import human_confidence, machine_confidence
from dcsc_torchrl.humans.keyboard import KeyboardPilot
from dcsc_torchrl.losses import QCriticLoss, ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import FirstDims, lunar_actor
from dcsc_torchrl.policy import PolicyBlend, SharedPolicyModule, check_distribution
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform


def net(n_in: int = 9, n_out: int = 4) -> nn.Module:
    return nn.Sequential(nn.Linear(n_in, 16), nn.Tanh(), nn.Dropout(0.1), nn.Linear(16, n_out))


def frame(**entries: torch.Tensor) -> TensorDict:
    base = {"machine_confidence": torch.full((2, 1), 0.5), "human_confidence": torch.full((2, 1), 0.5)}
    base.update(entries)
    return TensorDict({k: v for k, v in base.items() if v is not None}, [2])


class ScriptedOperator:
    """Answers every frame with a fixed action, RT (0.3 s) and decision flag (a bool True)."""

    def __init__(self, action: list[float], dtype: torch.dtype = torch.float32, *, rt: float = 0.3,
                 decided: torch.Tensor | None = None) -> None:
        self.action = torch.tensor(action, dtype=dtype)
        self.rt = rt
        self.decided = torch.tensor(True) if decided is None else decided

    def reset(self, seed: int | None) -> None:
        pass

    def __call__(self, td: TensorDict) -> TensorDict:
        batch = td.batch_size
        return TensorDict(
            {
                "human_action": self.action.expand(*batch, -1).clone(),
                "human_rt": torch.full((*batch, 1), self.rt),
                "human_decided": self.decided.expand(*batch, 1).clone(),
            },
            batch,
        )


class NaNVelocity(gym.ObservationWrapper):
    """LunarLander whose horizontal velocity (index 2) is NaN on every frame."""

    def observation(self, observation: np.ndarray) -> np.ndarray:
        observation = observation.copy()
        observation[2] = np.nan
        return observation


def lunar_with(operator, *, nan_velocity: bool = False) -> TransformedEnv:
    base = gym.make(LUNAR_ID)
    env = GymWrapper(NaNVelocity(base) if nan_velocity else base)
    return TransformedEnv(env, HumanOperatorTransform(operator, seed=0))


def nan_weights() -> MCDropoutPolicy:
    network = net()
    with torch.no_grad():
        network[3].weight[0, :3] = float("nan")
    return MCDropoutPolicy(network)


class Overconfident(Arbiter):
    """A custom arbiter whose beta leaves [0, 1]."""

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDict) -> torch.Tensor:
        return torch.full_like(ratio, 1.5)


class TwoBetas(Arbiter):
    """A custom arbiter giving 2 betas per frame, whatever its dims."""

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDict) -> torch.Tensor:
        return ratio.expand(*ratio.shape[:-1], 2)


def blend(machine: list[float], human: list[float], **kwargs) -> torch.Tensor:
    return PolicyBlend(**kwargs)(torch.full((1, 1), 0.5), torch.tensor([machine]), torch.tensor([human]))


def q_batch(n: int = 4, **entries: torch.Tensor) -> TensorDict:
    batch = {"observation": torch.zeros(n, 9), "action": torch.eye(4)[torch.arange(n) % 4].long(),
             "next": {"observation": torch.zeros(n, 9), "reward": torch.zeros(n, 1),
                      "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.zeros(n, 1, dtype=torch.bool)}}
    batch.update(entries)
    return TensorDict(batch, [n])


def q_loss(batch: TensorDict):
    return QCriticLoss(TensorDictModule(nn.Linear(9, 4), ["observation"], ["action_value"]))(batch)


def theta_loss(**entries: torch.Tensor):
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    stored = {"human_action": torch.eye(4), "machine_confidence": torch.full((4, 1), 0.5),
              "human_confidence": torch.full((4, 1), 0.5), "machine_probs": torch.full((4, 4), 0.25)}
    batch = q_batch(**{**stored, **entries})
    return ThetaLoss(policy, TensorDictModule(nn.Linear(9, 4), ["observation"], ["action_value"]))(batch)


def arbiter_file_without_arbiter():
    with tempfile.TemporaryDirectory() as tmp:
        path = save_checkpoint(f"{tmp}/other.pt", task="lunarlander", payload={"state": {}})
        return load_arbiter(path, task="lunarlander")


def policy_without_transform():
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    td = TensorDict({"observation": torch.zeros(2, 9), "human_action": torch.eye(4)[:2]}, [2])
    return policy(td)


CASES: list[tuple[str, Callable[[], object], type[Exception], str]] = [
    # the confidences the arbiter reads (every frame)
    ("b_h=2", lambda: ConfidenceArbiter()(frame(human_confidence=torch.full((2, 1), 2.0))),
     ValueError, r"human_confidence must be in \[0.0, 1.0\], got 2.0"),
    ("b_h=-1", lambda: ConfidenceArbiter()(frame(human_confidence=torch.full((2, 1), -1.0))),
     ValueError, r"human_confidence must be in \[0.0, 1.0\], got -1.0"),
    ("b_m=1.5,b_h=-0.5", lambda: ConfidenceArbiter()(
        frame(machine_confidence=torch.full((2, 1), 1.5), human_confidence=torch.full((2, 1), -0.5))),
     ValueError, r"machine_confidence must be in \[0.0, 1.0\], got 1.5"),
    ("b_m=nan", lambda: ConfidenceArbiter()(frame(machine_confidence=torch.full((2, 1), math.nan))),
     ValueError, r"machine_confidence must be in \[0.0, 1.0\], got nan"),
    ("missing human_confidence", lambda: ConfidenceArbiter()(frame(human_confidence=None)),
     KeyError, r"ConfidenceArbiter reads 'human_confidence', which is missing: add HumanConfidenceTransform"),
    ("missing human_confidence, whole policy", policy_without_transform,
     KeyError, r"reads 'human_confidence', which is missing: add HumanConfidenceTransform to the env"),
    ("missing machine_uncertainty (HULA)", lambda: HULAArbiter(0.1)(frame()),
     KeyError, r"HULAArbiter reads 'machine_uncertainty', which is missing"),
    # specs and sizes at construction
    ("OneHot(6) over a 4-action machine", lambda: SharedPolicyModule(
        MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(6)),
     ValueError, r"OneHot\(6\) does not match the machine network, whose last layer gives 4"),
    ("Bounded(3) over a 2-output machine", lambda: SharedPolicyModule(
        MCDropoutPolicy(net(9, 2), output="action"), ConfidenceArbiter(dims=1), Bounded(0.0, 1.0, shape=(3,))),
     ValueError, r"Bounded\w*\(3\) does not match the machine network, whose last layer gives 2"),
    ("20-value observation spec for a 9-value machine", lambda: SharedPolicyModule(
        MCDropoutPolicy(lunar_actor([16], 0.1, obs_dims=8), observation_size=9), ConfidenceArbiter(), OneHot(4),
        observation_spec=Unbounded(shape=(20,))),
     ValueError, r"'observation' has 20 values but the machine network was built for 9"),
    ("observation_size disagrees with the first layer", lambda: MCDropoutPolicy(net(9), observation_size=8),
     ValueError, r"observation_size=8 but the network's first layer reads 9"),
    # the machine's frames (every frame)
    ("20-value observation cut to 8", lambda: MCDropoutPolicy(
        lunar_actor([16], 0.1, obs_dims=8), observation_size=9)(TensorDict({"observation": torch.zeros(2, 20)}, [2])),
     ValueError, r"'observation' has 20 values per frame but the machine network was built for 9"),
    ("20-value observation, Linear first layer", lambda: MCDropoutPolicy(net(9))(
        TensorDict({"observation": torch.zeros(2, 20)}, [2])),
     ValueError, r"'observation' has 20 values per frame but the machine network was built for 9"),
    ("NaN weight", lambda: nan_weights()(TensorDict({"observation": torch.zeros(2, 9)}, [2])),
     ValueError, r"the machine network's output \(probs, observation finite: look at its weights\) has 80 non-finite"),
    ("NaN observation into the machine", lambda: MCDropoutPolicy(net())(
        TensorDict({"observation": torch.full((2, 9), math.nan)}, [2])),
     ValueError, r"observation has 18 non-finite value"),
    ("missing observation", lambda: MCDropoutPolicy(net())(TensorDict({}, [2])),
     KeyError, r"the machine reads 'observation', which is missing"),
    # the operator's answer and the env's frame, at the transform (every frame)
    ("human action not one-hot", lambda: lunar_with(ScriptedOperator([0.99, 0.99, 0.0, 0.0])).reset(),
     ValueError, r"human_action \(ScriptedOperator\) must be one-hot for a OneHot action spec.*0\.99"),
    ("human action all zeros", lambda: lunar_with(ScriptedOperator([0.0, 0.0, 0.0, 0.0])).reset(),
     ValueError, r"human_action \(ScriptedOperator\) must be one-hot"),
    ("operator's NaN float action", lambda: lunar_with(ScriptedOperator([math.nan, 1.0, 0.0, 0.0])).reset(),
     ValueError, r"the operator's human_action \(ScriptedOperator\) has 1 non-finite value"),
    ("NaN velocity, no machine in the loop", lambda: lunar_with(
        ScriptedOperator([1.0, 0.0, 0.0, 0.0]), nan_velocity=True).reset(),
     ValueError, r"the env's 'observation' \(before the operator saw it\) has 1 non-finite value\(s\) of 9: nan at index \(2,\)"),
    # the math's parameters
    ("delta2=inf", lambda: machine_confidence(torch.tensor([0.5]), 0.6, math.inf),
     ValueError, r"delta2 must be in \(1.0, inf\), got inf"),
    ("delta2=inf (machine)", lambda: MCDropoutPolicy(net(), delta2=math.inf),
     ValueError, r"delta2 must be in \(1.0, inf\), got inf"),
    ("delta1=inf", lambda: human_confidence(torch.tensor([0.5]), 0.1, 0.6, math.inf),
     ValueError, r"delta1 must be in \(0.0, inf\), got inf"),
    ("K=inf (transform)", lambda: HumanConfidenceTransform(K=math.inf),
     ValueError, r"K must be in \(0.0, inf\), got inf"),
    ("eta=0", lambda: human_confidence(torch.tensor([0.5]), 0.1, 0.0, 2.0),
     ValueError, r"eta must be in \(0.0, 1.0\), got 0.0"),
    # issue #37: an adversary's inputs
    ("inf human_rt", lambda: lunar_with(ScriptedOperator([1.0, 0.0, 0.0, 0.0], rt=math.inf)).reset(),
     ValueError, r"the operator's human_rt \(ScriptedOperator\) has 1 non-finite value\(s\) of 1: inf"),
    ("negative human_rt", lambda: lunar_with(ScriptedOperator([1.0, 0.0, 0.0, 0.0], rt=-0.1)).reset(),
     ValueError, r"the operator's human_rt \(ScriptedOperator\) must be in \[0.0, inf\], got -0.1"),
    ("human_decided a float", lambda: lunar_with(ScriptedOperator([1.0, 0.0, 0.0, 0.0],
                                                                  decided=torch.tensor(0.3))).reset(),
     ValueError, r"the operator's human_decided \(ScriptedOperator\) must be a bool tensor, got torch.float32"),
    ("beta 1.5 from a custom arbiter", lambda: Overconfident()(frame()),
     ValueError, r"beta \(Overconfident\) must be in \[0.0, 1.0\], got 1.5"),
    ("2 betas from a custom arbiter of dims=3", lambda: TwoBetas(dims=3)(frame()),
     ValueError, r"TwoBetas gives beta of shape \(2, 2\): its last dim must be 1 or dims=3"),
    ("b_m and b_h of different shapes", lambda: ConfidenceArbiter()(frame(human_confidence=torch.full((2,), 0.5))),
     ValueError, r"'machine_confidence' has shape \(2, 1\) but 'human_confidence' has \(2,\)"),
    ("HULA uncertainty < 0", lambda: HULAArbiter(0.1)(frame(machine_uncertainty=torch.full((2, 1), -0.5))),
     ValueError, r"machine_uncertainty must be in \[0.0, inf\], got -0.5"),
    ("HULA threshold NaN", lambda: HULAArbiter(math.nan), ValueError, r"threshold must be in \[0.0, inf\), got nan"),
    ("constant beta 1.5", lambda: ConstantArbiter(1.5), ValueError, r"value must be in \[0.0, 1.0\], got 1.5"),
    ("frozen HULA", lambda: FrozenConfidenceArbiter(HULAArbiter(0.1), 0.5, 0.5),
     ValueError, r"FrozenConfidenceArbiter needs a learned arbiter \(one with a theta parameter\), got HULAArbiter"),
    ("theta of dims=1 into a dims=3 arbiter", lambda: ConfidenceArbiter(dims=3).load_state_dict(
        ConfidenceArbiter(dims=1).state_dict()),
     CheckpointError, r"a ConfidenceArbiter's state of dims=1 cannot be loaded into one of dims=3"),
    ("a dims=2 arbiter for a 3-value action", lambda: SharedPolicyModule(
        MCDropoutPolicy(net(9, 3), output="action"), ConfidenceArbiter(dims=2), Bounded(0.0, 1.0, shape=(3,))),
     ValueError, r"arbiter.dims=2 must be 1 or the action size 3"),
    ("saving a RuleArbiter", lambda: save_arbiter(RuleArbiter(lambda obs: obs[..., 0] > 0), "unused.pt", task="uav"),
     ValueError, r"a RuleArbiter's rule is code, not state: it cannot be saved"),
    ("a file without an arbiter", arbiter_file_without_arbiter, CheckpointError,
     r"other.pt holds no arbiter \(save_arbiter writes one\)"),
    ("stored machine probs summing to 1.5 into the theta loss", lambda: theta_loss(
        machine_probs=torch.tensor([[0.5, 0.5, 0.5, 0.0]]).expand(4, 4)),
     ValueError, r"machine_probs's sum per frame \(one-hot or probabilities\) must be in \[0.99965, 1.00035\], got 1.5"),
    ("a soft human action with a negative entry", lambda: blend([0.25] * 4, [1.2, -0.2, 0.0, 0.0], discrete=True),
     ValueError, r"human_action must be in \[0.0, 1.0\], got 1.2"),
    ("NaN continuous human action", lambda: blend([0.5, 0.5], [math.nan, 0.5], low=torch.zeros(2), high=torch.ones(2)),
     ValueError, r"human_action has 1 non-finite value\(s\) of 2: nan"),
    ("human action batch differs from the machine's", lambda: PolicyBlend(discrete=True)(
        torch.full((2, 1), 0.5), torch.full((2, 4), 0.25), torch.eye(4)[:1]),
     ValueError, r"the operator's human_action has shape \(1, 4\) but machine_probs has \(2, 4\)"),
    ("float64 observation", lambda: MCDropoutPolicy(net())(TensorDict({"observation": torch.zeros(2, 9).double()}, [2])),
     ValueError, r"'observation' is torch.float64 but the machine network's parameters are torch.float32"),
    ("int observation", lambda: MCDropoutPolicy(net())(TensorDict({"observation": torch.zeros(2, 9).long()}, [2])),
     ValueError, r"'observation' is torch.int64 but the machine network's parameters are torch.float32"),
    ("network without dropout", lambda: MCDropoutPolicy(nn.Sequential(nn.Linear(9, 4))),
     ValueError, r"network has no dropout layer: its MC-dropout uncertainty would always be 0"),
    ("dropout p=0", lambda: MCDropoutPolicy(nn.Sequential(nn.Linear(9, 4), nn.Dropout(0.0))),
     ValueError, r"network's dropout layers all have p=0 \(1 of them\)"),
    ("num_samples=1", lambda: MCDropoutPolicy(net(), num_samples=1),
     ValueError, r"num_samples must be an integer >= 2 .*, got 1"),
    ("FirstDims keeping more than it reads", lambda: FirstDims(10, in_dims=9),
     ValueError, r"n must be an integer in \[1, in_dims=9\], got 10"),
    ("action index into the critic loss", lambda: q_loss(q_batch(action=torch.zeros(4, 1, dtype=torch.long))),
     ValueError, r"the batch's 'action' has shape \(4, 1\) but the critic gives \(4, 4\) action values"),
    ("two keys pressed in the critic loss's action", lambda: q_loss(q_batch(action=torch.ones(4, 4, dtype=torch.long))),
     ValueError, r"action's sum per frame \(one-hot or probabilities\) must be in \[1.0, 1.0\], got 4"),
    ("NaN reward into the critic loss", lambda: q_loss(q_batch(next={
        "observation": torch.zeros(4, 9), "reward": torch.full((4, 1), math.nan),
        "done": torch.zeros(4, 1, dtype=torch.bool), "terminated": torch.zeros(4, 1, dtype=torch.bool)})),
     ValueError, r"\('next', 'reward'\) has 4 non-finite value\(s\) of 4: nan"),
    ("keyboard fps=inf", lambda: KeyboardPilot(fps=math.inf, screen=object(), events=list, joystick=False),
     ValueError, r"fps must be in \(0.0, inf\), got inf"),
]


@pytest.mark.parametrize(("make", "error", "message"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_refused_with_a_message_naming_it(make, error, message):
    with pytest.raises(error, match=message) as raised:
        make()
    text = str(raised.value.args[0]) if raised.value.args else ""
    assert "\n" not in text  # one line


def test_per_frame_checks_run_on_every_frame():
    arbiter = ConfidenceArbiter()
    arbiter(frame())
    with pytest.raises(ValueError, match="machine_confidence must be in"):
        arbiter(frame(machine_confidence=torch.full((2, 1), 1.5)))
    machine = MCDropoutPolicy(net())
    obs = TensorDict({"observation": torch.zeros(2, 9)}, [2])
    machine(obs.clone())
    with pytest.raises(ValueError, match="observation has 18 non-finite"):
        machine(TensorDict({"observation": torch.full((2, 9), math.nan)}, [2]))
    with torch.no_grad():
        machine.network[3].weight[0, 0] = math.nan  # weights gone NaN after the first frames
    with pytest.raises(ValueError, match=r"the machine network's output \(probs, observation finite: look at its weights"):
        machine(obs.clone())
    rule = RuleArbiter(lambda observation: observation[..., 0])
    rule(frame(observation=torch.full((2, 1), 0.5)))
    with pytest.raises(ValueError, match=r"rule share must be in \[0.0, 1.0\], got nan"):
        rule(frame(observation=torch.full((2, 1), math.nan)))


def test_an_empty_batch_passes_through_the_policy():
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    td = TensorDict({"observation": torch.zeros(0, 9), "human_action": torch.zeros(0, 4, dtype=torch.long),
                     "human_confidence": torch.zeros(0, 1)}, [0])
    assert policy(td)["action"].shape == (0, 4)


def test_a_continuous_human_action_outside_the_box_is_clipped_with_the_blend():
    """Eq. 14 on a bounded action: the blend is clipped to the box (what the env could take), the operator's
    action with it; a NaN is refused (above), never clipped."""
    spec = Bounded(0.0, 3.0, shape=(3,))
    policy = SharedPolicyModule(MCDropoutPolicy(net(9, 3), output="action"), ConstantArbiter(0.0, dims=3), spec)
    td = TensorDict({"observation": torch.zeros(9), "human_action": torch.tensor([5.0, -1.0, 1.5]),
                     "human_confidence": torch.tensor([0.3])}, [])
    assert policy(td)["action"].tolist() == [3.0, 0.0, 1.5]


def test_a_machine_starting_with_a_lazy_linear_reads_any_width_until_it_is_built():
    machine = MCDropoutPolicy(nn.Sequential(nn.LazyLinear(16), nn.Tanh(), nn.Dropout(0.1), nn.Linear(16, 4)))
    assert machine.observation_size is None
    assert machine(TensorDict({"observation": torch.zeros(2, 9)}, [2]))["machine_probs"].shape == (2, 4)


def test_the_machine_probabilities_of_many_samples_pass_the_distribution_check():
    machine = MCDropoutPolicy(net(9, 18), num_samples=256)
    probs = machine(TensorDict({"observation": 10 * torch.randn(512, 9)}, [512]))["machine_probs"]
    assert check_distribution("machine_probs", probs) is probs  # the rounding of a mean of softmaxes passes


def test_good_inputs_pass_every_check():
    env = lunar_with(ScriptedOperator([0.0, 0.0, 1.0, 0.0]))
    td = env.reset()
    assert td["human_action"].tolist() == [0, 0, 1, 0]
    policy = SharedPolicyModule(
        MCDropoutPolicy(lunar_actor([16], 0.1, obs_dims=8), observation_size=9), ConfidenceArbiter(),
        env.full_action_spec["action"], observation_spec=env.observation_spec,
    )
    td.set("human_confidence", torch.full((1,), 0.3))
    assert policy(td)["action"].shape == (4,)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_every_frame_is_checked_on_the_device_without_a_sync_and_a_nan_is_reported_later():
    device = torch.device("cuda")
    policy = SharedPolicyModule(MCDropoutPolicy(net().to(device)), ConfidenceArbiter().to(device), OneHot(4))
    td = TensorDict({"observation": torch.randn(8, 9, device=device),
                     "human_action": torch.eye(4, device=device)[torch.arange(8, device=device) % 4],
                     "human_confidence": torch.full((8, 1), 0.3, device=device)}, [8], device=device)

    def checked_parts(frame: TensorDict) -> TensorDict:  # the sampling (torch.distributions') is not ours
        for part in ("machine", "arbiter", "blend"):
            frame = policy[part](frame)
        return frame

    checked_parts(td.clone())  # warm-up (the allocators)
    flush_frame_checks()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(20):
            checked_parts(td.clone())
        bad = td.clone()
        bad["observation"][3, 2] = math.nan
        checked_parts(bad)  # no sync: the verdict is on its way
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with pytest.raises(ValueError, match=r"^observation must be finite: a frame on cuda:0 was not"):
        flush_frame_checks()
    flush_frame_checks()  # read once, then forgotten
    checked_parts(td.clone())  # the CUDA context is still usable (no device assert)
    flush_frame_checks()
