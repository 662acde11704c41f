"""An arbiter that learns *when*, not only *whom*: theta depends on the frame (docs/architecture.md,
"The state-dependent arbiter").

Eq. 15 and its centred form give the machine ``beta = sigmoid(theta b_t)`` or
``sigmoid(theta + gain (2 b_t - 1))`` with one learned ``theta`` per action dimension: a
scalar that can only pick a partner. Here theta is a function of the frame::

    theta_t = theta + spread * tanh(g_psi(s_t, b_h, b_m, a_h, a_m))

with ``g_psi`` a small MLP on the observation, the two confidences and the two partners'
actions (the operator's key or action, the machine's probabilities or action), and the same
two forms on top. The MLP's last layer starts at zero, so a new arbiter is today's scalar
``theta`` exactly, and with ``g_psi`` held at zero the gradient of any loss with respect to
``theta`` is the scalar arbiter's (Eq. 19 through :class:`~dcsc_torchrl.losses.ThetaLoss`:
the bias-only special case). ``spread`` bounds how far the frame moves theta (``beta``
stays strictly inside (0, 1), so a policy gradient never meets ``log 0``).

It writes the keys every arbiter writes, so :class:`~dcsc_torchrl.policy.SharedPolicyModule`,
the protocol and ``dcsc play`` run it unchanged.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from dcsc_torchrl.arbiters import Arbiter, centred_fusion_weight, fusion_weight
from dcsc_torchrl.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from dcsc_torchrl.checks import check_in_range, check_values
from dcsc_torchrl.networks import authority_critic, machine_fingerprint, mlp

if TYPE_CHECKING:
    from dcsc_torchrl.online import OnlineLearner, PolicyGradientLearner
    from dcsc_torchrl.policy import SharedPolicyModule
    from dcsc_torchrl.task import Task

LEARNER_SETTINGS: dict[str, tuple[str, ...]] = {
    "authority": ("lr", "gamma", "betas", "blend_scenarios", "critic_updates", "arbiter_updates", "batch_size"),
    "policy_gradient": ("lr", "gamma", "gae_lambda", "entropy_coeff", "critic_coeff", "max_grad_norm",
                        "segment_length", "rounds", "scenarios"),
}
"""Each algorithm's settings, which a pretrained arbiter keeps for its cell: ``authority``, the
arbiter against a critic of the authority split ``Q(s, beta)`` fitted on constant blends
(:class:`~dcsc_torchrl.online.AuthorityOnlineLearner`, the critic held); ``policy_gradient``,
A2C on the shared policy's own frames (:class:`~dcsc_torchrl.online.PolicyGradientLearner`)."""

STATE_FORMS = ("paper", "centred")
"""The two forms theta_t enters: Eq. 15 as printed, ``sigmoid(theta_t b_t)``, and the centred one."""


class StateDependentArbiter(Arbiter):
    """``beta = sigmoid(theta_t b_t)`` (``form="paper"``, Eq. 15) or
    ``sigmoid(theta_t + gain (2 b_t - 1))`` (``"centred"``), ``theta_t`` a function of the frame.

    Args:
        observation_size: the observation's width.
        action_size: the width of each partner's action (keys: their number).
        dims: beta's size (1 for keys, the action's dimensions on the UAV).
        form: ``"paper"`` or ``"centred"``.
        theta_init: theta's bias, the value of theta_t of a new arbiter.
        gain: the centred form's confidence-gap weight (> 0).
        hidden: the MLP's hidden widths (Tanh).
        spread: the largest move of theta_t away from its bias (> 0).
        observation_key, human_key, machine_key: what the features are read from; the
            machine's mean is ``machine_probs`` (keys) or ``machine_action``.

    Examples:
        >>> from tensordict import TensorDict
        >>> arbiter = StateDependentArbiter(9, 4, theta_init=0.0)
        >>> td = TensorDict({"machine_confidence": torch.tensor([[0.2]]), "human_confidence": torch.tensor([[0.6]]),
        ...                  "observation": torch.zeros(1, 9), "human_action": torch.eye(4)[:1],
        ...                  "machine_probs": torch.full((1, 4), 0.25)}, [1])
        >>> arbiter(td)["beta"]   # a new arbiter is the centred scalar form at theta_init
        tensor([[0.1824]], grad_fn=<ExpandBackward0>)
    """

    def __init__(self, observation_size: int, action_size: int, dims: int = 1, *, form: str = "centred",
                 theta_init: float = 0.0, gain: float = 3.0, hidden: Sequence[int] = (64, 64), spread: float = 8.0,
                 observation_key: NestedKey = "observation", human_key: NestedKey = "human_action",
                 machine_key: NestedKey = "machine_probs", **kwargs) -> None:
        super().__init__(dims, **kwargs)
        if not math.isfinite(theta_init):
            raise ValueError(f"theta_init must be finite, got {theta_init!r}")
        self.set_arguments(form, gain, spread)
        self.theta = nn.Parameter(torch.full((self.dims,), float(theta_init)))
        self.state_term = mlp(observation_size + 2 + 2 * action_size, self.dims, hidden, activation=nn.Tanh)
        last = self.state_term[-1]
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.observation_size, self.action_size = int(observation_size), int(action_size)
        self.in_keys = [*self.in_keys[:2], observation_key, human_key, machine_key]

    def features(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``[s, b_h, b_m, a_h, a_m]`` per frame, what ``g_psi`` reads."""
        machine_confidence, human_confidence, observation, human, machine = self.in_keys
        keys = (observation, human_confidence, machine_confidence, human, machine)
        widths = (self.observation_size, 1, 1, self.action_size, self.action_size)
        values = []
        for key, width in zip(keys, widths, strict=True):
            value = tensordict.get(key)
            if value.shape[-1] != width:
                raise ValueError(f"{type(self).__name__} reads {key!r} with {width} values per frame, "
                                 f"got shape {tuple(value.shape)}")
            values.append(value)
        return torch.cat([value.to(values[0].dtype) for value in values], -1)

    def thetas(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``theta_t [*batch, dims]``: the bias plus the frame's bounded move."""
        theta = check_values(f"theta ({type(self).__name__})", self.theta)
        return theta + self.spread * torch.tanh(self.state_term(self.features(tensordict)))

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        theta = self.thetas(tensordict)
        if self.form == "paper":
            return fusion_weight(theta, ratio)
        return centred_fusion_weight(theta, ratio, self.gain)

    def arguments(self) -> dict[str, Any]:
        return {"form": self.form, "gain": self.gain, "spread": self.spread}

    def get_extra_state(self) -> dict[str, Any]:
        hidden = [layer.out_features for layer in self.state_term if isinstance(layer, nn.Linear)][:-1]
        return {**super().get_extra_state(),
                "shape": {"observation_size": self.observation_size, "action_size": self.action_size,
                          "hidden": hidden, "in_keys": [str(key) for key in self.in_keys[2:]]}}

    @classmethod
    def from_state(cls, state: Mapping[str, Any], prefix: str = "") -> StateDependentArbiter:
        """A new arbiter of the saved shape and arguments (:func:`~dcsc_torchrl.arbiters.load_arbiter`), not yet loaded."""
        extra = state[prefix + "_extra_state"]
        shape = extra["shape"]
        observation_key, human_key, machine_key = shape["in_keys"]
        return cls(shape["observation_size"], shape["action_size"], extra["dims"], hidden=shape["hidden"],
                   observation_key=observation_key, human_key=human_key, machine_key=machine_key,
                   **extra["arguments"])

    def set_arguments(self, form: str, gain: float, spread: float) -> None:
        if form not in STATE_FORMS:
            raise ValueError(f"form must be one of {', '.join(STATE_FORMS)}, got {form!r}")
        check_in_range("gain", gain, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        check_in_range("spread", spread, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        self.form, self.gain, self.spread = form, float(gain), float(spread)


@dataclass(frozen=True)
class PretrainedArbiter:
    """A state-dependent arbiter pretrained in simulation: the arbiter, the value critic of the
    shared policy fitted beside it, the learner's settings (the cell fine-tunes with them), the
    operators of its pool (it refuses to be evaluated next to one) and the machine it was
    pretrained next to (it refuses another)."""

    arbiter: StateDependentArbiter
    value_net: nn.Module
    settings: Mapping[str, float]
    operators: tuple[str, ...]
    machine: str

    def check_evaluated_next_to(self, operator: str, machine_net: nn.Module) -> None:
        """Refuses an ``operator`` of the pool, or a machine other than the pretraining's, in one line."""
        if operator in self.operators:
            raise ValueError(f"the state-dependent arbiter was pretrained with operator {operator!r} (its pool: "
                             f"{', '.join(self.operators)}): evaluate it next to an operator outside its pool")
        fingerprint = machine_fingerprint(machine_net)
        if fingerprint != self.machine:
            raise ValueError(f"the state-dependent arbiter was pretrained next to machine {self.machine}, "
                             f"this machine is {fingerprint}: pretrain one next to it (dcsc arbiter)")

    def check_refittable(self) -> None:
        """Refuses a refit on a cell's calibration runs (``warmup.refit_state_arbiter``) in one line
        unless the arbiter learns by ``authority``: the refit is of its critic ``Q(s, beta)``."""
        if self.settings["algorithm"] != "authority":
            raise ValueError(f"warmup.refit_state_arbiter refits the authority critic Q(s, beta): this arbiter learns "
                             f"by {self.settings['algorithm']!r}, which has none (set warmup.refit_state_arbiter=false)")

    def learner(self, policy: SharedPolicyModule, *, copy_critic: bool = True) -> OnlineLearner | PolicyGradientLearner:
        """The learner of ``policy`` (whose arbiter a cell copies from :attr:`arbiter`) by the
        settings' ``algorithm``, with its own copy of the critic (``copy_critic``; the
        pretraining trains :attr:`value_net` itself): ``authority``, the arbiter against the
        held ``Q(s, beta)``; ``policy_gradient``, A2C with the value critic."""
        from dcsc_torchrl.online import AuthorityOnlineLearner, PolicyGradientLearner

        critic = copy.deepcopy(self.value_net) if copy_critic else self.value_net
        settings = self.settings
        if settings["algorithm"] == "authority":
            return AuthorityOnlineLearner(policy, critic, theta_lr=settings["lr"], critic_lr=0.0,
                                          gamma=settings["gamma"], tau=1.0, theta_optimizer="adam")
        pretraining_only = ("rounds", "scenarios")
        return PolicyGradientLearner(policy, critic, **{key: settings[key] for key in LEARNER_SETTINGS["policy_gradient"]
                                                        if key not in pretraining_only})


def authority_fit_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """The keywords of :meth:`~dcsc_torchrl.online.AuthorityOnlineLearner.fit` from an ``authority``
    arbiter's settings: the same fit in pretraining and in a cell's refit on its calibration runs."""
    return {key: settings[key] for key in ("critic_updates", "arbiter_updates", "batch_size", "lr")}


def save_pretrained_arbiter(path: str | Path, task: Task, pretrained: PretrainedArbiter,
                            config: Mapping[str, Any], **record: Any) -> Path:
    """Writes ``task``'s pretrained arbiter (weights only: the arbiter's and the value critic's
    states, the settings, the pool, the machine's fingerprint), the ``config`` (with the two
    networks' widths as its ``network``) and ``record``."""
    linears = [layer.out_features for layer in pretrained.value_net.modules() if isinstance(layer, nn.Linear)]
    network = {"hidden": pretrained.arbiter.get_extra_state()["shape"]["hidden"], "value_hidden": linears[:-1]}
    payload = {"state": {"arbiter": pretrained.arbiter.state_dict(), "value": pretrained.value_net.state_dict()},
               "settings": dict(pretrained.settings), "operators": list(pretrained.operators),
               "machine": pretrained.machine, "config": {**config, "network": network}, **record}
    return save_checkpoint(path, task=state_arbiter_task(task), payload=payload)


def load_pretrained_arbiter(path: str | Path, task: Task) -> PretrainedArbiter:
    """``task``'s pretrained arbiter saved at ``path`` (:func:`save_pretrained_arbiter`).

    Raises:
        ValueError: no such file, or a checkpoint of something else (one line).
    """
    data = load_checkpoint(path, task=state_arbiter_task(task), modules=("arbiter", "value"))
    settings = data.get("settings", {})
    missing = [key for key in ("algorithm", *LEARNER_SETTINGS.get(settings.get("algorithm"), ())) if key not in settings]
    if missing:
        raise CheckpointError(f"{path} lacks the learner's settings {missing} (written by another version of "
                              "dcsc-torchrl?): pretrain it again (dcsc arbiter)")
    arbiter = StateDependentArbiter.from_state(data["state"]["arbiter"])
    arbiter.load_state_dict(data["state"]["arbiter"])
    value_net = state_arbiter_critic(settings["algorithm"], arbiter, data["config"]["network"]["value_hidden"])
    value_net.load_state_dict(data["state"]["value"])
    return PretrainedArbiter(arbiter, value_net, dict(data["settings"]), tuple(data["operators"]), data["machine"])


def state_arbiter_task(task: Task) -> str:
    """The task a pretrained arbiter's checkpoint names (``lunarlander-state-arbiter``)."""
    return f"{task.name}-state-arbiter"


def state_value_network(observation_size: int, hidden: Sequence[int]) -> nn.Sequential:
    """``V(s)``, the shared policy's value critic beside the arbiter: an MLP (Tanh) to one value."""
    return mlp(observation_size, 1, hidden, activation=nn.Tanh)


def state_arbiter_critic(algorithm: str, arbiter: StateDependentArbiter, hidden: Sequence[int]) -> nn.Module:
    """The critic beside ``arbiter`` for ``algorithm``: ``Q(s, beta)`` (``authority``; one network on
    ``(s, beta)``, so its best beta may depend on the state) or ``V(s)`` (``policy_gradient``)."""
    if algorithm == "authority":
        return authority_critic(arbiter.observation_size, arbiter.dims, hidden, separable=False)
    return state_value_network(arbiter.observation_size, hidden)


def checked_learner_settings(learner: Mapping[str, Any]) -> dict[str, Any]:
    """``learner``'s ``algorithm`` and that algorithm's :data:`LEARNER_SETTINGS`, typed; a ValueError
    naming an unknown algorithm or a missing setting."""
    algorithm = learner.get("algorithm")
    if algorithm not in LEARNER_SETTINGS:
        raise ValueError(f"algorithm must be one of {', '.join(LEARNER_SETTINGS)}, got {algorithm!r}")
    missing = [key for key in LEARNER_SETTINGS[algorithm] if key not in learner]
    if missing:
        raise ValueError(f"the {algorithm} algorithm needs the settings {missing}")
    counts = {"segment_length", "rounds", "scenarios", "blend_scenarios", "critic_updates", "arbiter_updates",
              "batch_size"}
    settings: dict[str, Any] = {"algorithm": algorithm}
    for key in LEARNER_SETTINGS[algorithm]:
        value = learner[key]
        settings[key] = ([float(v) for v in value] if key == "betas" else int(value) if key in counts
                         else float(value))
    return settings
