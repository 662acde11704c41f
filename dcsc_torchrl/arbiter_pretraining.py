"""The state-dependent arbiter pretrained in simulation, before a cell meets its operator.

Every peer that lifts an imperfect pilot far above both partners trains its assistant against
surrogate pilots first. :func:`pretrain_state_arbiter` does that for
:class:`~dcsc_torchrl.state_arbiter.StateDependentArbiter`: next to the cell's machine, each
operator of a pool flies development scenarios with the shared policy, the arbiter and a
value critic of the shared policy learning from every batch
(:class:`~dcsc_torchrl.online.PolicyGradientLearner`), the pool's operators in turn; or, the
default, the pool flies constant blends and the arbiter learns against a critic of the
authority split fitted on their returns (:class:`~dcsc_torchrl.online.AuthorityOnlineLearner`).
The runs are the protocol's own (:class:`~dcsc_torchrl.protocol.ProtocolCell`): the same envs,
confidences and machine, its uncertainty unit calibrated on each operator's own runs alone
first. The evaluated operator is never in the pool: the cell refuses an arbiter whose pool
holds it
(:meth:`~dcsc_torchrl.state_arbiter.PretrainedArbiter.check_evaluated_next_to`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase

from dcsc_torchrl.episodes import EpisodeBatch, concat_runs
from dcsc_torchrl.machine import machine_mean_key
from dcsc_torchrl.networks import machine_fingerprint
from dcsc_torchrl.online import AuthorityOnlineLearner, PolicyGradientLearner
from dcsc_torchrl.protocol import (
    ArbiterSettings,
    MachineSettings,
    ProtocolCell,
    ProtocolSettings,
    run_seed,
)
from dcsc_torchrl.state_arbiter import (
    PretrainedArbiter,
    StateDependentArbiter,
    authority_fit_settings,
    checked_learner_settings,
    state_arbiter_critic,
)
from dcsc_torchrl.task import Task
from dcsc_torchrl.transforms import HumanOperator


def pretrain_state_arbiter(
    task: Task,
    machine_net: torch.nn.Module,
    pool: Mapping[str, HumanOperator],
    *,
    human: Mapping[str, Any],
    machine: MachineSettings,
    arbiter: ArbiterSettings,
    protocol: ProtocolSettings,
    calibration_runs: int,
    first_seed: int,
    hidden: Sequence[int],
    value_hidden: Sequence[int],
    spread: float,
    learner: Mapping[str, Any],
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> tuple[PretrainedArbiter, list[dict[str, Any]], TensorDictBase]:
    """Pretrains a state-dependent arbiter next to ``machine_net`` against the operators of ``pool``.

    Each operator first flies ``calibration_runs`` scenarios alone (the machine's uncertainty
    unit, as a cell calibrates it). Then, by ``learner["algorithm"]``:

    - ``"authority"``: each operator flies ``blend_scenarios`` fresh scenarios at every constant
      beta of ``betas`` (the protocol's shared action); a critic of the authority split
      ``Q(s, beta)`` (:func:`~dcsc_torchrl.networks.authority_critic`, not separable: its best
      beta may depend on the state) is fitted on their recorded returns (``critic_updates``
      steps), then the arbiter follows ``-Q(s, beta_psi(frame))`` on the same frames
      (``arbiter_updates`` steps; :class:`~dcsc_torchrl.losses.AuthorityThetaLoss`, the critic held);
    - ``"policy_gradient"``: ``rounds`` times, each operator in turn flies ``scenarios`` fresh
      scenarios with the shared policy drawn from Eq. 14's mixture (on-policy), one
      :class:`~dcsc_torchrl.online.PolicyGradientLearner` update per ``segment_length`` frames.

    Scenario seeds start at ``first_seed`` and never repeat (keep them off the validation seeds).

    Args:
        task: the task (``policy_gradient``: a discrete one).
        machine_net: the cell's pretrained actor (frozen).
        pool: the operators by name (never the one a cell will evaluate).
        human, machine, arbiter, protocol: the protocol's settings (``arbiter.form`` and its
            start give the arbiter's form, bias and gain).
        calibration_runs: scenarios each operator flies alone first.
        first_seed: the first development scenario.
        hidden, value_hidden: the arbiter's and its critic's hidden widths.
        spread: the largest move of theta_t (:class:`StateDependentArbiter`).
        learner: ``algorithm`` and its settings (:data:`~dcsc_torchrl.state_arbiter.LEARNER_SETTINGS`
            of that update); they travel with the arbiter to the cell, which fine-tunes with them.
        seed: torch's seed for the networks' initialisation and each run.
        progress: called with a short line as each run starts.

    Returns:
        The pretrained arbiter, one row per run (operator, round or beta, frames, success and
        mean beta of its first episodes) and the frames the arbiter learned from last, each
        with the pretrained arbiter's beta (:func:`~dcsc_torchrl.episodes.concat_runs`).
    """
    if not pool:
        raise ValueError("the pretraining pool holds no operator")
    settings = checked_learner_settings(learner)
    check_algorithm_for(task, settings["algorithm"])
    if settings["algorithm"] == "policy_gradient":
        protocol = dataclasses.replace(protocol, shared_action="sample")
    cells = {name: ProtocolCell(task, operator, machine_net, base={}, pretrain_seed=seed, human=human,
                                machine=machine, arbiter=arbiter, online={}, protocol=protocol, progress=progress)
             for name, operator in pool.items()}
    seeds = SeedBlocks(first_seed)
    for name, cell in cells.items():
        cell.calibrate_unit(cell.play("operator_alone", "operator", seeds.take(calibration_runs), cell.policy("operator"),
                                      torch_seed=run_seed(seed, 0, "arbiter_calibration", name)))
    torch.manual_seed(seed)
    start = arbiter.start("dcsc_centred" if arbiter.form == "centred" else "dcsc")
    first = next(iter(cells.values()))
    shared = StateDependentArbiter(first.observation_size, first.action_spec.shape[-1], task.action_dims,
                                   form=arbiter.form, theta_init=start["theta_init"], gain=start["gain"],
                                   hidden=hidden, spread=spread,
                                   machine_key=machine_mean_key(task.discrete))
    critic = state_arbiter_critic(settings["algorithm"], shared, value_hidden)
    pretrained = PretrainedArbiter(shared, critic, settings, tuple(pool), machine_fingerprint(machine_net))
    policies = {name: cell.policy("dcsc_state", shared) for name, cell in cells.items()}
    update = pretrained.learner(next(iter(policies.values())), copy_critic=False)
    if settings["algorithm"] == "authority":
        rows, frames = _from_constant_blends(cells, seeds, settings, update, seed)
    else:
        rows, frames = _by_policy_gradient(cells, policies, seeds, settings, update, seed)
    with torch.no_grad():
        shared(frames)  # the pretrained arbiter's beta on them, for the figure
    return pretrained, rows, frames


def check_algorithm_for(task: Task, algorithm: str) -> None:
    """Refuses ``policy_gradient`` on a continuous task (one line): it learns on Eq. 14's mixture
    of keys, which a continuous task does not draw from."""
    if algorithm == "policy_gradient" and not task.discrete:
        raise ValueError(f"state.algorithm policy_gradient learns on Eq. 14's mixture of keys, which task "
                         f"{task.name} does not draw from (its actions are blended): use authority")


class SeedBlocks:
    """Consecutive blocks of development scenario seeds from ``first``, never one twice."""

    def __init__(self, first: int) -> None:
        self.next = int(first)

    def take(self, count: int) -> range:
        block = range(self.next, self.next + int(count))
        self.next += int(count)
        return block


def _success_row(result: EpisodeBatch, **columns: Any) -> dict[str, Any]:
    return {**columns, "success": sum(bool(row["success"]) for row in result.rows) / len(result.rows),
            "mean_beta": sum(row["mean_beta"] for row in result.rows) / len(result.rows)}


def _from_constant_blends(cells: Mapping[str, ProtocolCell], seeds: SeedBlocks, settings: Mapping[str, Any],
                          update: AuthorityOnlineLearner, seed: int) -> tuple[list[dict[str, Any]], TensorDictBase]:
    """The authority update: the pool at constant betas, ``Q(s, beta)`` fitted on their returns,
    then the arbiter against it (the critic held)."""
    rows, runs = [], []
    for name, cell in cells.items():
        for beta in settings["betas"]:
            block = seeds.take(settings["blend_scenarios"])
            result = cell.play("arbiter_pretraining", f"constant/{beta}", block,
                               cell.policy("constant", constant_beta=beta),
                               torch_seed=run_seed(seed, 0, "arbiter_pretraining", f"{name}/{beta}"))
            runs.append(result.frames)
            rows.append(_success_row(result, operator=name, beta=float(beta), first_seed=block[0],
                                     scenarios=len(block), frames=result.frames.numel()))
    frames = concat_runs(*runs)
    update.fit(frames, **authority_fit_settings(settings), seed=seed)
    return rows, frames


def _by_policy_gradient(cells: Mapping[str, ProtocolCell], policies: Mapping[str, Any], seeds: SeedBlocks,
                        settings: Mapping[str, Any], update: PolicyGradientLearner,
                        seed: int) -> tuple[list[dict[str, Any]], TensorDictBase]:
    """The policy-gradient update: the pool in turn, the shared policy drawn from the mixture."""
    rows: list[dict[str, Any]] = []
    last_round: list[TensorDictBase] = []
    for round_index in range(settings["rounds"]):
        last_round = []
        for name, cell in cells.items():
            block = seeds.take(settings["scenarios"])
            before = len(update.history)
            result = cell.play("arbiter_pretraining", "dcsc_state", block, policies[name], update=update,
                               torch_seed=run_seed(seed, round_index, "arbiter_pretraining", name))
            last_round.append(result.frames)
            rows.append(_success_row(result, operator=name, round=round_index, first_seed=block[0],
                                     scenarios=len(block),
                                     frames=(len(update.history) - before) * len(block) * update.segment_length))
    return rows, concat_runs(*last_round)
