"""The shared policy of Eq. 14: MC-dropout machine -> arbiter -> blend (-> sample)."""

from __future__ import annotations

import functools
from collections import OrderedDict

import torch
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Bounded, Composite, OneHot, TensorSpec
from torchrl.modules import OneHotCategorical

from dcsc_torchrl.arbiters import Arbiter
from dcsc_torchrl.checks import check_values
from dcsc_torchrl.machine import MCDropoutPolicy


class PolicyBlend(nn.Module):
    """Eq. 14: ``beta * machine + (1 - beta) * human``, optionally clipped to a box.

    Discrete: ``machine`` and ``human`` are distributions over actions (the operator's
    one-hot key is a point mass), the result is the mixture's probabilities. ``human`` is
    checked on every frame to be one (:func:`check_distribution`): a ``human_action`` of
    ``[1, 1, 0, 0]`` would make probabilities summing to more than 1. ``machine`` is the
    MC-dropout machine's mean softmax, a distribution by construction from samples it
    checks finite (:class:`~dcsc_torchrl.machine.MCDropoutPolicy`); a stored one entering
    a loss is checked there (:class:`~dcsc_torchrl.losses.ThetaLoss`).
    Continuous: they are actions and the result is the blended action, clipped to
    ``[low, high]`` when given (Eq. 14 on a bounded action: an operator's action outside
    the box is clipped with the blend, as the env would; a NaN is refused, never clipped).
    The checks are one reduction per tensor and no device sync
    (:func:`~dcsc_torchrl.checks.check_values`); the shapes are compared for free.

    Args:
        low: the box's lower corner (continuous), or ``None``.
        high: the box's upper corner (continuous), or ``None``.
        discrete: whether ``machine`` and ``human`` are distributions.
        names: what ``machine`` and ``human`` are called in messages (their TensorDict keys).
    """

    def __init__(
        self,
        low: torch.Tensor | None = None,
        high: torch.Tensor | None = None,
        *,
        discrete: bool = False,
        names: tuple[str, str] = ("machine_probs", "human_action"),
    ) -> None:
        super().__init__()
        self.register_buffer("low", None if low is None else torch.as_tensor(low))
        self.register_buffer("high", None if high is None else torch.as_tensor(high))
        self.discrete = discrete
        self.names = names

    def forward(self, beta: torch.Tensor, machine: torch.Tensor, human: torch.Tensor) -> torch.Tensor:
        machine_name, human_name = self.names
        if machine.shape[-1:] != human.shape[-1:]:  # a shape check: no host sync
            raise ValueError(
                f"the machine gives {machine.shape[-1]} action values per frame but the operator's "
                f"{human_name} has {human.shape[-1]}: the action spec and the machine network disagree"
            )
        if machine.shape != human.shape:
            raise ValueError(
                f"the operator's {human_name} has shape {tuple(human.shape)} but {machine_name} has "
                f"{tuple(machine.shape)}: one action per frame each"
            )
        if self.discrete:
            check_distribution(human_name, human)
        else:
            check_values(human_name, human)
        human = human.to(machine.dtype)
        blended = beta * machine + (1 - beta) * human
        if self.low is not None:
            blended = torch.maximum(torch.minimum(blended, self.high), self.low)
        return blended


def check_distribution(name: str, values: torch.Tensor) -> torch.Tensor:
    """Checks that every frame of ``values`` ``[*batch, n]`` is a distribution: in [0, 1], summing to 1.

    Two reductions, no device sync (:func:`~dcsc_torchrl.checks.check_values`); a float
    sum may miss 1 by the square root of the dtype's epsilon (3.5e-4 in float32: a mean of
    softmaxes' rounding, far below any mass gained or lost).

    Raises:
        ValueError: naming ``name``, for a NaN, an entry out of [0, 1] or a sum other than 1.

    Examples:
        >>> check_distribution("human_action", torch.tensor([[1, 1, 0, 0]]))
        Traceback (most recent call last):
        ...
        ValueError: human_action's sum per frame (one-hot or probabilities) must be in [1.0, 1.0], got 2
    """
    check_values(name, values, 0.0, 1.0)
    slack = _sum_slack(values.dtype)
    check_values(f"{name}'s sum per frame (one-hot or probabilities)", values.sum(-1), 1.0 - slack, 1.0 + slack)
    return values


@functools.cache
def _sum_slack(dtype: torch.dtype) -> float:
    """How far a distribution's sum may miss 1: the square root of ``dtype``'s epsilon, 2 digits (0 for integers)."""
    return float(f"{torch.finfo(dtype).eps ** 0.5:.1e}") if dtype.is_floating_point else 0.0


class OneHotMixture(OneHotCategorical):
    """Eq. 14's mixture over the keys as TorchRL's ``OneHotCategorical``, with a mode that is one key.

    TorchRL's ``mode`` marks every key tied for the largest logit. Eq. 14 ties two keys
    exactly where ``beta = 1/2`` meets a machine sure of a key other than the operator's
    (both get probability 1/2), and that mode is a two-hot "action": the env pressed its
    first key, a critic's loss refused it. Here the mode is that first key alone (the
    same key wherever there is no tie); sampling is TorchRL's.
    """

    @property
    def mode(self) -> torch.Tensor:
        logits = self.logits  # what TorchRL's mode compares
        return torch.nn.functional.one_hot(logits.argmax(-1), logits.shape[-1])


def plays_operator_alone(beta: float, *, discrete: bool, mode: bool) -> bool:
    """Whether Eq. 14 at a constant ``beta`` acts exactly as the operator alone, on every frame.

    ``beta = 0`` always: the blend is the operator's action (continuous) or the point mass
    on its key (discrete). With a discrete action taken as the mixture's mode (``mode``),
    also every ``beta < 1/2``: the operator's key ``h`` has probability
    ``(1 - beta) + beta p_m(h) >= 1 - beta > 1/2 > beta >= beta p_m(k)`` for every other key
    ``k``, so the mode is the operator's key whatever the machine's probabilities. Drawing
    the action instead (Algorithm 1) gives the machine's keys a chance at any ``beta > 0``.
    A protocol can reuse the operator-alone run for such a ``beta`` instead of replaying it.

    Examples:
        >>> [b for b in (0.0, 0.2, 0.5, 0.8) if plays_operator_alone(b, discrete=True, mode=True)]
        [0.0, 0.2]
        >>> plays_operator_alone(0.2, discrete=True, mode=False), plays_operator_alone(0.2, discrete=False, mode=True)
        (False, False)
    """
    as_blended = float(torch.tensor(beta, dtype=torch.float32))  # the blend's precision
    return as_blended == 0.0 or (discrete and mode and as_blended < 0.5)


class SharedPolicyModule(TensorDictSequential):
    """DC-SC's shared policy (Eq. 14) as one TensorDict module, ready for a Collector.

    Named parts, in order (``policy["arbiter"]`` etc.):

    - ``machine``: the :class:`~dcsc_torchrl.machine.MCDropoutPolicy` (Eqs. 10, 13);
    - ``arbiter``: any :class:`~dcsc_torchrl.arbiters.Arbiter` (Eqs. 15, 18);
    - ``blend``: :class:`PolicyBlend` (Eq. 14);
    - discrete only, ``sample``: a probabilistic module drawing the one-hot ``action``
      from :class:`OneHotMixture` ``(probs)`` (Algorithm 1, line 7: actions are sampled; with
      ``ExplorationType.MODE`` its most likely key, the first of tied ones).

    Discrete when ``action_spec`` is ``OneHot`` (the machine must output ``"probs"``);
    continuous when it is ``Bounded`` (the machine outputs ``"action"``, the blend is
    clipped to the box). The human action is read from ``human_action``, written by
    :class:`~dcsc_torchrl.transforms.HumanOperatorTransform`.

    Args:
        machine: the MC-dropout machine policy.
        arbiter: the arbiter deciding beta.
        action_spec: the environment's action spec (``OneHot`` or ``Bounded``).
        action_key: where the shared action is written.
        human_action_key: where the operator's action is read.
        observation_spec: the env's observation spec (optional); with it, an observation
            wider or narrower than the machine's ``observation_size`` is refused here,
            at construction, rather than at the first frame.

    The action sizes are checked at construction where the machine network's last
    ``nn.Linear`` says its output size (:func:`~dcsc_torchrl.machine.linear_widths`),
    otherwise at every call of the blend (a shape comparison, free).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import OneHot
        >>> from dcsc_torchrl.arbiters import ConfidenceArbiter
        >>> net = torch.nn.Sequential(torch.nn.Linear(9, 16), torch.nn.Dropout(0.1),
        ...                           torch.nn.Linear(16, 4))
        >>> policy = SharedPolicyModule(MCDropoutPolicy(net), ConfidenceArbiter(), OneHot(4))
        >>> td = TensorDict({"observation": torch.randn(9),
        ...                  "human_action": torch.tensor([0, 0, 1, 0]),
        ...                  "human_confidence": torch.tensor([0.3])}, [])
        >>> policy(td)["action"].shape
        torch.Size([4])
    """

    def __init__(
        self,
        machine: MCDropoutPolicy,
        arbiter: Arbiter,
        action_spec: TensorSpec,
        *,
        action_key: str = "action",
        human_action_key: str = "human_action",
        observation_spec: TensorSpec | None = None,
    ) -> None:
        mean_key, _, confidence_key = machine.out_keys
        if confidence_key != arbiter.in_keys[0]:
            raise ValueError(
                f"the arbiter reads machine confidence from {arbiter.in_keys[0]!r} but the "
                f"machine writes it to {confidence_key!r}"
            )
        beta_key = arbiter.out_keys[1]
        if isinstance(action_spec, OneHot | Bounded):
            n_actions = action_spec.shape[-1]
            if machine.output_size is not None and machine.output_size != n_actions:
                raise ValueError(
                    f"the action spec {type(action_spec).__name__}({n_actions}) does not match the machine "
                    f"network, whose last layer gives {machine.output_size} values"
                )
        if observation_spec is not None and machine.observation_size is not None:
            obs_key = machine.in_keys[0]
            obs_spec = observation_spec[obs_key] if isinstance(observation_spec, Composite) else observation_spec
            if obs_spec.shape[-1] != machine.observation_size:
                raise ValueError(
                    f"the env's {obs_key!r} has {obs_spec.shape[-1]} values but the machine network was "
                    f"built for {machine.observation_size} (observation_size)"
                )
        parts: OrderedDict[str, nn.Module] = OrderedDict(machine=machine, arbiter=arbiter)
        if isinstance(action_spec, OneHot):
            if machine.output != "probs":
                raise ValueError("a OneHot action spec needs a machine with output='probs'")
            blend = PolicyBlend(discrete=True, names=(str(mean_key), str(human_action_key)))
            parts["blend"] = TensorDictModule(blend, in_keys=[beta_key, mean_key, human_action_key], out_keys=["probs"])
            parts["sample"] = ProbabilisticTensorDictModule(
                in_keys=["probs"],
                out_keys=[action_key],
                distribution_class=OneHotMixture,
                default_interaction_type=InteractionType.RANDOM,
            )
        elif isinstance(action_spec, Bounded):
            if machine.output != "action":
                raise ValueError("a Bounded action spec needs a machine with output='action'")
            if arbiter.dims not in (1, action_spec.shape[-1]):
                raise ValueError(
                    f"arbiter.dims={arbiter.dims} must be 1 or the action size {action_spec.shape[-1]}"
                )
            box = PolicyBlend(action_spec.space.low, action_spec.space.high, names=(str(mean_key), str(human_action_key)))
            parts["blend"] = TensorDictModule(
                box, in_keys=[beta_key, mean_key, human_action_key], out_keys=[action_key]
            )
        else:
            raise TypeError(
                f"action_spec must be OneHot (discrete) or Bounded (continuous), got {type(action_spec).__name__}"
            )
        super().__init__(parts)
        self.discrete = isinstance(action_spec, OneHot)

    def authority_actor(self) -> ProbabilisticTensorDictSequential:
        """The discrete shared policy on the machine's stored output: arbiter, blend and mixture.

        The machine is not rerun (its ``machine_probs`` and confidence are read from the
        frame), so a policy-gradient loss (TorchRL's ``A2CLoss``) differentiates Eq. 14's
        mixture with respect to the arbiter's parameters alone. The parts are this policy's
        own modules: a step of the loss moves the arbiter the policy acts with.
        """
        if not self.discrete:
            raise ValueError("authority_actor is the discrete mixture of Eq. 14; a continuous shared action "
                             "is a deterministic blend (DDPGLoss differentiates it)")
        return ProbabilisticTensorDictSequential(self["arbiter"], self["blend"], self["sample"])
