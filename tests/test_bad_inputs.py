"""Every bad input of the modules (issue #14): where it is refused, the exception, and that
the one-line message names the culprit (the key, the parameter or the network).

Each row: an id, a callable that feeds the bad input, the exception type, and a regex the
message must match. The operator's answers and the env's frames are checked at the
transform that receives them; specs and sizes at construction; the confidences and the
machine's observation on the first call of the per-frame modules.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import Bounded, OneHot, Unbounded
from torchrl.envs import GymWrapper, TransformedEnv

from dcsc_torchrl.arbiters import ConfidenceArbiter, HULAArbiter
from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.confidence import CHECK_FINITE_ENV, human_confidence, machine_confidence
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import lunar_actor
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform


def net(n_in: int = 9, n_out: int = 4) -> nn.Module:
    return nn.Sequential(nn.Linear(n_in, 16), nn.Tanh(), nn.Dropout(0.1), nn.Linear(16, n_out))


def frame(**entries: torch.Tensor) -> TensorDict:
    base = {"machine_confidence": torch.full((2, 1), 0.5), "human_confidence": torch.full((2, 1), 0.5)}
    base.update(entries)
    return TensorDict({k: v for k, v in base.items() if v is not None}, [2])


class ScriptedOperator:
    """Answers every frame with a fixed action (and RT 0.3 s)."""

    def __init__(self, action: list[float], dtype: torch.dtype = torch.float32) -> None:
        self.action = torch.tensor(action, dtype=dtype)

    def reset(self, seed: int | None) -> None:
        pass

    def __call__(self, td: TensorDict) -> TensorDict:
        batch = td.batch_size
        return TensorDict(
            {
                "human_action": self.action.expand(*batch, -1).clone(),
                "human_rt": torch.full((*batch, 1), 0.3),
                "human_decided": torch.ones(*batch, 1, dtype=torch.bool),
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


def policy_without_transform():
    policy = SharedPolicyModule(MCDropoutPolicy(net()), ConfidenceArbiter(), OneHot(4))
    td = TensorDict({"observation": torch.zeros(2, 9), "human_action": torch.eye(4)[:2]}, [2])
    return policy(td)


CASES: list[tuple[str, Callable[[], object], type[Exception], str]] = [
    # the confidences the arbiter reads (first call)
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
    # the machine's first call
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
]


@pytest.mark.parametrize(("make", "error", "message"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_refused_with_a_message_naming_it(make, error, message):
    with pytest.raises(error, match=message) as raised:
        make()
    text = str(raised.value.args[0]) if raised.value.args else ""
    assert "\n" not in text  # one line


def test_per_frame_checks_run_once_unless_asked_for(monkeypatch):
    arbiter = ConfidenceArbiter()
    arbiter(frame())  # the first call checks
    bad = frame(machine_confidence=torch.full((2, 1), 1.5))
    monkeypatch.delenv(CHECK_FINITE_ENV, raising=False)
    arbiter(bad.clone())  # later frames: no host read, no check
    monkeypatch.setenv(CHECK_FINITE_ENV, "1")
    with pytest.raises(ValueError, match="machine_confidence must be in"):
        arbiter(bad.clone())
    machine = MCDropoutPolicy(net())
    machine(TensorDict({"observation": torch.zeros(2, 9)}, [2]))
    with pytest.raises(ValueError, match="observation has 18 non-finite"):
        machine(TensorDict({"observation": torch.full((2, 9), math.nan)}, [2]))


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
def test_machine_and_arbiter_frames_after_the_first_do_not_sync_the_device(monkeypatch):
    monkeypatch.delenv(CHECK_FINITE_ENV, raising=False)
    device = torch.device("cuda")
    machine = MCDropoutPolicy(net().to(device))
    arbiter = ConfidenceArbiter().to(device)
    td = TensorDict({"observation": torch.randn(8, 9, device=device),
                     "human_confidence": torch.full((8, 1), 0.3, device=device)}, [8], device=device)
    arbiter(machine(td.clone()))  # the first call checks (and syncs)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        arbiter(machine(td.clone()))
    finally:
        torch.cuda.set_sync_debug_mode("default")
