"""Arbiters: who gets how much authority (the fusion weight beta of Eqs. 14-15, 18).

Every arbiter reads the two confidences (and, for HULA, the machine's uncertainty) and
writes the same two keys, ``confidence_ratio`` (b_t, Eq. 18) and ``beta`` (the
machine's share of authority in Eq. 14), so every method of the paper is the same
pipeline with a different arbiter.

Every frame is checked where it enters, at one reduction per tensor and no device sync
(:func:`~dcsc_torchrl.checks.check_values`): the two confidences in [0, 1], theta
finite, the beta an arbiter gives in [0, 1] (a custom arbiter's too).

An arbiter's whole state (theta, and the gain, threshold, value or frozen confidences
its form was built with, with the form's name and ``dims``) is its ``state_dict``;
loading the state of another form or ``dims`` is refused with one line.
:func:`save_arbiter` / :func:`load_arbiter` write and read it as a checkpoint
(atomic, ``weights_only``, of one task).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from dcsc_torchrl.checks import check_in_range, check_values
from dcsc_torchrl.machine import machine_mean_key

_EXTRA_STATE = "_extra_state"


def confidence_ratio(machine_confidence: torch.Tensor, human_confidence: torch.Tensor) -> torch.Tensor:
    """Eq. 18: ``b_t = b_m / (b_m + b_h)``, in [0, 1].

    When both confidences are 0 the ratio is undefined; it is set to 0.5 (neither side
    is favoured), so the result is never NaN.

    Examples:
        >>> confidence_ratio(torch.tensor([0.9, 0.0]), torch.tensor([0.1, 0.0]))
        tensor([0.9000, 0.5000])
    """
    total = machine_confidence + human_confidence
    safe_total = torch.where(total > 0, total, torch.ones_like(total))
    return torch.where(total > 0, machine_confidence / safe_total, torch.full_like(total, 0.5))


def fusion_weight(theta: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """Eq. 15: ``beta_t(theta) = 1 / (1 + exp(-theta * b_t))`` (one theta per action dim)."""
    return torch.sigmoid(theta * ratio)


class Arbiter(TensorDictModuleBase):
    """Base arbiter: writes ``confidence_ratio`` (Eq. 18) and ``beta`` of shape ``[*batch, dims]``.

    Subclasses define :meth:`machine_share`, the beta that Eq. 14 gives the machine, and,
    where their constructor takes numbers besides ``dims``, :meth:`arguments` and
    :meth:`set_arguments` (they travel in the ``state_dict``'s extra state).

    Args:
        dims: number of action dimensions beta is given for (1 for a discrete
            action, d for a d-dimensional continuous action).
        in_keys: machine confidence, human confidence (and any further key the
            subclass reads).
        out_keys: confidence ratio, beta.
    """

    default_in_keys: tuple[NestedKey, ...] = ("machine_confidence", "human_confidence")

    def __init__(
        self,
        dims: int = 1,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] = ("confidence_ratio", "beta"),
    ) -> None:
        super().__init__()
        if int(dims) != dims or dims < 1:
            raise ValueError(f"dims must be an integer >= 1, got {dims!r}")
        self.dims = int(dims)
        self.in_keys = list(in_keys) if in_keys is not None else list(self.default_in_keys)
        self.out_keys = list(out_keys)
        self.register_load_state_dict_pre_hook(_refuse_another_form)

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        """The machine's authority beta, broadcastable to ``[*batch, dims]``."""
        raise NotImplementedError

    def confidences(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``(b_m, b_h)`` of the frame, each checked in [0, 1] (NaN refused) and of one shape."""
        machine_key, human_key = self.in_keys[:2]
        b_m = tensordict.get(machine_key, None)
        b_h = tensordict.get(human_key, None)
        name = type(self).__name__
        if b_m is None:
            raise KeyError(
                f"{name} reads {machine_key!r}, which is missing: run the MCDropoutPolicy before the "
                "arbiter (SharedPolicyModule does)"
            )
        if b_h is None:
            raise KeyError(
                f"{name} reads {human_key!r}, which is missing: add HumanConfidenceTransform to the env"
            )
        if b_m.shape != b_h.shape:
            raise ValueError(
                f"{name}'s {machine_key!r} has shape {tuple(b_m.shape)} but {human_key!r} has {tuple(b_h.shape)}: "
                "one confidence per frame each"
            )
        return check_values(str(machine_key), b_m, 0.0, 1.0), check_values(str(human_key), b_h, 0.0, 1.0)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        ratio = confidence_ratio(*self.confidences(tensordict))
        beta = self.machine_share(ratio, tensordict)
        name = type(self).__name__
        if beta.shape[-1:] not in ((1,), (self.dims,)):
            raise ValueError(f"{name} gives beta of shape {tuple(beta.shape)}: its last dim must be 1 or dims={self.dims}")
        check_values(f"beta ({name})", beta, 0.0, 1.0)
        beta = beta.expand(*ratio.shape[:-1], self.dims)
        ratio_key, beta_key = self.out_keys
        tensordict.set(ratio_key, ratio)
        tensordict.set(beta_key, beta)
        return tensordict

    def arguments(self) -> dict[str, float]:
        """The numbers besides ``dims`` this form's constructor took (saved with its state)."""
        return {}

    def set_arguments(self) -> None:
        """Checks and sets the numbers of :meth:`arguments` (the constructor and a state load call it)."""

    def get_extra_state(self) -> dict[str, Any]:
        return {"form": type(self).__name__, "dims": self.dims, "arguments": self.arguments()}

    def set_extra_state(self, state: Mapping[str, Any]) -> None:
        self.set_arguments(**state["arguments"])

    @classmethod
    def from_state(cls, state: Mapping[str, Any], prefix: str = "") -> Arbiter:
        """A new arbiter of this form built from a ``state_dict`` (its extra state at ``prefix``), not yet loaded."""
        extra = state[prefix + _EXTRA_STATE]
        return cls(dims=extra["dims"], **extra["arguments"])


def _refuse_another_form(
    module: Arbiter, state: Mapping[str, Any], prefix: str, local_metadata: dict, strict: bool, *args: Any
) -> None:
    """``load_state_dict``'s pre-hook: refuses, before anything is loaded, the state of another form or dims."""
    # imported here: the checkpoint module imports the config, needed only when a state is loaded
    from dcsc_torchrl.checkpoint import CheckpointError

    mine = type(module).__name__
    extra = state.get(prefix + _EXTRA_STATE)
    if extra is None:
        if strict:
            raise CheckpointError(f"the state holds no arbiter form ({prefix}{_EXTRA_STATE}): it is not a {mine}'s")
        return
    if extra["form"] != mine:
        raise CheckpointError(f"a {extra['form']}'s state cannot be loaded into a {mine} (another arbiter form)")
    if extra["dims"] != module.dims:
        raise CheckpointError(f"a {mine}'s state of dims={extra['dims']} cannot be loaded into one of dims={module.dims}")


def arbiter_forms() -> dict[str, type[Arbiter]]:
    """Every :class:`Arbiter` subclass imported, by class name (the form a saved state names)."""
    forms: dict[str, type[Arbiter]] = {}
    todo = [Arbiter]
    while todo:
        for sub in todo.pop().__subclasses__():
            forms[sub.__name__] = sub
            todo.append(sub)
    return forms


def save_arbiter(arbiter: Arbiter, path: str | os.PathLike, *, task: str) -> Path:
    """Writes ``arbiter``'s ``state_dict`` (form, dims, theta, gain, ...) as a checkpoint of ``task``.

    Atomic and plain data (:func:`~dcsc_torchrl.checkpoint.save_checkpoint`): read it back
    with :func:`load_arbiter`.

    Raises:
        ValueError: for a :class:`RuleArbiter` (its rule is code, not state).
    """
    from dcsc_torchrl.checkpoint import save_checkpoint
    if isinstance(arbiter, RuleArbiter):
        raise ValueError("a RuleArbiter's rule is code, not state: it cannot be saved; rebuild it from its rule")
    if isinstance(arbiter, InterventionArbiter):
        raise ValueError("an InterventionArbiter holds no state of its own: save its q_value network, "
                         "and rebuild the arbiter from it")
    return save_checkpoint(path, task=task, payload={"arbiter": arbiter.state_dict()})


def load_arbiter(path: str | os.PathLike, *, task: str, into: Arbiter | None = None) -> Arbiter:
    """Reads an arbiter written by :func:`save_arbiter` (``weights_only``), refusing another task or form.

    Args:
        path: the file.
        task: the task it must have been saved for.
        into: load the state into this arbiter, which must be of the saved form and dims;
            by default a new arbiter of the saved form is built (default keys).

    Returns:
        The loaded arbiter (``into`` where given).

    Raises:
        CheckpointError: naming both, for a file of another task, or a state of another
            form or dims than ``into``; or for a file that holds no arbiter.
    """
    from dcsc_torchrl.checkpoint import CheckpointError, load_checkpoint
    data = load_checkpoint(path, task=task)
    state = data.get("arbiter")
    if not isinstance(state, Mapping) or not isinstance(state.get(_EXTRA_STATE), Mapping):
        raise CheckpointError(f"{path} holds no arbiter (save_arbiter writes one)")
    form = state[_EXTRA_STATE].get("form")
    forms = arbiter_forms()
    if into is None and form not in forms:
        raise CheckpointError(f"{path} holds an arbiter of form {form!r}, which is not an Arbiter class imported here")
    arbiter = forms[form].from_state(state) if into is None else into
    try:
        arbiter.load_state_dict(state)
    except CheckpointError as error:
        raise CheckpointError(f"{path}: {error}") from None
    return arbiter


class ConfidenceArbiter(Arbiter):
    """DC-SC's learnable arbiter, Eq. 15: ``beta = sigmoid(theta * b_t)``.

    ``theta`` is an ``nn.Parameter`` with one entry per action dimension (docs/math.md §6:
    1 for LunarLander, 3 for the UAV), trained by Eq. 19 (:class:`~dcsc_torchrl.losses.ThetaLoss`
    or TorchRL's ``DDPGLoss``). With ``theta >= 0`` beta stays in [0.5, sigmoid(theta)].

    Args:
        theta_init: initial value of every entry of theta (finite).
        dims: number of action dimensions.

    Examples:
        >>> from tensordict import TensorDict
        >>> arbiter = ConfidenceArbiter(theta_init=2.0, dims=1)
        >>> td = TensorDict({"machine_confidence": torch.tensor([[0.8]]),
        ...                  "human_confidence": torch.tensor([[0.2]])}, [1])
        >>> arbiter(td)["beta"]
        tensor([[0.8320]], grad_fn=<ExpandBackward0>)
    """

    def __init__(self, theta_init: float = 1.0, dims: int = 1, **kwargs) -> None:
        super().__init__(dims, **kwargs)
        if not math.isfinite(theta_init):
            raise ValueError(f"theta_init must be finite, got {theta_init!r}")
        self.theta = nn.Parameter(torch.full((self.dims,), float(theta_init)))

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return fusion_weight(check_values(f"theta ({type(self).__name__})", self.theta), ratio)


class MachineOnlyArbiter(Arbiter):
    """The machine alone (A2C / DDPG baseline): beta = 1."""

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return torch.ones_like(ratio)


class HumanOnlyArbiter(Arbiter):
    """The operator alone: beta = 0."""

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return torch.zeros_like(ratio)


class HULAArbiter(Arbiter):
    """HULA (the paper's ref. [31]): the operator takes over when the machine is unsure.

    ``beta = 0`` when ``machine_uncertainty > threshold``, else ``beta = 1``.

    Args:
        threshold: the uncertainty above which control passes to the operator (>= 0).
            The experiments calibrate it as the 90th percentile of the machine's
            uncertainty during the operator-alone runs.
        dims: number of action dimensions.
        uncertainty_key: where the machine's uncertainty c_t is read.
    """

    def __init__(
        self,
        threshold: float,
        dims: int = 1,
        *,
        uncertainty_key: NestedKey = "machine_uncertainty",
        **kwargs,
    ) -> None:
        super().__init__(dims, **kwargs)
        self.set_arguments(threshold)
        self.uncertainty_key = uncertainty_key
        self.in_keys = [*self.in_keys[:2], uncertainty_key]

    def arguments(self) -> dict[str, float]:
        return {"threshold": self.threshold}

    def set_arguments(self, threshold: float) -> None:
        check_in_range("threshold", threshold, 0.0, float("inf"), low_inclusive=True, high_inclusive=False)
        self.threshold = float(threshold)

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        uncertainty = tensordict.get(self.uncertainty_key, None)
        if uncertainty is None:
            raise KeyError(
                f"HULAArbiter reads {self.uncertainty_key!r}, which is missing: run the MCDropoutPolicy "
                "before the arbiter (SharedPolicyModule does)"
            )
        check_values(str(self.uncertainty_key), uncertainty, 0.0)
        return (uncertainty <= self.threshold).to(ratio.dtype)


class RuleArbiter(Arbiter):
    """A hand-written, rule-based switch: the machine holds the controls where ``rule`` holds.

    The paper's other family of authority allocation (its §1: "rule-based approaches grant
    authority based on predefined logic or conditions"), kept as a reference that reads
    the state and no confidence: ``beta = rule(observation)``, 1 (the machine) where the
    rule holds and 0 (the operator) elsewhere. A rule may also return a share in [0, 1].
    It shows whether the two partners are complementary *in state*, which no constant
    beta and no scalar theta can express (docs/records/results.md).

    Args:
        rule: ``observation [*batch, obs] -> [*batch]``, a bool or a share in [0, 1] per frame.
        dims: number of action dimensions.
        observation_key: where the observation is read.

    Examples:
        >>> from tensordict import TensorDict
        >>> arbiter = RuleArbiter(lambda obs: obs[..., 0] > 0)
        >>> td = TensorDict({"machine_confidence": torch.ones(2, 1), "human_confidence": torch.ones(2, 1),
        ...                  "observation": torch.tensor([[0.5, 0.0], [-0.5, 0.0]])}, [2])
        >>> arbiter(td)["beta"]
        tensor([[1.],
                [0.]])
    """

    def __init__(self, rule: Callable[[torch.Tensor], torch.Tensor], dims: int = 1, *,
                 observation_key: NestedKey = "observation", **kwargs) -> None:
        super().__init__(dims, **kwargs)
        if not callable(rule):
            raise TypeError(f"rule must be callable (observation -> share per frame), got {type(rule).__name__}")
        self.rule = rule
        self.observation_key = observation_key
        self.in_keys = [*self.in_keys[:2], observation_key]

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        share = self.rule(tensordict.get(self.observation_key)).to(ratio.dtype)
        if share.shape != ratio.shape[:-1]:
            raise ValueError(f"RuleArbiter's rule must return one share per frame, shape {tuple(ratio.shape[:-1])}, "
                             f"got {tuple(share.shape)}")
        return check_values("rule share", share, 0.0, 1.0).unsqueeze(-1)


class InterventionArbiter(Arbiter):
    """IDA, interventional assistance (McMahan et al., 2024): the machine acts exactly where a
    Q function says its action beats the operator's.

    ``beta = 1`` where ``Q(s, a_machine) > Q(s, a_operator)``, else ``beta = 0``: on a tie the
    operator keeps control. Discrete actions: ``q_value(observation) -> [*batch, n]`` action
    values, ``a_machine`` the machine's most likely key (the argmax of ``machine_probs``),
    ``a_operator`` the operator's key. Continuous actions: ``q_value(observation, action) ->
    [*batch, 1]`` on the two actions. One beta for every action dimension: IDA hands over the
    whole action. No confidence enters the decision. ``q_value`` is used as given, under
    ``torch.no_grad()`` (the protocol hands it a copy of the cell's critic).

    Args:
        q_value: the action-value network.
        dims: number of action dimensions.
        discrete: whether the actions are one-hot keys (``q_value`` gives a value per key).
        observation_key, machine_key, human_key: where the state and the two actions are read
            (``machine_key`` defaults to ``machine_probs`` for discrete actions, ``machine_action``
            otherwise).

    Examples:
        >>> from tensordict import TensorDict
        >>> q = lambda obs: torch.tensor([[0.0, 1.0, 0.5], [0.0, 1.0, 2.0]])
        >>> arbiter = InterventionArbiter(q, discrete=True)
        >>> td = TensorDict({"machine_confidence": torch.ones(2, 1), "human_confidence": torch.ones(2, 1),
        ...                  "observation": torch.zeros(2, 1), "machine_probs": torch.tensor([[0.2, 0.7, 0.1]] * 2),
        ...                  "human_action": torch.tensor([[0.0, 0.0, 1.0]] * 2)}, [2])
        >>> arbiter(td)["beta"]
        tensor([[1.],
                [0.]])
    """

    def __init__(self, q_value: Callable[..., torch.Tensor], dims: int = 1, *, discrete: bool,
                 observation_key: NestedKey = "observation", machine_key: NestedKey | None = None,
                 human_key: NestedKey = "human_action", **kwargs) -> None:
        super().__init__(dims, **kwargs)
        if not callable(q_value):
            raise TypeError(f"q_value must be callable (an action-value network), got {type(q_value).__name__}")
        self.q_value = q_value
        self.discrete = bool(discrete)
        self.observation_key = observation_key
        self.machine_key = machine_key or machine_mean_key(discrete)
        self.human_key = human_key
        self.in_keys = [*self.in_keys[:2], observation_key, self.machine_key, human_key]

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        observation = tensordict.get(self.observation_key)
        machine, human = tensordict.get(self.machine_key), tensordict.get(self.human_key)
        with torch.no_grad():
            if self.discrete:
                values = self.q_value(observation)
                q_machine = values.gather(-1, machine.argmax(-1, keepdim=True))
                q_human = values.gather(-1, human.argmax(-1, keepdim=True))
            else:
                q_machine, q_human = self.q_value(observation, machine), self.q_value(observation, human)
        check_values("the intervention's Q", torch.cat([q_machine, q_human], -1))
        return (q_machine > q_human).to(ratio.dtype)


def centred_fusion_weight(theta: torch.Tensor, ratio: torch.Tensor, gain: float) -> torch.Tensor:
    """The centred form of Eq. 15: ``beta = sigmoid(theta + gain * (2 b_t - 1))``.

    Equal confidences (``b_t = 1/2``) give ``sigmoid(theta)``, so at ``theta = 0`` both
    partners get half the authority; a more confident machine always gets more authority
    than a less confident one (``gain > 0``), and theta, a learnable offset, can hand the
    majority to either side. ``d beta / d theta = beta (1 - beta)``, so Eq. 19 carries
    over without its ``b_t`` factor.

    Examples:
        >>> centred_fusion_weight(torch.zeros(1), torch.tensor([0.5, 2 / 3]), gain=3.0)
        tensor([0.5000, 0.7311])
    """
    return torch.sigmoid(theta + gain * (2.0 * ratio - 1.0))


class CentredConfidenceArbiter(Arbiter):
    """DC-SC's arbiter in centred form: ``beta = sigmoid(theta + gain * (2 b_t - 1))``.

    Eq. 15 as printed, ``sigmoid(theta * b_t)``, keeps ``beta >= 1/2`` while
    ``theta >= 0`` and, for ``theta < 0``, gives a *more* confident machine *less*
    authority. This form keeps what the paper's text asks of the arbiter (authority
    favours the more confident side) and lets the learned theta move authority either
    way: equal confidences give ``sigmoid(theta)``, and ``gain`` says how much a
    confidence gap counts (with the default 3, a side twice as confident as the other,
    ``b_t = 2/3``, gets 73% of the authority at ``theta = 0``). theta is trained by the
    same losses as :class:`ConfidenceArbiter` (:class:`~dcsc_torchrl.losses.ThetaLoss`,
    TorchRL's ``DDPGLoss``); its gradient is Eq. 19 with ``b_t`` replaced by 1.

    Args:
        theta_init: initial value of every entry of theta (finite; 0: equal authority
            at equal confidences).
        dims: number of action dimensions.
        gain: weight of the confidence gap, > 0 and finite.

    Examples:
        >>> from tensordict import TensorDict
        >>> arbiter = CentredConfidenceArbiter(theta_init=0.0)
        >>> td = TensorDict({"machine_confidence": torch.tensor([[0.2]]),
        ...                  "human_confidence": torch.tensor([[0.6]])}, [1])
        >>> arbiter(td)["beta"]
        tensor([[0.1824]], grad_fn=<ExpandBackward0>)
    """

    def __init__(self, theta_init: float = 0.0, dims: int = 1, *, gain: float = 3.0, **kwargs) -> None:
        super().__init__(dims, **kwargs)
        if not math.isfinite(theta_init):
            raise ValueError(f"theta_init must be finite, got {theta_init!r}")
        self.set_arguments(gain)
        self.theta = nn.Parameter(torch.full((self.dims,), float(theta_init)))

    def arguments(self) -> dict[str, float]:
        return {"gain": self.gain}

    def set_arguments(self, gain: float) -> None:
        check_in_range("gain", gain, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        self.gain = float(gain)

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return centred_fusion_weight(check_values(f"theta ({type(self).__name__})", self.theta), ratio, self.gain)


class ConstantArbiter(Arbiter):
    """A fixed blend, ``beta = value`` whatever the confidences (the best-constant reference).

    A sweep of constant betas over the validation scenarios is an oracle no real arbiter
    has: it shows how well the two partners could do blended at the best fixed weight.

    Args:
        value: the machine's authority, in [0, 1].
        dims: number of action dimensions.
    """

    def __init__(self, value: float, dims: int = 1, **kwargs) -> None:
        super().__init__(dims, **kwargs)
        self.set_arguments(value)

    def arguments(self) -> dict[str, float]:
        return {"value": self.value}

    def set_arguments(self, value: float) -> None:
        check_in_range("value", value, 0.0, 1.0, low_inclusive=True, high_inclusive=True)
        self.value = float(value)

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return torch.full_like(ratio, self.value)


class FrozenConfidenceArbiter(Arbiter):
    """A learned arbiter fed constant confidences: the ablation "what the confidences add".

    Reads nothing from the frame: ``b_m`` and ``b_h`` are held at fixed values (their
    means over the collaboration runs), and ``arbiter``'s own theta (and its form)
    decides beta from the constant ratio. Trained like any DC-SC arbiter.

    Args:
        arbiter: a :class:`ConfidenceArbiter` or :class:`CentredConfidenceArbiter`.
        machine_confidence: the frozen ``b_m``, in [0, 1].
        human_confidence: the frozen ``b_h``, in [0, 1].
    """

    def __init__(self, arbiter: Arbiter, machine_confidence: float, human_confidence: float) -> None:
        if not isinstance(getattr(arbiter, "theta", None), nn.Parameter):
            raise ValueError(
                f"FrozenConfidenceArbiter needs a learned arbiter (one with a theta parameter), got "
                f"{type(arbiter).__name__}"
            )
        super().__init__(arbiter.dims, in_keys=arbiter.in_keys, out_keys=arbiter.out_keys)
        self.set_arguments(machine_confidence, human_confidence)
        self.arbiter = arbiter

    def arguments(self) -> dict[str, float]:
        return dict(zip(("machine_confidence", "human_confidence"), self.frozen, strict=True))

    def set_arguments(self, machine_confidence: float, human_confidence: float) -> None:
        check_in_range("machine_confidence", machine_confidence, 0.0, 1.0, low_inclusive=True, high_inclusive=True)
        check_in_range("human_confidence", human_confidence, 0.0, 1.0, low_inclusive=True, high_inclusive=True)
        self.frozen = (float(machine_confidence), float(human_confidence))

    @classmethod
    def from_state(cls, state: Mapping[str, Any], prefix: str = "") -> Arbiter:
        inner_prefix = f"{prefix}arbiter."
        inner = arbiter_forms()[state[inner_prefix + _EXTRA_STATE]["form"]].from_state(state, inner_prefix)
        return cls(inner, **state[prefix + _EXTRA_STATE]["arguments"])

    @property
    def theta(self) -> nn.Parameter:
        return self.arbiter.theta

    def confidences(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """The frozen ``(b_m, b_h)``, shaped like the frame's ``human_confidence``."""
        like = tensordict.get(self.in_keys[1])
        b_m, b_h = (torch.full_like(like, value) for value in self.frozen)
        return b_m, b_h

    def machine_share(self, ratio: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        return self.arbiter.machine_share(ratio, tensordict)
