"""The state-dependent arbiter pretrained in simulation, before a cell meets its operator.

Every peer that lifts an imperfect pilot far above both partners trains its assistant against
surrogate pilots first. :func:`pretrain_state_arbiter` does that for
:class:`~dcsc_torchrl.state_arbiter.StateDependentArbiter`: next to the cell's machine, each
operator of a pool flies development scenarios with the shared policy, the arbiter and a
value critic of the shared policy learning from every batch
(:class:`~dcsc_torchrl.online.PolicyGradientLearner`), the pool's operators in turn. The runs
are the protocol's own (:class:`~dcsc_torchrl.protocol.ProtocolCell`): the same envs, confidences
and machine, its uncertainty unit calibrated on each operator's own runs alone first, the
shared action drawn from Eq. 14's mixture (on-policy). The evaluated operator is never in the
pool: the cell refuses an arbiter whose pool holds it
(:meth:`~dcsc_torchrl.state_arbiter.PretrainedArbiter.check_evaluated_next_to`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase

from dcsc_torchrl.episodes import concat_runs
from dcsc_torchrl.online import PolicyGradientLearner
from dcsc_torchrl.protocol import (
    ArbiterSettings,
    MachineSettings,
    ProtocolCell,
    ProtocolSettings,
    run_seed,
)
from dcsc_torchrl.state_arbiter import (
    LEARNER_SETTINGS,
    PretrainedArbiter,
    StateDependentArbiter,
    machine_fingerprint,
    state_value_network,
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
    rounds: int,
    scenarios: int,
    calibration_runs: int,
    first_seed: int,
    hidden: Sequence[int],
    value_hidden: Sequence[int],
    spread: float,
    learner: Mapping[str, float],
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> tuple[PretrainedArbiter, list[dict[str, Any]], TensorDictBase]:
    """Pretrains a state-dependent arbiter next to ``machine_net`` against the operators of ``pool``.

    Each operator first flies ``calibration_runs`` scenarios alone (the machine's uncertainty
    unit, as a cell calibrates it); then, ``rounds`` times, each operator in turn flies
    ``scenarios`` fresh development scenarios with the shared policy, one learner update per
    collected batch. Scenario seeds start at ``first_seed`` and never repeat (keep them off
    the validation seeds).

    Args:
        task: a discrete task.
        machine_net: the cell's pretrained actor (frozen).
        pool: the operators by name (never the one a cell will evaluate).
        human, machine, arbiter, protocol: the protocol's settings (``arbiter.form`` and its
            start give the arbiter's form, bias and gain; ``protocol.shared_action`` is
            replaced by ``sample``: the policy gradient is on-policy).
        rounds: plays per operator.
        scenarios: scenarios per play (one env each).
        calibration_runs: scenarios each operator flies alone first.
        first_seed: the first development scenario.
        hidden, value_hidden: the arbiter's and the value critic's hidden widths.
        spread: the largest move of theta_t (:class:`StateDependentArbiter`).
        learner: :data:`~dcsc_torchrl.state_arbiter.LEARNER_SETTINGS`.
        seed: torch's seed for the networks' initialisation and each play.
        progress: called with a short line as each play starts.

    Returns:
        The pretrained arbiter, one row per play (operator, round, frames learned from, updates
        so far, success and mean beta of its first episodes) and the last round's first
        episodes' frames (:func:`~dcsc_torchrl.episodes.concat_runs`).
    """
    if not task.discrete:
        raise ValueError(f"task {task.name}: the state-dependent arbiter learns by A2C on Eq. 14's mixture of "
                         "keys; a continuous task has no such mixture")
    if not pool:
        raise ValueError("the pretraining pool holds no operator")
    sampling = dataclasses.replace(protocol, shared_action="sample")
    cells = {name: ProtocolCell(task, operator, machine_net, base={}, pretrain_seed=seed, human=human,
                                machine=machine, arbiter=arbiter, online={}, protocol=sampling, progress=progress)
             for name, operator in pool.items()}
    next_seed = first_seed
    for name, cell in cells.items():
        seeds = range(next_seed, next_seed + calibration_runs)
        next_seed += calibration_runs
        cell.calibrate_unit(cell.play("operator_alone", "operator", seeds, cell.policy("operator"),
                                      torch_seed=run_seed(seed, 0, "arbiter_calibration", name)))
    torch.manual_seed(seed)
    start = arbiter.start("dcsc_centred" if arbiter.form == "centred" else "dcsc")
    first = next(iter(cells.values()))
    shared = StateDependentArbiter(first.observation_size, first.action_spec.shape[-1], task.action_dims, form=arbiter.form, theta_init=start["theta_init"],
                                   gain=start["gain"], hidden=hidden, spread=spread)
    value_net = state_value_network(shared.observation_size, value_hidden)
    policies = {name: cell.policy("dcsc_state", shared) for name, cell in cells.items()}
    settings = {key: int(learner[key]) if key == "segment_length" else float(learner[key]) for key in LEARNER_SETTINGS}
    update = PolicyGradientLearner(next(iter(policies.values())), value_net, **settings)
    rows: list[dict[str, Any]] = []
    last_round: list[TensorDictBase] = []
    for round_index in range(rounds):
        last_round = []
        for name, cell in cells.items():
            seeds = range(next_seed, next_seed + scenarios)
            next_seed += scenarios
            before = len(update.history)
            result = cell.play("arbiter_pretraining", "dcsc_state", seeds, policies[name], update=update,
                               torch_seed=run_seed(seed, round_index, "arbiter_pretraining", name))
            last_round.append(result.frames)
            rows.append({"round": round_index, "operator": name, "first_seed": seeds[0], "scenarios": scenarios,
                         "frames": (len(update.history) - before) * scenarios * update.segment_length,
                         "updates": len(update.history),
                         "success": sum(bool(row["success"]) for row in result.rows) / len(result.rows),
                         "mean_beta": sum(row["mean_beta"] for row in result.rows) / len(result.rows)})
    pretrained = PretrainedArbiter(shared, value_net, settings, tuple(pool), machine_fingerprint(machine_net))
    return pretrained, rows, concat_runs(*last_round)
