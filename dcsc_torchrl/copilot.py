"""Reddy et al.'s copilot (*Shared autonomy via deep reinforcement learning*, RSS 2018) as a
machine of the common pipeline (docs/architecture.md, "The field's assistants").

The copilot is a Q network on the observation it is allowed to see and the pilot's action,
``Q(s~, a_pilot, .)``, one value per action of a finite set ``A`` (its ``actions``, ``[|A|, D]``):
on LunarLander the 4 one-hot keys, the pad's x masked as deepassist masks ``obs[8]``; on the UAV
the simulated operator's 27 ``(rho0, sigma0, tau)`` grid points, the whole observation (the
task's registry entry, :attr:`~dcsc_torchrl.task.Task.make_copilot_network`, says which). At run
time it keeps the pilot's action where the action of ``A`` nearest to it is within a
tolerance ``alpha`` of the best (values shifted to be non-negative)::

    keep the pilot's a_p  iff  Q'(s, n(a_p)) >= (1 - alpha) max_a Q'(s, a),   Q' = Q - min_a Q

with ``n(a_p)`` the action of ``A`` nearest ``a_p`` (the pilot's key itself on LunarLander), and
otherwise takes, among the actions within the tolerance, the one nearest the pilot's (ties: the
larger Q), Reddy et al.'s rule for a general action set. With 4 keys every other key is as far
from the pilot's, so that is the copilot's best key. In Eq. 14's terms: a machine proposing
that action (:class:`CopilotPolicy`) and an arbiter handing it the frame, ``beta = 1``, exactly
where the pilot's action falls outside the tolerance (:class:`ToleranceArbiter`): the shared
policy, the protocol, the map and ``dcsc play`` run it unchanged.

Examples:
    >>> q = torch.tensor([[1.0, 3.0, 2.0, 0.0]])
    >>> pilot = torch.tensor([[2]])   # the pilot presses key 2: Q' = 2 of a best 3
    >>> keeps_pilot(q, pilot, alpha=0.5), keeps_pilot(q, pilot, alpha=0.2)
    (tensor([[True]]), tensor([[False]]))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import OneHot, TensorSpec

from dcsc_torchrl.arbiters import Arbiter
from dcsc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from dcsc_torchrl.checks import check_in_range, check_values
from dcsc_torchrl.networks import FirstDims, mlp
from dcsc_torchrl.policy import SharedPolicyModule

if TYPE_CHECKING:
    from dcsc_torchrl.task import Task


def copilot_task(task: Task) -> str:
    """The task a copilot checkpoint of ``task`` names (``lunarlander-copilot``): a machine
    checkpoint is refused as a copilot, a copilot of another task too, and the other way."""
    return f"{task.name}-copilot"


class CopilotQNetwork(nn.Module):
    """Reddy et al.'s copilot Q network: ``Q(s~, a_pilot, .)``, one value per action of ``actions``.

    ``s~`` is the first ``obs_dims`` of the ``in_dims`` observation values; the pilot's action
    (``D`` values: a one-hot key, or a continuous action) is appended.

    Args:
        hidden: the MLP's hidden widths (ReLU, as DQN's).
        actions: the copilot's action set ``[|A|, D]`` (a buffer outside the ``state_dict``: the
            task's :attr:`~dcsc_torchrl.task.Task.make_copilot_network` rebuilds it).
        in_dims: the observation's width (checked).
        obs_dims: observation values the copilot sees (default: all).

    Examples:
        >>> net = CopilotQNetwork([16], torch.eye(4), in_dims=9, obs_dims=8)
        >>> net(torch.zeros(2, 9), torch.eye(4)[:2]).shape
        torch.Size([2, 4])
    """

    def __init__(self, hidden: Sequence[int], actions: torch.Tensor, *, in_dims: int,
                 obs_dims: int | None = None) -> None:
        super().__init__()
        actions = torch.as_tensor(actions, dtype=torch.float32)
        if actions.ndim != 2 or len(actions) < 2:
            raise ValueError(f"the copilot's actions must have shape [|A| >= 2, D], got {tuple(actions.shape)}")
        obs_dims = in_dims if obs_dims is None else obs_dims
        self.register_buffer("actions", actions, persistent=False)
        self.masked = FirstDims(obs_dims, in_dims=in_dims)
        self.q = mlp(obs_dims + actions.shape[-1], len(actions), hidden, activation=nn.ReLU)
        self.observation_size, self.action_size = in_dims, actions.shape[-1]

    def forward(self, observation: torch.Tensor, pilot_action: torch.Tensor) -> torch.Tensor:
        if pilot_action.shape[-1] != self.action_size:
            raise ValueError(f"the pilot's action must have {self.action_size} values (the width of the copilot's "
                             f"actions), got shape {tuple(pilot_action.shape)}")
        return self.q(torch.cat([self.masked(observation), pilot_action.to(observation.dtype)], -1))


def action_distances(actions: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The squared Euclidean distance from ``action [*batch, D]`` to each of ``actions [|A|, D]``, ``[*batch, |A|]``."""
    return (action.to(actions.dtype).unsqueeze(-2) - actions).square().sum(-1)


def nearest_action(actions: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The index of the action of ``actions [|A|, D]`` nearest ``action [*batch, D]`` (Euclidean;
    the first of tied ones), ``[*batch, 1]``: a one-hot key's own index."""
    return action_distances(actions, action).argmin(-1, keepdim=True)


def within_tolerance(q_values: torch.Tensor, alpha: float) -> torch.Tensor:
    """Reddy et al.'s feasible set: ``Q'(s, a) >= (1 - alpha) max_a Q'(s, a)`` with
    ``Q' = Q - min_a Q``, one bool per action."""
    shifted = q_values - q_values.min(-1, keepdim=True).values
    return shifted >= (1.0 - alpha) * shifted.max(-1, keepdim=True).values


def keeps_pilot(q_values: torch.Tensor, pilot_choice: torch.Tensor, alpha: float) -> torch.Tensor:
    """Reddy et al.'s tolerance rule: whether the pilot's action (its index ``pilot_choice``
    ``[*batch, 1]`` in the copilot's set) is within ``alpha`` of the best
    (:func:`within_tolerance`); ``[*batch, 1]`` bools."""
    return within_tolerance(q_values, alpha).gather(-1, pilot_choice)


def tolerant_choice(q_values: torch.Tensor, actions: torch.Tensor, pilot_action: torch.Tensor,
                    alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The copilot's action index and whether the pilot keeps its own (``[*batch, 1]`` each).

    Where the pilot keeps its action (:func:`keeps_pilot` on its nearest action), the copilot's
    own best; elsewhere the action within the tolerance nearest the pilot's, ties broken by
    the larger Q (4 keys: every other key is as near, so the copilot's best key).
    """
    feasible = within_tolerance(q_values, alpha)
    distances = action_distances(actions, pilot_action)
    kept = feasible.gather(-1, distances.argmin(-1, keepdim=True))
    distances = distances.masked_fill(~feasible, torch.inf)
    nearest = distances == distances.min(-1, keepdim=True).values
    yielding = q_values.masked_fill(~nearest, -torch.inf).argmax(-1, keepdim=True)
    return torch.where(kept, q_values.argmax(-1, keepdim=True), yielding), kept


class CopilotPolicy(TensorDictModuleBase):
    """The copilot as the shared policy's machine: the action :func:`tolerant_choice` gives.

    Writes the keys an :class:`~dcsc_torchrl.machine.MCDropoutPolicy` writes, so
    :class:`~dcsc_torchrl.policy.SharedPolicyModule` takes it as its machine: the mean
    (``machine_probs``: one-hot on the key; ``machine_action``: the continuous action),
    ``machine_uncertainty`` (0: the copilot has no uncertainty estimate) and
    ``machine_confidence`` (1; Reddy's rule reads no confidence).

    Args:
        q_network: a :class:`CopilotQNetwork` (used under ``torch.no_grad()``).
        alpha: the tolerance in [0, 1].
        output: ``"probs"`` (keys) or ``"action"`` (a continuous action).
    """

    def __init__(self, q_network: CopilotQNetwork, alpha: float, *, output: str = "probs",
                 observation_key: NestedKey = "observation", human_key: NestedKey = "human_action") -> None:
        super().__init__()
        if output not in ("probs", "action"):
            raise ValueError(f"output must be 'probs' or 'action', got {output!r}")
        check_in_range("alpha", alpha, 0.0, 1.0)
        self.q_network, self.alpha, self.output = q_network, float(alpha), output
        self.in_keys = [observation_key, human_key]
        self.out_keys = [f"machine_{output}", "machine_uncertainty", "machine_confidence"]
        self.output_size, self.observation_size = q_network.action_size, q_network.observation_size

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation, pilot = (tensordict.get(key) for key in self.in_keys)
        with torch.no_grad():
            q_values = self.q_network(observation, pilot)
        check_values("the copilot's Q", q_values)
        choice, _ = tolerant_choice(q_values, self.q_network.actions, pilot, self.alpha)
        action = self.q_network.actions[choice.squeeze(-1)].to(observation.dtype)
        ones = torch.ones_like(q_values[..., :1])
        mean_key, uncertainty_key, confidence_key = self.out_keys
        tensordict.set(mean_key, action)
        tensordict.set(uncertainty_key, torch.zeros_like(ones))
        tensordict.set(confidence_key, ones)
        return tensordict


class ToleranceArbiter(Arbiter):
    """Reddy et al.'s arbiter: ``beta = 1`` (the copilot's action) exactly where the pilot's
    action falls outside the tolerance ``alpha`` of the copilot's Q (:func:`keeps_pilot` on its
    nearest action of the copilot's set), else 0; the same in every action dimension.

    Args:
        q_network: the copilot's :class:`CopilotQNetwork` (used under ``torch.no_grad()``).
        alpha: the tolerance in [0, 1].
        dims: beta's size (1: a key is handed over whole; the UAV: 3).

    Examples:
        >>> from tensordict import TensorDict
        >>> net = CopilotQNetwork([8], torch.eye(4), in_dims=9)
        >>> td = TensorDict({"machine_confidence": torch.ones(2, 1), "human_confidence": torch.ones(2, 1),
        ...                  "observation": torch.zeros(2, 9), "human_action": torch.eye(4)[:2]}, [2])
        >>> ToleranceArbiter(net, alpha=1.0)(td)["beta"]   # alpha = 1: the pilot always
        tensor([[0.],
                [0.]])
    """

    def __init__(self, q_network: CopilotQNetwork, alpha: float, dims: int = 1, *,
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
        kept = keeps_pilot(q_values, nearest_action(self.q_network.actions, pilot), self.alpha)
        return (~kept).to(ratio.dtype)

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
        """The shared policy of Eq. 14 with the copilot as machine and its tolerance rule as
        arbiter, for keys (a ``OneHot`` spec) or a continuous action (``Bounded``)."""
        discrete = isinstance(action_spec, OneHot)
        machine = CopilotPolicy(self.network, self.alpha, output="probs" if discrete else "action")
        arbiter = ToleranceArbiter(self.network, self.alpha, 1 if discrete else action_spec.shape[-1])
        return SharedPolicyModule(machine, arbiter, action_spec)


def save_copilot(path: str | Path, task: Task, copilot: TrainedCopilot, config: Mapping[str, Any],
                 **record: Any) -> Path:
    """Writes ``task``'s ``copilot`` (weights, alpha, its operators), the recipe's ``config``
    (its ``network.hidden`` rebuilds the network) and ``record`` atomically."""
    payload = {"state": {"copilot": copilot.network.state_dict()}, "config": dict(config),
               "alpha": copilot.alpha, "operators": list(copilot.operators), **record}
    return save_checkpoint(path, task=copilot_task(task), payload=payload)


def load_copilot(path: str | Path, task: Task) -> TrainedCopilot:
    """``task``'s copilot saved at ``path`` (:func:`save_copilot`), frozen in eval mode.

    Raises:
        ValueError: no copilot there, or a checkpoint of something else (one line).
    """
    data = load_checkpoint(path, task=copilot_task(task), modules=("copilot",))
    network = task.make_copilot_network(data["config"]["network"]["hidden"])
    network.load_state_dict(data["state"]["copilot"])
    return TrainedCopilot(network.requires_grad_(False).eval(), float(data["alpha"]), tuple(data["operators"]))
