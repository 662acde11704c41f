"""Reddy et al.'s copilot (*Shared autonomy via deep reinforcement learning*, RSS 2018) as a
machine of the common pipeline (docs/architecture.md, "The field's assistants").

The copilot is a Q network on the goal-masked observation and the pilot's one-hot key,
``Q(s~, a_pilot, .)`` (deepassist masks the pad's x, ``obs[8]``, and appends the pilot's
action). At run time it keeps the pilot's key where that key is within a tolerance ``alpha``
of the best (values shifted to be non-negative), and presses its own best key otherwise:

    keep the pilot's a_p  iff  Q'(s, a_p) >= (1 - alpha) max_a Q'(s, a),   Q' = Q - min_a Q

(``alpha = 0``: the copilot unless the pilot's key is already its best; ``alpha = 1``: the
pilot always). In Eq. 14's terms that is a machine whose policy is one-hot on the copilot's
best key (:class:`CopilotPolicy`) and an arbiter that hands it the frame, ``beta = 1``, exactly
where the pilot's key falls outside the tolerance (:class:`ToleranceArbiter`): the shared
policy, the protocol, the map and ``dcsc play`` run it unchanged.

Examples:
    >>> q = torch.tensor([[1.0, 3.0, 2.0, 0.0]])
    >>> pilot = torch.tensor([[0.0, 0.0, 1.0, 0.0]])   # the pilot presses key 2: Q' = 2 of a best 3
    >>> keeps_pilot(q, pilot, alpha=0.5), keeps_pilot(q, pilot, alpha=0.2)
    (tensor([[True]]), tensor([[False]]))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorSpec

from dcsc_torchrl.arbiters import Arbiter
from dcsc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from dcsc_torchrl.checks import check_in_range, check_values
from dcsc_torchrl.networks import LUNAR_OBS_DIMS, FirstDims, mlp
from dcsc_torchrl.policy import SharedPolicyModule

COPILOT_TASK = "lunarlander-copilot"
"""The task a copilot checkpoint names: a machine checkpoint of LunarLander is refused, and the other way."""


class CopilotQNetwork(nn.Module):
    """Reddy et al.'s copilot Q network: ``Q(s~, a_pilot, .)``, one value per key.

    ``s~`` is the first ``obs_dims`` of the ``in_dims`` observation values (TargetLunarLander:
    the 8 standard values, the pad's x masked); the pilot's one-hot key is appended.

    Args:
        hidden: the MLP's hidden widths (ReLU, as DQN's).
        obs_dims: observation values the copilot sees.
        in_dims: the observation's width (checked).
        n_actions: the number of keys.
    """

    def __init__(self, hidden: Sequence[int] = (64, 64), *, obs_dims: int = 8, in_dims: int = LUNAR_OBS_DIMS,
                 n_actions: int = 4) -> None:
        super().__init__()
        self.masked = FirstDims(obs_dims, in_dims=in_dims)
        self.q = mlp(obs_dims + n_actions, n_actions, hidden, activation=nn.ReLU)
        self.observation_size, self.n_actions = in_dims, n_actions

    def forward(self, observation: torch.Tensor, pilot_action: torch.Tensor) -> torch.Tensor:
        if pilot_action.shape[-1] != self.n_actions:
            raise ValueError(f"the pilot's action must be one-hot over {self.n_actions} keys, "
                             f"got shape {tuple(pilot_action.shape)}")
        return self.q(torch.cat([self.masked(observation), pilot_action.to(observation.dtype)], -1))


def keeps_pilot(q_values: torch.Tensor, pilot_action: torch.Tensor, alpha: float) -> torch.Tensor:
    """Reddy et al.'s tolerance rule: whether the pilot's key is within ``alpha`` of the best,
    ``Q'(s, a_p) >= (1 - alpha) max_a Q'(s, a)`` with ``Q' = Q - min_a Q``; ``[*batch, 1]`` bools."""
    shifted = q_values - q_values.min(-1, keepdim=True).values
    pilot = shifted.gather(-1, pilot_action.argmax(-1, keepdim=True))
    return pilot >= (1.0 - alpha) * shifted.max(-1, keepdim=True).values


class CopilotPolicy(TensorDictModuleBase):
    """The copilot as the shared policy's machine: one-hot on its best key given the pilot's.

    Writes the keys an :class:`~dcsc_torchrl.machine.MCDropoutPolicy` writes, so
    :class:`~dcsc_torchrl.policy.SharedPolicyModule` takes it as its machine: ``machine_probs``
    (one-hot on ``argmax_a Q(s~, a_pilot, a)``), ``machine_uncertainty`` (0: the copilot has no
    uncertainty estimate) and ``machine_confidence`` (1; Reddy's rule reads no confidence).

    Args:
        q_network: a :class:`CopilotQNetwork` (used under ``torch.no_grad()``).
    """

    output = "probs"

    def __init__(self, q_network: CopilotQNetwork, *, observation_key: NestedKey = "observation",
                 human_key: NestedKey = "human_action") -> None:
        super().__init__()
        self.q_network = q_network
        self.in_keys = [observation_key, human_key]
        self.out_keys = ["machine_probs", "machine_uncertainty", "machine_confidence"]
        self.output_size, self.observation_size = q_network.n_actions, q_network.observation_size

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation, pilot = (tensordict.get(key) for key in self.in_keys)
        with torch.no_grad():
            q_values = self.q_network(observation, pilot)
        check_values("the copilot's Q", q_values)
        best = nn.functional.one_hot(q_values.argmax(-1), self.output_size).to(observation.dtype)
        ones = torch.ones_like(q_values[..., :1])
        probs_key, uncertainty_key, confidence_key = self.out_keys
        tensordict.set(probs_key, best)
        tensordict.set(uncertainty_key, torch.zeros_like(ones))
        tensordict.set(confidence_key, ones)
        return tensordict


class ToleranceArbiter(Arbiter):
    """Reddy et al.'s arbiter: ``beta = 1`` (the copilot's key) exactly where the pilot's key
    falls outside the tolerance ``alpha`` of the copilot's Q (:func:`keeps_pilot`), else 0.

    Args:
        q_network: the copilot's :class:`CopilotQNetwork` (used under ``torch.no_grad()``).
        alpha: the tolerance in [0, 1].
        dims: beta's size (1: a key is handed over whole).

    Examples:
        >>> from tensordict import TensorDict
        >>> class Fixed(torch.nn.Module):
        ...     def forward(self, obs, pilot):
        ...         return torch.tensor([[1.0, 3.0, 2.0, 0.0]]).expand(obs.shape[0], 4)
        >>> td = TensorDict({"machine_confidence": torch.ones(2, 1), "human_confidence": torch.ones(2, 1),
        ...                  "observation": torch.zeros(2, 9),
        ...                  "human_action": torch.tensor([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])}, [2])
        >>> ToleranceArbiter(Fixed(), alpha=0.5)(td)["beta"]
        tensor([[0.],
                [1.]])
    """

    def __init__(self, q_network: nn.Module, alpha: float, dims: int = 1, *,
                 observation_key: NestedKey = "observation", human_key: NestedKey = "human_action",
                 **kwargs) -> None:
        super().__init__(dims, **kwargs)
        self.q_network = q_network
        self.set_arguments(alpha)
        self.observation_key, self.human_key = observation_key, human_key
        self.in_keys = [*self.in_keys[:2], observation_key, human_key]

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        observation, pilot = tensordict.get(self.observation_key), tensordict.get(self.human_key)
        with torch.no_grad():
            q_values = self.q_network(observation, pilot)
        check_values("the copilot's Q", q_values)
        return (~keeps_pilot(q_values, pilot, self.alpha)).to(ratio.dtype)

    def arguments(self) -> dict[str, float]:
        return {"alpha": self.alpha}

    def set_arguments(self, alpha: float) -> None:
        check_in_range("alpha", alpha, 0.0, 1.0)
        self.alpha = float(alpha)


@dataclass(frozen=True)
class TrainedCopilot:
    """A trained copilot: its Q network, the tolerance chosen on development scenarios, and
    the operators it was trained with (it refuses to be evaluated next to one of them)."""

    network: CopilotQNetwork
    alpha: float
    operators: tuple[str, ...]

    def check_evaluated_next_to(self, operator: str) -> None:
        """Refuses an ``operator`` the copilot was trained with, in one line naming both."""
        if operator in self.operators:
            raise ValueError(f"the copilot was trained with operator {operator!r} (its pool: "
                             f"{', '.join(self.operators)}): evaluate it next to an operator outside its pool")

    def policy(self, action_spec: TensorSpec) -> SharedPolicyModule:
        """The shared policy of Eq. 14 with the copilot as machine and its tolerance rule as arbiter."""
        return SharedPolicyModule(CopilotPolicy(self.network), ToleranceArbiter(self.network, self.alpha),
                                  action_spec)


def save_copilot(path: str | Path, copilot: TrainedCopilot, config: Mapping[str, Any], **record: Any) -> Path:
    """Writes ``copilot`` (weights, alpha, its operators), the recipe's ``config`` (its
    ``network.hidden`` rebuilds the network) and ``record`` atomically."""
    payload = {"state": {"copilot": copilot.network.state_dict()}, "config": dict(config),
               "alpha": copilot.alpha, "operators": list(copilot.operators), **record}
    return save_checkpoint(path, task=COPILOT_TASK, payload=payload)


def load_copilot(path: str | Path) -> TrainedCopilot:
    """The copilot saved at ``path`` (:func:`save_copilot`), frozen in eval mode.

    Raises:
        ValueError: no copilot there, or a checkpoint of something else (one line).
    """
    data = load_checkpoint(path, task=COPILOT_TASK, modules=("copilot",))
    network = CopilotQNetwork(data["config"]["network"]["hidden"])
    network.load_state_dict(data["state"]["copilot"])
    return TrainedCopilot(network.requires_grad_(False).eval(), float(data["alpha"]), tuple(data["operators"]))
