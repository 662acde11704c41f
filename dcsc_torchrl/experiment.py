"""The paper's protocol (DESIGN §5) for one experiment cell: calibrate, collaborate, validate.

A *cell* is (task, operator preset, pretraining seed). Within it every method is the same
pipeline — batched env + operator transforms + :class:`SharedPolicyModule` — with a
different arbiter:

==========  ==================================================================
machine     :class:`MachineOnlyArbiter` (A2C / DDPG alone)
operator    :class:`HumanOnlyArbiter` (the operator alone)
hula        :class:`HULAArbiter` (threshold: 90th percentile of the machine's
            uncertainty during the operator-alone runs, unless set)
dcsc        :class:`ConfidenceArbiter`, theta and the critic updated online
            (Algorithm 1) during collaboration and validation
==========  ==================================================================

Each env of a batch is one scenario and plays exactly one recorded episode (its first);
envs that finish early keep running (their frames still feed DC-SC's online updates)
until every scenario of the batch is done.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import TensorSpec
from torchrl.envs import TransformedEnv
from torchrl.modules import ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators

from dcsc_torchrl.arbiters import (
    Arbiter,
    ConfidenceArbiter,
    HULAArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
)
from dcsc_torchrl.humans import SimulatedOperator, SimulatedPilot
from dcsc_torchrl.losses import ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.tasks import make_lunar_env, make_uav_env
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

METHODS = ("machine", "operator", "hula", "dcsc")
TRACE_KEYS = ("knowledge", "human_confidence", "machine_uncertainty", "machine_confidence",
              "confidence_ratio", "beta")
ACTION_DIMS = {"lunarlander": 1, "uav": 3}


def make_arbiter(method: str, task: str, *, theta_init: float, hula_threshold: float | None) -> Arbiter:
    """The arbiter that makes ``method`` out of the common pipeline."""
    dims = ACTION_DIMS[task]
    if method == "machine":
        return MachineOnlyArbiter(dims)
    if method == "operator":
        return HumanOnlyArbiter(dims)
    if method == "hula":
        if hula_threshold is None:
            raise ValueError("the HULA arbiter needs a threshold: calibrate it on the operator-alone runs")
        return HULAArbiter(hula_threshold, dims)
    if method == "dcsc":
        return ConfidenceArbiter(theta_init, dims)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def make_operator(task: str, preset: str) -> SimulatedPilot | SimulatedOperator:
    """The simulated operator of ``task`` with the traits of ``preset``."""
    if task == "lunarlander":
        return SimulatedPilot.from_preset(preset)
    if task == "uav":
        return SimulatedOperator.from_preset(preset)
    raise ValueError(f"task must be 'lunarlander' or 'uav', got {task!r}")


def make_env(task: str, cfg: DictConfig, preset: str, scenario_seeds: list[int], operator_seed: int) -> TransformedEnv:
    """A batch of scenarios (one per env) with the operator and its confidence as transforms."""
    conf = cfg.confidence
    transforms = [
        HumanOperatorTransform(make_operator(task, preset), seed=operator_seed),
        HumanConfidenceTransform(conf.p, conf.eta, conf.delta1, conf.K, conf.t_d, conf.k0, conf.mode),
    ]
    if task == "lunarlander":
        env = make_lunar_env(len(scenario_seeds), random_pad=True, max_steps=cfg.protocol.max_steps,
                             transforms=transforms)
        env.set_seed(scenario_seeds[0])  # env i plays the pad drawn from seed scenario_seeds[0] + i
        return env
    return make_uav_env(len(scenario_seeds), scenario_seeds=scenario_seeds, max_steps=cfg.protocol.max_steps,
                        transforms=transforms)


class OnlineLearner:
    """Algorithm 1's online updates of theta (Eq. 19) and the critic, once per collected batch.

    Discrete (LunarLander): :class:`ThetaLoss` — ``-sum_a pi_theta Q`` + the Q critic's TD
    loss. Continuous (UAV): TorchRL's ``DDPGLoss`` with the shared policy as actor and only
    theta trainable (its actor loss has the gradient of Eq. 19), the critic's TD loss
    keeping it adapting. Targets are soft-updated with ``SoftUpdate``.

    Args:
        policy: the DC-SC shared policy (its arbiter holds theta).
        critic: the pretrained critic network (``Q(s, .)`` or ``Q(s, a)``), trained on.
        theta_lr: alpha of Algorithm 1 (line 15).
        critic_lr: beta of Algorithm 1 (line 12).
        gamma: discount factor.
        tau: soft-update rate of the target critic.
    """

    def __init__(
        self, policy: SharedPolicyModule, critic: torch.nn.Module, *, theta_lr: float, critic_lr: float,
        gamma: float, tau: float,
    ) -> None:
        self.policy = policy
        theta = policy["arbiter"].theta
        if policy.discrete:
            self.loss = ThetaLoss(policy, TensorDictModule(critic, ["observation"], ["action_value"]), gamma=gamma)
            critic_params = list(self.loss.qvalue_network_params.values(True, True))
        else:
            self.loss = DDPGLoss(policy, ValueOperator(critic, in_keys=["observation", "action"]))
            self.loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
            critic_params = list(self.loss.value_network_params.values(True, True))
        self.targets = SoftUpdate(self.loss, tau=tau)
        self.theta_optim = torch.optim.SGD([theta], lr=theta_lr)
        self.critic_optim = torch.optim.Adam(critic_params, lr=critic_lr)
        self.history: list[dict[str, Any]] = []

    def __call__(self, batch: TensorDictBase) -> None:
        batch = batch.reshape(-1)
        if self.policy.discrete:
            out = self.loss(batch)
            loss_theta, loss_critic = out["loss_theta"], out["loss_qvalue"]
        else:
            loss_critic, _ = self.loss.loss_value(batch)
            loss_theta, _ = self.loss.loss_actor(batch)
        self.critic_optim.zero_grad()
        self.theta_optim.zero_grad()
        (loss_theta + loss_critic).backward()
        theta = self.policy["arbiter"].theta
        grad = theta.grad.detach().clone()
        self.critic_optim.step()
        self.theta_optim.step()
        self.targets.step()
        self.history.append({
            "update": len(self.history) + 1,
            "theta": theta.detach().tolist(),
            "theta_grad": grad.tolist(),
            "loss_theta": loss_theta.item(),
            "loss_critic": loss_critic.item(),
        })


@dataclass
class EpisodeBatch:
    """What :func:`run_scenarios` returns: one row per scenario, the trace of the first,
    and the machine's uncertainty over every recorded frame."""

    rows: list[dict[str, Any]]
    trace: list[dict[str, Any]] = field(default_factory=list)
    uncertainty: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _trace_rows(frames: TensorDictBase, task: str) -> list[dict[str, Any]]:
    """One row per frame: confidences, authority, the three actions (Figs. 3, 5, 6)."""
    rows = []
    for step in range(frames.shape[0]):
        frame = frames[step]
        row = {"step": step + 1, "reward": frame["next", "reward"].item()}
        row.update({key: frame[key].item() for key in TRACE_KEYS if key != "beta"})
        if task == "lunarlander":
            row["beta"] = frame["beta"].item()
            row["machine_action"] = int(frame["machine_probs"].argmax())
            row["operator_action"] = int(frame["human_action"].argmax())
            row["shared_action"] = int(frame["action"].argmax())
        else:
            dims = ("rho", "sigma", "tau")
            row.update({f"beta_{d}": v for d, v in zip(dims, frame["beta"].tolist(), strict=True)})
            for name, key in (("machine", "machine_action"), ("operator", "human_action"), ("shared", "action")):
                row.update({f"{name}_{d}": v for d, v in zip(dims, frame[key].tolist(), strict=True)})
            row.update({f"position_{a}": v for a, v in zip("xyz", frame["next", "position"].tolist(), strict=True)})
        rows.append(row)
    return rows


def run_scenarios(
    env: TransformedEnv,
    policy: SharedPolicyModule,
    task: str,
    *,
    rollout_length: int,
    update: Callable[[TensorDictBase], None] | None = None,
    trace: bool = False,
) -> EpisodeBatch:
    """Plays the first episode of every env (scenario) of ``env`` under ``policy``.

    Args:
        env: a batch of scenarios from :func:`make_env`.
        policy: the shared policy (any arbiter).
        task: ``"lunarlander"`` or ``"uav"`` (which info keys and trace columns exist).
        rollout_length: frames per env between two calls of ``update``.
        update: called on every collected batch ``[envs, rollout_length]`` (DC-SC's
            online learning); ``None`` for the fixed methods.
        trace: record every frame of scenario 0's episode.
    """
    n_envs = env.batch_size[0]
    collector = Collector(env, policy, frames_per_batch=n_envs * rollout_length, total_frames=-1,
                          auto_register_policy_transforms=False)
    active = torch.ones(n_envs, dtype=torch.bool)
    rows: list[dict[str, Any] | None] = [None] * n_envs
    traced: list[TensorDictBase] = []
    uncertainty: list[torch.Tensor] = []
    extra = ["success", "path_length"] if task == "uav" else ["success"]
    for batch in collector:
        done = batch["next", "done"].squeeze(-1)
        before_done = (done.long().cumsum(-1) - done.long()) == 0
        in_first = active.unsqueeze(-1) & before_done
        uncertainty.append(batch["machine_uncertainty"][in_first].reshape(-1))
        if trace and in_first[0].any():
            traced.append(batch[0][in_first[0]])
        for i in (active & done.any(-1)).nonzero().reshape(-1).tolist():
            t = int(done[i].nonzero()[0])
            nxt = batch[i, t]["next"]
            rows[i] = {"return": nxt["episode_reward"].item(), "steps": int(nxt["step_count"].item()),
                       **{key: nxt[key].item() for key in extra}}
        active &= ~done.any(-1)
        if update is not None:
            update(batch)
        if not active.any():
            break
    collector.shutdown()
    trace_rows = _trace_rows(torch.cat(traced), task) if traced else []
    return EpisodeBatch(rows, trace_rows, torch.cat(uncertainty).numpy())


def build_policy(
    machine_net: torch.nn.Module, arbiter: Arbiter, task: str, cfg: DictConfig, action_spec: TensorSpec
) -> SharedPolicyModule:
    """The shared policy of Eq. 14 over the frozen pretrained machine."""
    machine = MCDropoutPolicy(
        machine_net,
        output="probs" if task == "lunarlander" else "action",
        num_samples=cfg.machine.mc_samples,
        lam=cfg.confidence.lam,
        delta2=cfg.confidence.delta2,
        tau_inv=cfg.machine.tau_inv,
    )
    return SharedPolicyModule(machine, arbiter, action_spec)


def scenario_seeds(phase: str, cfg: DictConfig) -> list[int]:
    """The scenario seeds of a protocol phase: validation 0..49 (DESIGN §5), the rest apart."""
    protocol = cfg.protocol
    if phase == "validation":
        return list(range(protocol.validation_scenarios))
    if phase == "operator_alone":
        return list(range(10_000, 10_000 + protocol.operator_runs))
    if phase == "collaboration":
        return list(range(20_000, 20_000 + protocol.collaboration_runs))
    raise ValueError(f"unknown phase {phase!r}")


@dataclass
class CellResult:
    """One cell's output: episode rows (every phase), traces of scenario 0, theta's updates."""

    episodes: list[dict[str, Any]]
    traces: list[dict[str, Any]]
    theta: list[dict[str, Any]]
    hula_threshold: float


def run_cell(
    task: str,
    cfg: DictConfig,
    preset: str,
    pretrain_seed: int,
    machine_net: torch.nn.Module,
    critic_net: torch.nn.Module,
    *,
    methods: tuple[str, ...] = METHODS,
    trace: bool = False,
) -> CellResult:
    """The protocol of DESIGN §5 for one (task, operator preset, pretraining seed).

    1. the operator alone on ``protocol.operator_runs`` scenarios (calibrates HULA's
       threshold: the 90th percentile of the machine's uncertainty seen, unless
       ``arbiter.hula_threshold`` is set);
    2. DC-SC collaborating on ``protocol.collaboration_runs`` scenarios, theta and the
       critic learning online (Algorithm 1);
    3. every method on the validation scenarios (seeds 0..49, groups of
       ``protocol.group_size``); DC-SC keeps learning online.

    The cell seeds torch itself (from ``cfg.seed``, the pretraining seed and the
    phase), so its rows do not depend on which cells ran before it.
    """
    import copy

    base = {"task": task, "operator": preset, "pretrain_seed": pretrain_seed}
    spec_env = make_env(task, cfg, preset, [0], operator_seed=0)
    action_spec = spec_env.full_action_spec["action"]
    spec_env.close()
    rollout = cfg.online.rollout_length
    episodes: list[dict[str, Any]] = []
    traces: list[dict[str, Any]] = []

    def play(
        phase: str,
        method: str,
        policy: SharedPolicyModule,
        update: OnlineLearner | None = None,
        record_trace: bool = False,
    ) -> EpisodeBatch:
        seeds = scenario_seeds(phase, cfg)
        torch.manual_seed(int(cfg.seed) * 1_000_003 + pretrain_seed * 1009 + METHODS.index(method) * 17
                          + ("operator_alone", "collaboration", "validation").index(phase))
        env = make_env(task, cfg, preset, seeds, operator_seed=int(cfg.seed) + pretrain_seed * 7919 + seeds[0])
        result = run_scenarios(env, policy, task, rollout_length=rollout, update=update, trace=record_trace)
        env.close()
        for index, (seed, row) in enumerate(zip(seeds, result.rows, strict=True)):
            group = index // cfg.protocol.group_size + 1 if phase == "validation" else 0
            episodes.append({**base, "method": method, "phase": phase, "group": group, "seed": seed,
                             "path_length": float("nan"), **row, "hula_threshold": threshold})
        traces.extend({**base, "method": method, "phase": phase, "seed": seeds[0], **r} for r in result.trace)
        return result

    def policy_for(method: str, threshold: float | None = None) -> SharedPolicyModule:
        arbiter = make_arbiter(method, task, theta_init=cfg.arbiter.theta_init, hula_threshold=threshold)
        return build_policy(machine_net, arbiter, task, cfg, action_spec)

    threshold = cfg.arbiter.hula_threshold
    alone = play("operator_alone", "operator", policy_for("operator"))
    if threshold is None:
        threshold = float(np.quantile(alone.uncertainty, 0.9))
        for row in episodes:
            row["hula_threshold"] = threshold

    dcsc = policy_for("dcsc")
    learner = OnlineLearner(dcsc, copy.deepcopy(critic_net), theta_lr=cfg.online.theta_lr,
                            critic_lr=cfg.online.critic_lr, gamma=cfg.online.gamma, tau=cfg.online.tau)
    if "dcsc" in methods:
        play("collaboration", "dcsc", dcsc, update=learner)
    collab_updates = len(learner.history)
    for method in methods:
        if method == "dcsc":
            play("validation", "dcsc", dcsc, update=learner, record_trace=trace)
        else:
            play("validation", method, policy_for(method, threshold), record_trace=trace)
    theta = [{**base, "phase": "collaboration" if h["update"] <= collab_updates else "validation", **h}
             for h in learner.history]
    return CellResult(episodes, traces, theta, threshold)
