"""The method registry: every method of the protocol is the common pipeline with its own arbiter.

A :class:`Method` names an arbiter and says how the protocol runs it (``kind``):

============  ==========  ================================================================
machine       fixed       :class:`MachineOnlyArbiter` (A2C / DDPG alone)
operator      fixed       :class:`HumanOnlyArbiter` (the operator alone)
hula          fixed       :class:`HULAArbiter` (threshold calibrated on the operator-alone runs)
rule          fixed       :class:`RuleArbiter` on the task's hand-written switch
                          (:attr:`Task.authority_rule`; skipped for a task without one)
ida           fixed       :class:`InterventionArbiter` (IDA): the machine acts where the
                          cell's critic (Algorithm 1's Q, after its warm-up) rates its
                          action above the operator's
ida_expert    fixed       the same rule on an expert's Q given to the cell (IDA as its
                          paper runs it, e.g. a converged machine's critic); run only
                          when named, with the expert given
reddy         fixed       Reddy et al.'s copilot (:mod:`dcsc_torchrl.copilot`): a DQN
                          trained with surrogate pilots is the machine, its tolerance
                          rule the arbiter (for a task with a copilot network); run
                          only when named, with a trained copilot given
dcsc          learned     :class:`ConfidenceArbiter` (Eq. 15 as printed), theta learned online
dcsc_centred  learned     :class:`CentredConfidenceArbiter`, theta learned online
dcsc_frozen   frozen      a learned arbiter fed its confidences' collaboration means
                          (:class:`FrozenConfidenceArbiter`): what the confidences add
dcsc_state    pretrained  the state-dependent arbiter (:mod:`dcsc_torchrl.state_arbiter`):
                          theta a function of the frame, pretrained in simulation against
                          a pool of operators, fine-tuned online; run only
                          when named, with a pretrained arbiter given
constant      sweep       :class:`ConstantArbiter`, once per beta of a sweep (its best beta
                          is the report's oracle row ``best_constant``)
============  ==========  ================================================================

Examples:
    >>> [m.name for m in METHODS.values() if m.kind == "learned"]
    ['dcsc', 'dcsc_centred']
    >>> learned_method("centred")
    'dcsc_centred'
    >>> make_arbiter("constant", 3, constant_beta=0.25).value
    0.25
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    import torch
    from torchrl.data import TensorSpec

    from dcsc_torchrl.arbiters import Arbiter
    from dcsc_torchrl.policy import SharedPolicyModule
    from dcsc_torchrl.task import Task


@dataclass(frozen=True)
class Method:
    """One method of the protocol.

    Args:
        name: the method's name in CSVs and on the command line.
        label: its name in tables and figures (``machine`` reads the task's ``machine_label``).
        kind: ``fixed`` (validated as it is), ``learned`` (collaborates, then validates,
            learning online), ``pretrained`` (the same, from an arbiter pretrained outside
            the cell), ``frozen`` (the ablation of a learned arbiter) or ``sweep`` (once per
            constant beta).
        form: the arbiter form of a learned method (``paper`` or ``centred``).
        default: whether a run with no method list runs it (``ida_expert``, ``reddy`` and
            ``dcsc_state`` need an input the protocol does not make, an expert's Q, a trained
            copilot or a pretrained arbiter, so they run only when named).
    """

    name: str
    label: str
    kind: str
    form: str | None = None
    default: bool = True


METHODS: dict[str, Method] = {
    method.name: method
    for method in (
        Method("machine", "machine", "fixed"),
        Method("operator", "operator", "fixed"),
        Method("hula", "HULA", "fixed"),
        Method("rule", "rule-based switch", "fixed"),
        Method("ida", "IDA (Algorithm 1's Q)", "fixed"),
        Method("ida_expert", "IDA (an expert's Q)", "fixed", default=False),
        Method("reddy", "Reddy et al.'s copilot", "fixed", default=False),
        Method("dcsc", "DC-SC (Eq. 15)", "learned", form="paper"),
        Method("dcsc_centred", "DC-SC (centred)", "learned", form="centred"),
        Method("dcsc_frozen", "DC-SC, confidences frozen", "frozen"),
        Method("dcsc_state", "DC-SC, state-dependent (pretrained)", "pretrained", default=False),
        Method("constant", "constant β", "sweep"),
    )
}
"""Every method, in the order of the protocol and the report."""
METHOD_NAMES = tuple(METHODS)
DEFAULT_METHODS = tuple(name for name, method in METHODS.items() if method.default)
"""The methods a run with no method list runs (every method but ``ida_expert``, ``reddy`` and ``dcsc_state``)."""
BEST_CONSTANT = Method("best_constant", "best constant β (oracle)", "oracle")
"""The report's row for the sweep's best beta (picked on the scenarios it is scored on)."""
ARBITER_FORMS = tuple(m.form for m in METHODS.values() if m.kind == "learned")


def task_methods(task: Task, methods: Sequence[str] = DEFAULT_METHODS) -> tuple[str, ...]:
    """``methods`` that ``task`` defines: all of them, less ``rule`` for a task without an
    :attr:`~dcsc_torchrl.tasks.Task.authority_rule`, ``reddy`` for one without a
    :attr:`~dcsc_torchrl.tasks.Task.make_copilot_network`.

    Examples:
        >>> from dcsc_torchrl.tasks import get_task
        >>> "rule" in task_methods(get_task("lunarlander")), "rule" in task_methods(get_task("uav"))
        (True, False)
    """
    return tuple(m for m in methods if (m != "rule" or task.authority_rule is not None)
                 and (m != "reddy" or task.make_copilot_network is not None))


def check_task_methods(task: Task, methods: Sequence[str]) -> None:
    """Refuses ``methods`` that ``task`` does not define (``rule`` without an authority rule,
    ``reddy`` without a copilot network, ``dcsc_state`` on continuous actions)."""
    undefined = [m for m in methods if m not in task_methods(task, METHOD_NAMES)]
    if undefined:
        why = ("no authority rule" if "rule" in undefined
               else "no copilot network (Task.make_copilot_network)" if "reddy" in undefined
               else "continuous actions (the state-dependent arbiter learns by A2C on Eq. 14's mixture of keys)")
        raise ValueError(f"task {task.name} does not define method(s) {', '.join(undefined)}: it has {why}")


def learned_method(form: str) -> str:
    """The learned method whose arbiter has ``form`` (``paper`` -> ``dcsc``, ``centred`` -> ``dcsc_centred``)."""
    for method in METHODS.values():
        if method.kind == "learned" and method.form == form:
            return method.name
    raise ValueError(f"arbiter form must be one of {', '.join(ARBITER_FORMS)}, got {form!r}")


def make_arbiter(
    method: str,
    action_dims: int,
    *,
    theta_init: float = 0.0,
    gain: float = 3.0,
    hula_threshold: float | None = None,
    constant_beta: float | None = None,
    rule: Callable[[torch.Tensor], torch.Tensor] | None = None,
    q_value: torch.nn.Module | None = None,
    expert_q: torch.nn.Module | None = None,
    discrete: bool = True,
) -> Arbiter:
    """The arbiter that makes ``method`` out of the common pipeline (``action_dims`` betas).

    ``dcsc`` is :class:`ConfidenceArbiter` (Eq. 15, ``theta_init``), ``dcsc_centred``
    :class:`CentredConfidenceArbiter` (``theta_init``, ``gain``), ``hula`` a
    :class:`HULAArbiter` of ``hula_threshold``, ``constant`` a :class:`ConstantArbiter`
    of ``constant_beta``, ``rule`` a :class:`RuleArbiter` of ``rule`` (a task's
    ``authority_rule``), ``ida`` an :class:`InterventionArbiter` on a frozen copy of
    ``q_value`` (``discrete``: whether it gives a value per key), ``ida_expert`` the same on
    ``expert_q``. ``dcsc_frozen`` wraps a learned arbiter
    (:class:`FrozenConfidenceArbiter`), so the protocol builds it; ``reddy`` brings its own
    machine too (:meth:`~dcsc_torchrl.copilot.TrainedCopilot.policy`).
    """
    from dcsc_torchrl import arbiters

    if method == "machine":
        return arbiters.MachineOnlyArbiter(action_dims)
    if method == "operator":
        return arbiters.HumanOnlyArbiter(action_dims)
    if method == "hula":
        if hula_threshold is None:
            raise ValueError("the HULA arbiter needs a threshold: calibrate it on the operator-alone runs")
        return arbiters.HULAArbiter(hula_threshold, action_dims)
    if method == "rule":
        if rule is None:
            raise ValueError("the rule arbiter needs a rule: the task's authority_rule (this task has none)")
        return arbiters.RuleArbiter(rule, action_dims)
    if method in ("ida", "ida_expert"):
        network = q_value if method == "ida" else expert_q
        if network is None:
            whose = "the cell's critic (Algorithm 1's Q)" if method == "ida" else "an expert's (expert_q)"
            raise ValueError(f"the {method} arbiter needs a Q network: {whose}")
        frozen = copy.deepcopy(network).requires_grad_(False).eval()
        return arbiters.InterventionArbiter(frozen, action_dims, discrete=discrete)
    if method == "dcsc":
        return arbiters.ConfidenceArbiter(theta_init, action_dims)
    if method == "dcsc_centred":
        return arbiters.CentredConfidenceArbiter(theta_init, action_dims, gain=gain)
    if method == "constant":
        if constant_beta is None:
            raise ValueError("the constant arbiter needs constant_beta")
        return arbiters.ConstantArbiter(constant_beta, action_dims)
    if method == "reddy":
        raise ValueError("method reddy brings its own machine: a TrainedCopilot's policy() builds its shared policy")
    if method == "dcsc_state":
        raise ValueError("method dcsc_state brings its own arbiter: a copy of a PretrainedArbiter's")
    built_here = [name for name in METHOD_NAMES if name not in ("dcsc_frozen", "reddy", "dcsc_state")]
    raise ValueError(f"method must be one of {', '.join(built_here)}, got {method!r}")


def build_policy(
    machine_net: torch.nn.Module,
    arbiter: Arbiter,
    action_spec: TensorSpec,
    *,
    discrete: bool,
    num_samples: int,
    lam: float,
    delta2: float,
    tau_inv: float = 0.0,
    uncertainty_scale: float = 1.0,
    observation_size: int | None = None,
) -> SharedPolicyModule:
    """The shared policy of Eq. 14: the frozen pretrained machine under MC dropout, and ``arbiter``.

    ``discrete`` picks the machine's output (key probabilities or a continuous action);
    ``num_samples``, ``lam``, ``delta2``, ``tau_inv`` and ``uncertainty_scale`` are
    :class:`MCDropoutPolicy`'s (Eqs. 10-13). ``observation_size`` is the env's
    observation width: the LunarLander actor keeps only the first 8 of its 9 values, so
    without it a wider observation would be cut without a word.
    """
    from dcsc_torchrl.machine import MCDropoutPolicy
    from dcsc_torchrl.policy import SharedPolicyModule

    machine = MCDropoutPolicy(
        machine_net, output="probs" if discrete else "action", num_samples=num_samples, lam=lam, delta2=delta2,
        tau_inv=tau_inv, uncertainty_scale=uncertainty_scale, observation_size=observation_size,
    )
    return SharedPolicyModule(machine, arbiter, action_spec)
