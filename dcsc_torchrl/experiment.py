"""The paper's protocol for one experiment cell: calibrate, collaborate, validate.

A *cell* is (task, operator preset, pretraining seed). Within it every method is the same
pipeline — batched env + operator transforms + :class:`SharedPolicyModule` — with a
different arbiter:

============  ================================================================
machine       :class:`MachineOnlyArbiter` (A2C / DDPG alone)
operator      :class:`HumanOnlyArbiter` (the operator alone)
hula          :class:`HULAArbiter` (threshold: 90th percentile of the machine's
              uncertainty during the operator-alone runs, unless set)
dcsc          :class:`ConfidenceArbiter` (Eq. 15 as printed), theta and the critic
              updated online (Algorithm 1) during collaboration and validation
dcsc_centred  :class:`CentredConfidenceArbiter`, learning the same way
dcsc_frozen   the ``arbiter.form`` arbiter fed its confidences' collaboration means
              (:class:`FrozenConfidenceArbiter`): what the confidences add
constant      :class:`ConstantArbiter`, once per beta of ``arbiter.constant_betas``
              (the best of them is the oracle reference of the report)
============  ================================================================

Each env of a batch is one scenario and plays exactly one recorded episode (its first);
envs that finish early keep running (their frames still feed DC-SC's online updates)
until every scenario of the batch is done. docs/architecture.md gives the reasons.
"""

from __future__ import annotations

import copy
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

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
    CentredConfidenceArbiter,
    ConfidenceArbiter,
    ConstantArbiter,
    FrozenConfidenceArbiter,
    HULAArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
)
from dcsc_torchrl.confidence import machine_confidence
from dcsc_torchrl.humans import SimulatedOperator, SimulatedPilot
from dcsc_torchrl.losses import ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy, calibrated_uncertainty_scale
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.tasks import make_lunar_env, make_uav_env
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

METHODS = ("machine", "operator", "hula", "dcsc", "dcsc_centred", "dcsc_frozen", "constant")
"""Every method of the protocol. ``dcsc``: Eq. 15 as printed; ``dcsc_centred``: the centred
arbiter; ``dcsc_frozen``: the default learned form fed its confidences' collaboration means
(what the confidences add); ``constant``: a sweep of fixed betas (the best is an oracle)."""
LEARNED_FORMS = {"dcsc": "paper", "dcsc_centred": "centred"}
"""The learned arbiters and their form: each collaborates, then validates, learning online."""
TRACE_KEYS = ("knowledge", "human_confidence", "machine_uncertainty", "machine_confidence",
              "confidence_ratio", "beta")
ACTION_DIMS = {"lunarlander": 1, "uav": 3}


def make_arbiter(
    method: str,
    task: str,
    *,
    theta_init: float,
    hula_threshold: float | None,
    gain: float = 3.0,
    constant_beta: float | None = None,
) -> Arbiter:
    """The arbiter that makes ``method`` out of the common pipeline.

    ``dcsc`` is :class:`ConfidenceArbiter` (Eq. 15), ``dcsc_centred``
    :class:`CentredConfidenceArbiter` (with ``gain``), ``constant`` a
    :class:`ConstantArbiter` of ``constant_beta``. ``dcsc_frozen`` is built by the
    protocol from a learned arbiter (:class:`FrozenConfidenceArbiter`).
    """
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
    if method == "dcsc_centred":
        return CentredConfidenceArbiter(theta_init, dims, gain=gain)
    if method == "constant":
        if constant_beta is None:
            raise ValueError("the constant arbiter needs constant_beta")
        return ConstantArbiter(constant_beta, dims)
    raise ValueError(f"method must be one of {METHODS[:-2] + ('constant',)}, got {method!r}")


def make_operator(task: str, preset: str) -> SimulatedPilot | SimulatedOperator:
    """The simulated operator of ``task`` with the traits of ``preset``."""
    if task == "lunarlander":
        return SimulatedPilot.from_preset(preset)
    if task == "uav":
        return SimulatedOperator.from_preset(preset)
    raise ValueError(f"task must be 'lunarlander' or 'uav', got {task!r}")


def make_env(task: str, cfg: DictConfig, preset: str, scenario_seeds: list[int], operator_seed: int) -> TransformedEnv:
    """A batch of scenarios (one per env) with the operator and its confidence as transforms."""
    transforms = [
        HumanOperatorTransform(make_operator(task, preset), seed=operator_seed),
        HumanConfidenceTransform(**cfg.human),
    ]
    if task == "lunarlander":
        env = make_lunar_env(len(scenario_seeds), random_pad=True, max_steps=cfg.protocol.max_steps,
                             transforms=transforms)
        env.set_seed(scenario_seeds[0])  # env i plays the pad drawn from seed scenario_seeds[0] + i
        return env
    return make_uav_env(len(scenario_seeds), scenario_seeds=scenario_seeds, max_steps=cfg.protocol.max_steps,
                        transforms=transforms)


THETA_OPTIMIZERS = {"sgd": torch.optim.SGD, "adam": torch.optim.Adam}


class OnlineLearner:
    """Algorithm 1's online updates of theta (Eq. 19) and the critic, once per collected batch.

    Discrete (LunarLander): :class:`ThetaLoss` — ``-sum_a pi_theta Q`` + the Q critic's TD
    loss. Continuous (UAV): TorchRL's ``DDPGLoss`` with the shared policy as actor and only
    theta trainable (its actor loss has the gradient of Eq. 19), the critic's TD loss
    keeping it adapting. Targets are soft-updated with ``SoftUpdate``. Each collected batch
    gives ``updates_per_batch`` gradient steps of both (every step on the whole batch).

    Args:
        policy: the DC-SC shared policy (its arbiter holds theta).
        critic: the pretrained critic network (``Q(s, .)`` or ``Q(s, a)``), trained on.
        theta_lr: alpha of Algorithm 1 (line 15).
        critic_lr: beta of Algorithm 1 (line 12).
        gamma: discount factor.
        tau: soft-update rate of the target critic.
        updates_per_batch: gradient steps per collected batch (>= 1).
        theta_optimizer: ``"sgd"`` (Algorithm 1 line 15 as printed: ``theta += alpha
            grad J``) or ``"adam"`` (the same ascent direction, steps of about ``alpha`` in
            theta's own units whatever the scale of Q: one step size serves both tasks).
    """

    def __init__(
        self, policy: SharedPolicyModule, critic: torch.nn.Module, *, theta_lr: float, critic_lr: float,
        gamma: float, tau: float, updates_per_batch: int = 1, theta_optimizer: str = "sgd",
    ) -> None:
        if int(updates_per_batch) != updates_per_batch or updates_per_batch < 1:
            raise ValueError(f"updates_per_batch must be an integer >= 1, got {updates_per_batch!r}")
        self.policy = policy
        self.critic = critic
        self.gamma = float(gamma)
        self.updates_per_batch = int(updates_per_batch)
        theta = policy["arbiter"].theta
        if policy.discrete:
            self.loss = ThetaLoss(policy, TensorDictModule(critic, ["observation"], ["action_value"]), gamma=gamma)
            critic_params = list(self.loss.qvalue_network_params.values(True, True))
        else:
            self.loss = DDPGLoss(policy, ValueOperator(critic, in_keys=["observation", "action"]))
            self.loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
            critic_params = list(self.loss.value_network_params.values(True, True))
        self.targets = SoftUpdate(self.loss, tau=tau)
        if theta_optimizer not in THETA_OPTIMIZERS:
            raise ValueError(f"theta_optimizer must be one of {sorted(THETA_OPTIMIZERS)}, got {theta_optimizer!r}")
        self.theta_optim = THETA_OPTIMIZERS[theta_optimizer]([theta], lr=theta_lr)
        self.critic_optim = torch.optim.Adam(critic_params, lr=critic_lr)
        self.history: list[dict[str, Any]] = []

    def critic_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """The critic's TD loss on a flat batch (Algorithm 1, lines 9-12)."""
        if self.policy.discrete:
            return self.loss.loss_qvalue(batch)[0]
        return self.loss.loss_value(batch)[0]

    def theta_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """The loss whose theta-gradient is minus Eq. 19, on a flat batch."""
        if self.policy.discrete:
            return self.loss.loss_theta(batch)[0]
        return self.loss.loss_actor(batch)[0]

    def warm_up(self, frames: TensorDictBase, *, updates: int, batch_size: int, lr: float, seed: int) -> float:
        """Fits the critic alone on recorded transitions (the operator-alone runs), theta untouched.

        The pretrained critic has never seen the task's target (the LunarLander machine is
        pretrained on the centred pad); ``updates`` TD steps (Adam at ``lr``) on minibatches
        of ``batch_size`` frames drawn (with a generator seeded by ``seed``) from ``frames``
        give it a start on the operator's transitions before theta learns from it.
        Returns the last minibatch loss (``nan`` with no updates).
        """
        frames = frames.reshape(-1)
        generator = torch.Generator().manual_seed(seed)
        optim = torch.optim.Adam(self.critic_optim.param_groups[0]["params"], lr=lr)
        loss = torch.tensor(float("nan"))
        for _ in range(updates):
            index = torch.randint(frames.shape[0], (min(batch_size, frames.shape[0]),), generator=generator)
            loss = self.critic_loss(frames[index])
            optim.zero_grad()
            loss.backward()
            optim.step()
            self.targets.step()
        return loss.item()

    def fit_returns(self, frames: TensorDictBase, *, updates: int, batch_size: int, lr: float, seed: int) -> float:
        """Fits the critic's ``Q(s, a_taken)`` to the observed discounted return-to-go (Monte Carlo).

        The alternative warm-up to :meth:`warm_up`: a TD target propagates an outcome
        back one step per update, so after a short warm-up the critic still ranks
        actions mostly by their immediate reward (a key that burns fuel looks worse than
        one that does not); the return of the recorded episode carries its outcome (the
        landing or the crash) to every frame at once. ``frames`` must come from
        :func:`run_scenarios` (first episodes, with ``env_index`` / ``frame_index``).
        """
        frames = frames.reshape(-1)
        target = returns_to_go(frames, self.gamma)
        generator = torch.Generator().manual_seed(seed)
        optim = torch.optim.Adam(self.critic_optim.param_groups[0]["params"], lr=lr)
        loss = torch.tensor(float("nan"))
        for _ in range(updates):
            index = torch.randint(frames.shape[0], (min(batch_size, frames.shape[0]),), generator=generator)
            loss = (self.taken_value(frames[index]) - target[index]).pow(2).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
            self.targets.step()
        return loss.item()

    def taken_value(self, frames: TensorDictBase) -> torch.Tensor:
        """The critic's value of the action taken on each frame of a flat batch, ``[N]``."""
        params = self.loss.qvalue_network_params if self.policy.discrete else self.loss.value_network_params
        if self.policy.discrete:
            q = self.loss.action_values(frames, params)
            return (q * frames["action"].to(q.dtype)).sum(-1)
        with params.to_module(self.loss.value_network):
            return self.loss.value_network(frames.select("observation", "action").copy())["state_action_value"].reshape(-1)

    def action_gap(self, frames: TensorDictBase) -> torch.Tensor:
        """``Q(s, a_machine) - Q(s, a_operator)`` per frame under the current critic.

        Discrete: the machine's action is its most likely key. Positive where the critic
        prefers the machine's action: how the protocol checks that low-``b_m`` frames are
        frames where the machine's action is worse.
        """
        frames = frames.reshape(-1)
        with torch.no_grad():
            if self.policy.discrete:
                q = self.critic(frames["observation"])
                machine = q.gather(-1, frames["machine_probs"].argmax(-1, keepdim=True))
                human = q.gather(-1, frames["human_action"].argmax(-1, keepdim=True))
                return (machine - human).reshape(-1)
            obs = frames["observation"]
            gap = self.critic(obs, frames["machine_action"]) - self.critic(obs, frames["human_action"].float())
            return gap.reshape(-1)

    def __call__(self, batch: TensorDictBase) -> None:
        batch = batch.reshape(-1)
        theta = self.policy["arbiter"].theta
        for _ in range(self.updates_per_batch):
            loss_critic = self.critic_loss(batch)
            loss_theta = self.theta_loss(batch)
            self.critic_optim.zero_grad()
            self.theta_optim.zero_grad()
            (loss_theta + loss_critic).backward()
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


def returns_to_go(frames: TensorDictBase, gamma: float) -> torch.Tensor:
    """``G_t = sum_k gamma^k r_{t+k}`` to the end of each env's recorded episode, per frame ``[N]``.

    ``frames`` is :attr:`EpisodeBatch.frames`: each env's first episode, frames tagged with
    ``env_index`` and ``frame_index``.
    """
    reward = frames["next", "reward"].reshape(-1).double()
    env, step = frames["env_index"].reshape(-1), frames["frame_index"].reshape(-1)
    out = torch.zeros_like(reward)
    for e in env.unique().tolist():
        rows = (env == e).nonzero().reshape(-1)
        rows = rows[step[rows].argsort()]
        acc = 0.0
        for row in reversed(rows.tolist()):
            acc = reward[row].item() + gamma * acc
            out[row] = acc
    return out.to(torch.get_default_dtype())


def make_online_learner(policy: SharedPolicyModule, critic: torch.nn.Module, online: Any) -> OnlineLearner:
    """Algorithm 1's learner with the settings of a config's ``online:`` group (the
    protocol's learned arbiters and ``dcsc play`` alike)."""
    return OnlineLearner(policy, critic, theta_lr=online.theta_lr, critic_lr=online.critic_lr, gamma=online.gamma,
                         tau=online.tau, updates_per_batch=online.updates_per_batch,
                         theta_optimizer=online.theta_optimizer)


@dataclass
class EpisodeBatch:
    """What :func:`run_scenarios` returns: one row per scenario, the trace of the first,
    and every recorded frame (the first episode of each env; only the keys the protocol
    reads afterwards)."""

    rows: list[dict[str, Any]]
    trace: list[dict[str, Any]] = field(default_factory=list)
    frames: TensorDictBase | None = None

    @property
    def uncertainty(self) -> torch.Tensor:
        """The machine's uncertainty ``c_t`` over the recorded frames."""
        return self.frames["machine_uncertainty"].reshape(-1)


FRAME_KEYS = ("observation", "action", "machine_probs", "machine_action", "machine_uncertainty",
              "machine_confidence", "human_confidence", "human_action", "confidence_ratio", "beta")


def _trace_rows(frames: TensorDictBase, task: str) -> list[dict[str, Any]]:
    """One row per frame: confidences, authority, the three actions (Figs. 3, 5, 6)."""
    rows = []
    for step in range(frames.shape[0]):
        frame = frames[step]
        row = {"step": step + 1, "reward": frame["next", "reward"].item(), "human_rt": frame["human_rt"].item()}
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
    beta_sum, frame_count = torch.zeros(n_envs), torch.zeros(n_envs)
    traced: list[TensorDictBase] = []
    frames: list[TensorDictBase] = []
    extra = ["success", "path_length"] if task == "uav" else ["success"]
    keys = [*FRAME_KEYS, *(("next", key) for key in (*FRAME_KEYS, "reward", "done", "terminated"))]
    for batch in collector:
        done = batch["next", "done"].squeeze(-1)
        before_done = (done.long().cumsum(-1) - done.long()) == 0
        in_first = active.unsqueeze(-1) & before_done
        selected = batch.select(*keys, strict=False)
        selected["env_index"] = torch.arange(n_envs).unsqueeze(-1).expand(done.shape)
        selected["frame_index"] = (len(frames) * rollout_length + torch.arange(done.shape[-1])).expand(done.shape)
        frames.append(selected[in_first])
        beta_sum += (batch["beta"].detach().mean(-1) * in_first).sum(-1)
        frame_count += in_first.sum(-1)
        if trace and in_first[0].any():
            traced.append(batch[0][in_first[0]])
        for i in (active & done.any(-1)).nonzero().reshape(-1).tolist():
            t = int(done[i].nonzero()[0])
            nxt = batch[i, t]["next"]
            rows[i] = {"return": nxt["episode_reward"].item(), "steps": int(nxt["step_count"].item()),
                       **{key: nxt[key].item() for key in extra},
                       "mean_beta": (beta_sum[i] / frame_count[i]).item()}
        active &= ~done.any(-1)
        if update is not None:
            update(batch)
        if not active.any():
            break
    collector.shutdown()
    trace_rows = _trace_rows(torch.cat(traced), task) if traced else []
    return EpisodeBatch(rows, trace_rows, torch.cat(frames))


def build_policy(
    machine_net: torch.nn.Module,
    arbiter: Arbiter,
    task: str,
    cfg: DictConfig,
    action_spec: TensorSpec,
    *,
    uncertainty_scale: float = 1.0,
    observation_size: int | None = None,
) -> SharedPolicyModule:
    """The shared policy of Eq. 14 over the frozen pretrained machine.

    ``observation_size`` is the env's observation width (9 on both tasks): the LunarLander
    actor keeps only the first 8 values, so without it a wider observation would be cut
    without a word.
    """
    machine = MCDropoutPolicy(
        machine_net,
        output="probs" if task == "lunarlander" else "action",
        num_samples=cfg.machine.num_samples,
        lam=cfg.machine.lam,
        delta2=cfg.machine.delta2,
        tau_inv=cfg.machine.tau_inv,
        uncertainty_scale=uncertainty_scale,
        observation_size=observation_size,
    )
    return SharedPolicyModule(machine, arbiter, action_spec)


PHASES = ("operator_alone", "machine_alone", "collaboration", "validation")


def scenario_seeds(phase: str, cfg: DictConfig) -> list[int]:
    """The scenario seeds of a protocol phase: validation ``first_validation_seed`` + 0..N-1 (0..49 in
    the experiments), the operator-alone and collaboration runs in ranges of their own."""
    protocol = cfg.protocol
    if phase == "validation":
        first = protocol.first_validation_seed
        return list(range(first, first + protocol.validation_scenarios))
    if phase == "operator_alone":
        return list(range(10_000, 10_000 + protocol.operator_runs))
    if phase == "machine_alone":  # the same scenarios, flown by the machine alone
        return list(range(10_000, 10_000 + protocol.machine_calibration_runs))
    if phase == "collaboration":
        return list(range(20_000, 20_000 + protocol.collaboration_runs))
    raise ValueError(f"unknown phase {phase!r}")


def run_seed(seed: int, pretrain_seed: int, phase: str, method: str) -> int:
    """The torch seed of one (phase, method) run of a cell: a stable hash of the names.

    So a run's rows depend neither on which cells ran before nor on which other methods
    run in the cell.
    """
    return zlib.crc32(f"{seed}/{pretrain_seed}/{phase}/{method}".encode())


def operator_seed(seed: int, pretrain_seed: int, first_scenario: int) -> int:
    """The operator's seed for a batch of scenarios starting at ``first_scenario``.

    The same for every method of a cell: each method meets the same person on the same
    scenario (the operator's streams are per env, see :class:`EnvStreams`).
    """
    return seed + pretrain_seed * 7919 + first_scenario


@dataclass
class CellResult:
    """One cell's output: episode rows (every phase), traces of scenario 0, theta's updates,
    and the calibration (HULA's threshold, the uncertainty unit, what b_m says)."""

    episodes: list[dict[str, Any]]
    traces: list[dict[str, Any]]
    theta: list[dict[str, Any]]
    hula_threshold: float
    calibration: dict[str, Any] = field(default_factory=dict)


def confidence_signal(uncertainty_scale: float, frames: TensorDictBase, gap: torch.Tensor,
                      lam: float, delta2: float) -> dict[str, float]:
    """How b_m spreads on the calibration frames, and whether low b_m marks worse machine actions.

    ``gap`` is :meth:`OnlineLearner.action_gap` on ``frames``: the critic's
    ``Q(s, a_machine) - Q(s, a_operator)``. Returns the 10/50/90th percentiles of b_m,
    the mean gap on the quarter of frames with the lowest and the highest b_m, and their
    rank correlation (Spearman).
    """
    b_m = machine_confidence(frames["machine_uncertainty"].reshape(-1).double() / uncertainty_scale, lam, delta2)
    low, high = torch.quantile(b_m, 0.25), torch.quantile(b_m, 0.75)
    ranks = torch.stack([b_m.argsort().argsort(), gap.double().argsort().argsort()]).double()
    spearman = torch.corrcoef(ranks)[0, 1].item() if len(b_m) > 1 else float("nan")
    return {
        "uncertainty_scale": uncertainty_scale,
        **{f"b_m_p{q}": torch.quantile(b_m, q / 100).item() for q in (10, 50, 90)},
        "gap_low_b_m": gap[b_m <= low].mean().item(),
        "gap_high_b_m": gap[b_m >= high].mean().item(),
        "spearman_b_m_gap": spearman,
    }


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
    progress: Callable[[str], None] | None = None,
) -> CellResult:
    """The protocol for one (task, operator preset, pretraining seed): calibrate, collaborate, validate.

    1. **calibrate** — the operator alone on ``protocol.operator_runs`` scenarios:
       HULA's threshold (the 90th percentile of the machine's uncertainty seen, unless
       ``arbiter.hula_threshold`` is set) and the unit of the machine's uncertainty
       (:func:`calibrated_uncertainty_scale`, when ``machine.calibrate``); the machine
       alone on the first ``protocol.machine_calibration_runs`` of the same scenarios;
       the critic's warm-up on both partners' transitions (``online.critic_warmup_updates``);
    2. **collaborate** — each learned arbiter (``dcsc``, ``dcsc_centred``) on
       ``protocol.collaboration_runs`` scenarios, theta and its own copy of the critic
       learning online (Algorithm 1);
    3. **validate** — every method on the validation scenarios (seeds 0..N-1, groups of
       ``protocol.group_size``); the learned arbiters keep learning online; ``constant``
       runs once per beta of ``arbiter.constant_betas``; ``dcsc_frozen`` starts from the
       ``arbiter.form`` arbiter's theta after collaboration, its confidences frozen at
       their collaboration means.

    Every run seeds torch with :func:`run_seed`, so its rows do not depend on which
    cells or methods ran before it. ``progress``, when given, is called with a short line
    as each run starts (``"validation: hula"``).
    """
    base = {"task": task, "operator": preset, "pretrain_seed": pretrain_seed}
    seed, rollout = int(cfg.seed), int(cfg.online.rollout_length)
    spec_env = make_env(task, cfg, preset, [0], operator_seed=0)
    action_spec = spec_env.full_action_spec["action"]
    observation_size = spec_env.observation_spec["observation"].shape[-1]
    spec_env.close()

    def play(phase: str, method: str, policy: SharedPolicyModule, update: OnlineLearner | None = None,
             record_trace: bool = False) -> tuple[list[int], EpisodeBatch]:
        seeds = scenario_seeds(phase, cfg)
        if progress is not None:
            progress(f"{phase}: {method}")
        torch.manual_seed(run_seed(seed, pretrain_seed, phase, method))
        env = make_env(task, cfg, preset, seeds, operator_seed=operator_seed(seed, pretrain_seed, seeds[0]))
        result = run_scenarios(env, policy, task, rollout_length=rollout, update=update,
                               trace=record_trace and trace)
        env.close()
        return seeds, result

    def rows(phase: str, method: str, seeds: list[int], result: EpisodeBatch, **extra: Any) -> list[dict[str, Any]]:
        return [{**base, "method": method, "phase": phase,
                 "group": index // cfg.protocol.group_size + 1 if phase == "validation" else 0,
                 "seed": s, "path_length": float("nan"), **row, "hula_threshold": threshold, **extra}
                for index, (s, row) in enumerate(zip(seeds, result.rows, strict=True))]

    def traced(phase: str, method: str, seeds: list[int], result: EpisodeBatch) -> list[dict[str, Any]]:
        return [{**base, "method": method, "phase": phase, "seed": seeds[0], **r} for r in result.trace]

    def policy_for(method: str, arbiter: Arbiter | None = None, **kwargs: Any) -> SharedPolicyModule:
        if arbiter is None:
            form = cfg.arbiter[LEARNED_FORMS.get(method, "paper")]
            arbiter = make_arbiter(method, task, theta_init=form.theta_init, gain=cfg.arbiter.centred.gain,
                                   hula_threshold=threshold, **kwargs)
        return build_policy(machine_net, arbiter, task, cfg, action_spec, uncertainty_scale=scale,
                            observation_size=observation_size)

    def learner_for(policy: SharedPolicyModule) -> OnlineLearner:
        return make_online_learner(policy, copy.deepcopy(warm_critic), cfg.online)

    # 1. calibrate: everything the other phases need is known before any row is written
    threshold, scale = None, 1.0
    alone_seeds, alone = play("operator_alone", "operator", policy_for("operator"))
    threshold = cfg.arbiter.hula_threshold
    if threshold is None:
        threshold = float(torch.quantile(alone.uncertainty.double(), 0.9))
    if cfg.machine.calibrate:
        scale = calibrated_uncertainty_scale(alone.uncertainty, cfg.machine.lam, cfg.machine.delta2)
    episodes = rows("operator_alone", "operator", alone_seeds, alone)
    warm_frames = alone.frames
    if cfg.protocol.machine_calibration_runs:
        machine_seeds, machine_alone = play("machine_alone", "machine", policy_for("machine"))
        episodes += rows("machine_alone", "machine", machine_seeds, machine_alone)
        warm_frames = torch.cat([alone.frames, machine_alone.frames])
    warm = OnlineLearner(policy_for("dcsc"), copy.deepcopy(critic_net), theta_lr=0.0,
                         critic_lr=cfg.online.critic_lr, gamma=cfg.online.gamma, tau=cfg.online.tau)
    fit = {"td": warm.warm_up, "return": warm.fit_returns}[cfg.online.warmup_target]
    fit(warm_frames, updates=cfg.online.critic_warmup_updates, batch_size=cfg.online.warmup_batch_size,
        lr=cfg.online.warmup_lr, seed=run_seed(seed, pretrain_seed, "operator_alone", "critic"))
    warm_critic = warm.critic
    calibration = {**base, "hula_threshold": threshold,
                   **confidence_signal(scale, alone.frames, warm.action_gap(alone.frames),
                                       cfg.machine.lam, cfg.machine.delta2)}
    traces: list[dict[str, Any]] = []
    theta: list[dict[str, Any]] = []

    # 2. collaborate: each learned arbiter with its own theta and critic
    learners: dict[str, OnlineLearner] = {}
    means: dict[str, tuple[float, float]] = {}
    needed = {m for m in methods if m in LEARNED_FORMS}
    if "dcsc_frozen" in methods:
        needed.add(next(m for m, form in LEARNED_FORMS.items() if form == cfg.arbiter.form))
    for method in sorted(needed, key=METHODS.index):
        learners[method] = learner_for(policy_for(method))
        seeds, result = play("collaboration", method, learners[method].policy, update=learners[method])
        episodes += rows("collaboration", method, seeds, result)
        frames = result.frames
        means[method] = (frames["machine_confidence"].mean().item(), frames["human_confidence"].mean().item())
    collaboration_updates = {method: len(learner.history) for method, learner in learners.items()}
    frozen_learner = None
    if "dcsc_frozen" in methods:
        source = next(m for m, form in LEARNED_FORMS.items() if form == cfg.arbiter.form)
        arbiter = FrozenConfidenceArbiter(copy.deepcopy(learners[source].policy["arbiter"]), *means[source])
        frozen_learner = learner_for(policy_for("dcsc_frozen", arbiter))
        frozen_learner.critic.load_state_dict(learners[source].critic.state_dict())

    # 3. validate every method
    for method in methods:
        if method in LEARNED_FORMS or method == "dcsc_frozen":
            learner = frozen_learner if method == "dcsc_frozen" else learners[method]
            seeds, result = play("validation", method, learner.policy, update=learner, record_trace=True)
            episodes += rows("validation", method, seeds, result)
            traces += traced("validation", method, seeds, result)
        elif method == "constant":
            for beta in cfg.arbiter.constant_betas:
                seeds, result = play("validation", f"constant/{beta}", policy_for("constant", constant_beta=beta))
                episodes += rows("validation", "constant", seeds, result, constant_beta=float(beta))
        else:
            seeds, result = play("validation", method, policy_for(method), record_trace=True)
            episodes += rows("validation", method, seeds, result)
            traces += traced("validation", method, seeds, result)
    for method, learner in [*learners.items(), *([("dcsc_frozen", frozen_learner)] if frozen_learner else [])]:
        split = collaboration_updates.get(method, 0)
        theta += [{**base, "method": method, "phase": "collaboration" if h["update"] <= split else "validation", **h}
                  for h in learner.history]
    return CellResult(episodes, traces, theta, threshold, calibration)
