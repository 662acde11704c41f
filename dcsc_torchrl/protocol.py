"""The paper's protocol for one experiment cell: calibrate, collaborate, validate.

A *cell* is (task, operator, pretrained machine). Within it every method of
:data:`~dcsc_torchrl.methods.METHODS` is the same pipeline — the task's batched env, the
operator and its confidence as transforms, :class:`SharedPolicyModule` — with its own
arbiter. :func:`run_cell` takes any operator with the :class:`HumanOperator` interface
and the scenario seeds of each phase (:class:`Scenarios`) as arguments; the settings are
plain dataclasses, one per config group of the recipe (``MachineSettings(**cfg.machine)``),
so this module never reads a config file.

Each env of a batch is one scenario and plays exactly one recorded episode (its first);
envs that finish early keep running (their frames still feed DC-SC's online updates)
until every scenario of the batch is done. docs/architecture.md gives the reasons.
"""

from __future__ import annotations

import copy
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType

from dcsc_torchrl.arbiters import Arbiter, FrozenConfidenceArbiter
from dcsc_torchrl.confidence import check_machine_params, machine_confidence
from dcsc_torchrl.copilot import TrainedCopilot
from dcsc_torchrl.episodes import EpisodeBatch, concat_runs, run_scenarios
from dcsc_torchrl.machine import calibrated_uncertainty_scale
from dcsc_torchrl.methods import (
    ARBITER_FORMS,
    DEFAULT_METHODS,
    METHOD_NAMES,
    METHODS,
    build_policy,
    check_task_methods,
    learned_method,
    make_arbiter,
)
from dcsc_torchrl.networks import authority_critic
from dcsc_torchrl.online import (
    WARMUP_TARGETS,
    OnlineLearner,
    PolicyGradientLearner,
    make_online_learner,
)
from dcsc_torchrl.policy import SharedPolicyModule, plays_operator_alone
from dcsc_torchrl.state_arbiter import PretrainedArbiter, authority_fit_settings
from dcsc_torchrl.task import Task
from dcsc_torchrl.transforms import (
    FirstEpisodeOnly,
    HumanConfidenceTransform,
    HumanOperator,
    HumanOperatorTransform,
)


def check_betas(name: str, betas: Sequence[float]) -> None:
    """Refuses a list of authorities ``betas`` with an entry that is not a number in [0, 1]."""
    if any(isinstance(b, bool) or not isinstance(b, (int, float)) or not 0 <= b <= 1 for b in betas):
        raise ValueError(f"{name} must be numbers in [0, 1], got {list(betas)!r}")


@dataclass(frozen=True)
class MachineSettings:
    """The MC-dropout machine (Eqs. 10-13): :class:`MCDropoutPolicy`'s keywords."""

    num_samples: int
    lam: float
    delta2: float
    tau_inv: float = 0.0

    def __post_init__(self) -> None:
        check_machine_params(self.lam, self.delta2, self.tau_inv)  # a ValueError naming the parameter


@dataclass(frozen=True)
class ArbiterSettings:
    """The arbiters: each learned form's start (``paper: {theta_init}``, ``centred: {theta_init, gain}``),
    the form the ablation freezes, HULA's threshold (``None``: calibrated) and the constant sweep."""

    form: str
    paper: Mapping[str, float]
    centred: Mapping[str, float]
    hula_threshold: float | None = None
    constant_betas: Sequence[float] = (0.0, 0.5, 1.0)

    def __post_init__(self) -> None:
        if self.form not in ARBITER_FORMS:
            raise ValueError(f"form must be one of {', '.join(ARBITER_FORMS)}, got {self.form!r}")
        check_betas("constant_betas", self.constant_betas)

    def start(self, method: str) -> dict[str, float]:
        """The ``make_arbiter`` keywords of a learned method's initial arbiter."""
        form = dict(getattr(self, METHODS[method].form or "paper"))
        return {"theta_init": form["theta_init"], "gain": form.get("gain", self.centred["gain"])}


@dataclass(frozen=True)
class WarmupSettings:
    """The critic's warm-up on the calibration runs (:meth:`OnlineLearner.warm_up`)."""

    updates: int
    batch_size: int
    lr: float
    target: str = "return"
    blend_betas: Sequence[float] = ()
    """Constant betas played on :attr:`Scenarios.blend` for the warm-up (beyond the two partners alone)."""
    refit_state_arbiter: bool = True
    """Method ``dcsc_state`` (``authority``): refit its pretrained ``Q(s, beta)`` on the cell's own calibration
    runs (the operator alone at beta 0, the machine alone at 1), then its arbiter against it, as in pretraining."""

    def __post_init__(self) -> None:
        if self.target not in WARMUP_TARGETS:
            raise ValueError(f"target must be one of {', '.join(WARMUP_TARGETS)}, got {self.target!r}")
        check_betas("blend_betas", self.blend_betas)


SHARED_ACTIONS = ("sample", "mode")
"""``protocol.shared_action``: draw the discrete shared action, or take the mixture's mode."""


@dataclass(frozen=True)
class ProtocolSettings:
    """What the protocol does in a cell besides the methods' own settings.

    Args:
        seed: the experiment's seed (every run's torch seed is hashed from it, :func:`run_seed`).
        rollout_length: frames per env between two online updates (Algorithm 1).
        group_size: validation scenarios per group (the paper's groups of 10).
        max_steps: the episode limit, ``None`` for the task's own.
        calibrate_machine: read the machine's uncertainty in the unit that gives the
            median operator-alone frame ``b_m = 1/2`` (:func:`calibrated_uncertainty_scale`).
        shared_action: how a discrete shared action is taken from Eq. 14's mixture:
            ``"sample"`` draws it (Algorithm 1, line 7), ``"mode"`` takes its most likely
            key (TorchRL's ``ExplorationType.MODE``: the operator keeps every frame where
            ``1 - beta`` outweighs the machine's mass on another key). Every method and phase
            plays the same way; continuous actions are not affected.
    """

    seed: int = 0
    rollout_length: int = 5
    group_size: int = 10
    max_steps: int | None = None
    calibrate_machine: bool = True
    shared_action: str = "sample"

    def __post_init__(self) -> None:
        if self.shared_action not in SHARED_ACTIONS:
            raise ValueError(f"shared_action must be one of {', '.join(SHARED_ACTIONS)}, got {self.shared_action!r}")

    @property
    def exploration_type(self) -> ExplorationType:
        """The collectors' exploration type for :attr:`shared_action`."""
        return ExplorationType.RANDOM if self.shared_action == "sample" else ExplorationType.MODE


@dataclass(frozen=True)
class Scenarios:
    """The scenario seeds of each phase of the protocol."""

    operator_alone: Sequence[int]
    machine_alone: Sequence[int]
    collaboration: Sequence[int]
    validation: Sequence[int]
    blend: Sequence[int] = ()

    @classmethod
    def standard(cls, *, operator_runs: int = 20, machine_alone_runs: int = 20, collaboration_runs: int = 20,
                 validation_scenarios: int = 50, first_validation_seed: int = 0, blend_runs: int = 0) -> Scenarios:
        """The experiments' seeds: validation ``first_validation_seed + 0..N-1`` (0..49), the
        operator alone from 10,000 (the machine alone and the calibration blends on the first of
        the same), collaboration from 20,000: ranges that never meet.

        Raises:
            ValueError: two phases' ranges meet (a phase would replay another's scenarios),
                naming the count or first seed that makes them meet.
        """
        runs = {"operator_runs": operator_runs, "machine_alone_runs": machine_alone_runs, "blend_runs": blend_runs}
        calibration = max(runs, key=runs.get)  # the calibration phases share their seeds on purpose
        phases = [  # (the key that sets the range, its value, the phase, its seeds)
            ("first_validation_seed", first_validation_seed, "validation",
             range(first_validation_seed, first_validation_seed + validation_scenarios)),
            (calibration, runs[calibration], "calibration", range(10_000, 10_000 + runs[calibration])),
            ("collaboration_runs", collaboration_runs, "collaboration", range(20_000, 20_000 + collaboration_runs)),
        ]
        for i, (key, value, phase, seeds) in enumerate(phases):
            for _, _, other, other_seeds in phases[i + 1:]:
                if seeds and other_seeds and seeds.start < other_seeds.stop and other_seeds.start < seeds.stop:
                    raise ValueError(f"{key} {value}: the {phase} seeds {seeds.start}..{seeds.stop - 1} meet the "
                                     f"{other} seeds {other_seeds.start}..{other_seeds.stop - 1} (a phase would "
                                     "replay another's scenarios)")
        return cls(
            operator_alone=range(10_000, 10_000 + operator_runs),
            machine_alone=range(10_000, 10_000 + machine_alone_runs),
            collaboration=range(20_000, 20_000 + collaboration_runs),
            validation=range(first_validation_seed, first_validation_seed + validation_scenarios),
            blend=range(10_000, 10_000 + blend_runs),
        )


def run_seed(seed: int, pretrain_seed: int, phase: str, method: str) -> int:
    """The torch seed of one (phase, method) run of a cell: a stable hash of the names.

    So a run's rows depend neither on which cells ran before nor on which other methods
    run in the cell.
    """
    return zlib.crc32(f"{seed}/{pretrain_seed}/{phase}/{method}".encode())


def operator_seed(seed: int, pretrain_seed: int, first_scenario: int) -> int:
    """The operator's seed for a batch of scenarios starting at ``first_scenario``.

    The same for every method of a cell: each method meets the same person on the same
    scenario (the operator's streams are per env, see :class:`EnvStreams`). 7919 (a prime)
    keeps the pretraining seeds' operator streams apart.
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


class ProtocolCell:
    """One cell of the protocol while it runs: its settings, what calibration found, and its runs.

    :func:`run_cell` plays each phase's scenarios as one batch; ``dcsc study`` plays a
    person's through the same methods one scenario at a time (:meth:`play` with one seed,
    :meth:`calibrate_with` on the person's practice episodes), so a person's rows and a
    simulated operator's are made by the same code.

    Args:
        task: the registered task.
        operator: the operator of every run but the machine-alone ones.
        machine_net: the pretrained actor.
        base: the columns every row starts with (task, operator, pretrain_seed).
        pretrain_seed: the machine's pretraining seed (seeds the runs).
        human, machine, arbiter, online, protocol: the settings of :func:`run_cell`.
        progress: called with a short line as each run starts.
        expert_q: the Q network method ``ida_expert`` reads.
        copilot: the trained copilot method ``reddy`` runs.
        state_arbiter: the pretrained arbiter method ``dcsc_state`` starts from.
        machine_alone_operator: the operator in the loop of the machine-alone runs, whose
            actions nobody reads (default: ``operator``; a person cannot fly a batch).
    """

    def __init__(self, task: Task, operator: HumanOperator, machine_net: torch.nn.Module, *,
                 base: dict[str, Any], pretrain_seed: int, human: Mapping[str, Any], machine: MachineSettings,
                 arbiter: ArbiterSettings, online: Mapping[str, Any], protocol: ProtocolSettings,
                 progress: Callable[[str], None] | None = None, expert_q: torch.nn.Module | None = None,
                 copilot: TrainedCopilot | None = None, state_arbiter: PretrainedArbiter | None = None,
                 machine_alone_operator: HumanOperator | None = None) -> None:
        self.task, self.operator, self.machine_net, self.expert_q = task, operator, machine_net, expert_q
        self.copilot, self.state_arbiter = copilot, state_arbiter
        self.machine_alone_operator = operator if machine_alone_operator is None else machine_alone_operator
        self.base, self.pretrain_seed = base, pretrain_seed
        self.human, self.machine, self.arbiter, self.online, self.protocol = human, machine, arbiter, online, protocol
        self.progress = progress
        self.hula_threshold: float | None = arbiter.hula_threshold
        self.uncertainty_scale = 1.0
        self.critic: torch.nn.Module | None = None  # Algorithm 1's Q after its warm-up (IDA reads it)
        self.calibration_frames: TensorDictBase | None = None  # what the warm-up fitted the critic on
        self.warmup: WarmupSettings | None = None
        spec_env = self.make_env([0], operator_seed=0, operator=self.machine_alone_operator)
        self.action_spec = spec_env.full_action_spec["action"]
        self.observation_size = spec_env.observation_spec["observation"].shape[-1]
        spec_env.close()

    def make_env(self, seeds: Sequence[int], operator_seed: int, first_episode_only: bool = False,
                 operator: HumanOperator | None = None) -> TransformedEnv:
        """The task's envs of ``seeds`` with ``operator`` (default the cell's) and its confidence."""
        operator = self.operator if operator is None else operator
        transforms = [HumanOperatorTransform(operator, seed=operator_seed), HumanConfidenceTransform(**self.human)]
        if first_episode_only:
            transforms.insert(0, FirstEpisodeOnly())
        return self.task.make_envs(list(seeds), self.protocol.max_steps, transforms)

    def policy(self, method: str, arbiter: Arbiter | None = None, **kwargs: Any) -> SharedPolicyModule:
        """The shared policy of ``method`` (its arbiter from the cell's settings and calibration, or
        ``arbiter``); ``reddy``'s is the copilot's own; ``dcsc_state``'s a copy of the pretrained arbiter."""
        if method == "reddy":
            if self.copilot is None:
                raise ValueError("method reddy runs a trained copilot: this cell has none")
            return self.copilot.policy(self.action_spec)
        if method == "dcsc_state" and arbiter is None:
            if self.state_arbiter is None:
                raise ValueError("method dcsc_state starts from a pretrained arbiter: this cell has none")
            arbiter = copy.deepcopy(self.state_arbiter.arbiter)
        if arbiter is None:
            start = self.arbiter.start(method) if METHODS[method].kind == "learned" else {}
            arbiter = make_arbiter(method, self.task.action_dims, hula_threshold=self.hula_threshold,
                                   rule=self.task.authority_rule, q_value=self.critic, expert_q=self.expert_q,
                                   discrete=self.task.discrete,
                                   **start, **kwargs)
        return build_policy(self.machine_net, arbiter, self.action_spec, discrete=self.task.discrete,
                            num_samples=self.machine.num_samples, lam=self.machine.lam, delta2=self.machine.delta2,
                            tau_inv=self.machine.tau_inv, uncertainty_scale=self.uncertainty_scale,
                            observation_size=self.observation_size)

    def play(self, phase: str, method: str, seeds: Sequence[int], policy: SharedPolicyModule,
             update: Callable[[TensorDictBase], None] | None = None, trace: bool = False, *,
             hold_done: bool | None = None, torch_seed: int | None = None) -> EpisodeBatch:
        """One run: ``policy`` on the scenarios ``seeds`` (one env each).

        Torch is seeded with ``torch_seed``, by default :func:`run_seed` of the phase and
        method (one run of each per cell). ``hold_done`` (default: when nothing learns)
        holds each env once its first episode is done (:class:`FirstEpisodeOnly`); a run
        that learns keeps every env stepping until the last is done, its frames fed to
        ``update``. The machine-alone runs fly with :attr:`machine_alone_operator`.
        """
        if self.progress is not None:
            self.progress(f"{phase}: {method}")
        seed = self.protocol.seed
        torch.manual_seed(run_seed(seed, self.pretrain_seed, phase, method) if torch_seed is None else torch_seed)
        env = self.make_env(seeds, operator_seed=operator_seed(seed, self.pretrain_seed, seeds[0]),
                            first_episode_only=update is None if hold_done is None else hold_done,
                            operator=self.machine_alone_operator if method == "machine" else None)
        rollout_length = (update.segment_length if isinstance(update, PolicyGradientLearner)
                          else self.protocol.rollout_length)
        result = run_scenarios(env, policy, self.task, rollout_length=rollout_length, update=update,
                               trace=trace, exploration_type=self.protocol.exploration_type)
        env.close()
        return result

    def reuse_operator_run(self, operator_alone: EpisodeBatch, name: str, beta: float) -> EpisodeBatch:
        """The operator's validation episodes as those of a constant ``beta`` that plays the
        operator alone exactly (:func:`~dcsc_torchrl.policy.plays_operator_alone`).

        Playing that ``beta`` would give the same episodes: every run seeds torch and the
        operator itself, and the env is deterministic given the actions. Only ``mean_beta``
        is the arbiter's own."""
        if self.progress is not None:
            self.progress(f"validation: {name} (the operator's run: beta {beta} plays the operator alone)")
        return EpisodeBatch([{**row, "mean_beta": float(beta)} for row in operator_alone.rows])

    def rows(self, phase: str, method: str, seeds: Sequence[int], result: EpisodeBatch, *, first_index: int = 0,
             **extra: Any) -> list[dict[str, Any]]:
        """``episodes.csv``'s rows of a run; ``first_index``: the position of ``seeds[0]`` among the
        phase's scenarios (a validation scenario's group is its position // ``group_size`` + 1)."""
        group = self.protocol.group_size
        return [{**self.base, "method": method, "phase": phase,
                 "group": (first_index + index) // group + 1 if phase == "validation" else 0,
                 "seed": s, "path_length": float("nan"), **row, "hula_threshold": self.hula_threshold, **extra}
                for index, (s, row) in enumerate(zip(seeds, result.rows, strict=True))]

    def traced(self, phase: str, method: str, seeds: Sequence[int], result: EpisodeBatch) -> list[dict[str, Any]]:
        """``trace.csv``'s rows of a run's traced scenario (``seeds[0]``)."""
        return [{**self.base, "method": method, "phase": phase, "seed": seeds[0], **r} for r in result.trace]

    # -- the three phases of run_cell ---------------------------------------------------
    def calibrate(self, scenarios: Scenarios, critic_net: torch.nn.Module,
                  warmup: WarmupSettings) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        """Phase 1: the operator alone on ``scenarios.operator_alone``, then :meth:`calibrate_with`
        its episodes. Returns the phase's rows and the cell's calibration record."""
        alone = self.play("operator_alone", "operator", scenarios.operator_alone, self.policy("operator"))
        machine_rows, calibration = self.calibrate_with(alone, scenarios, critic_net, warmup)
        return self.rows("operator_alone", "operator", scenarios.operator_alone, alone) + machine_rows, calibration

    def calibrate_with(self, alone: EpisodeBatch, scenarios: Scenarios, critic_net: torch.nn.Module,
                       warmup: WarmupSettings) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        """Everything the other phases need, from the operator-alone episodes ``alone`` (the
        calibration runs; played here, or one by one by a person): HULA's threshold, the
        uncertainty unit, the machine alone on ``scenarios.machine_alone`` and :attr:`critic`,
        warmed up on both partners' transitions. Returns the machine's (and blends') rows and
        the calibration record."""
        protocol, machine = self.protocol, self.machine
        if self.hula_threshold is None:
            self.hula_threshold = float(torch.quantile(alone.uncertainty.double(), 0.9))
        self.calibrate_unit(alone)
        episodes: list[dict[str, Any]] = []
        warm_frames = alone.frames
        if len(scenarios.machine_alone):
            machine_alone = self.play("machine_alone", "machine", scenarios.machine_alone, self.policy("machine"))
            episodes += self.rows("machine_alone", "machine", scenarios.machine_alone, machine_alone)
            warm_frames = concat_runs(warm_frames, machine_alone.frames)
        for beta in warmup.blend_betas if len(scenarios.blend) else ():
            blend = self.play("calibration_blend", f"constant/{beta}", scenarios.blend,
                              self.policy("constant", constant_beta=beta))
            episodes += self.rows("calibration_blend", "constant", scenarios.blend, blend, constant_beta=float(beta))
            warm_frames = concat_runs(warm_frames, blend.frames)
        if self.online.get("theta_critic") == "authority":  # a fresh Q(s, beta), fitted on the partners' returns
            torch.manual_seed(run_seed(protocol.seed, self.pretrain_seed, "operator_alone", "authority_critic"))
            critic_net = authority_critic(self.observation_size, self.task.action_dims)
        warm = make_online_learner(self.policy("dcsc"), copy.deepcopy(critic_net), **{**self.online, "theta_lr": 0.0})
        warm.warm_up(warm_frames, target=warmup.target, updates=warmup.updates, batch_size=warmup.batch_size,
                     lr=warmup.lr, seed=run_seed(protocol.seed, self.pretrain_seed, "operator_alone", "critic"))
        self.calibration_frames, self.warmup = warm_frames, warmup
        calibration = {**self.base, "hula_threshold": self.hula_threshold,
                       **confidence_signal(self.uncertainty_scale, alone.frames, warm.action_gap(alone.frames),
                                           machine.lam, machine.delta2)}
        self.critic = warm.critic
        return episodes, calibration

    def calibrate_unit(self, alone: EpisodeBatch) -> None:
        """The unit of the machine's uncertainty from the operator-alone episodes ``alone``
        (:func:`calibrated_uncertainty_scale`), when ``protocol.calibrate_machine``."""
        if self.protocol.calibrate_machine:
            self.uncertainty_scale = calibrated_uncertainty_scale(alone.uncertainty, self.machine.lam,
                                                                  self.machine.delta2)

    def learner(self, policy: SharedPolicyModule) -> OnlineLearner:
        """Algorithm 1's online learner of ``policy`` with its own copy of the warmed-up :attr:`critic`."""
        return make_online_learner(policy, copy.deepcopy(self.critic), **self.online)

    def collaborate(self, seeds: Sequence[int], methods: Sequence[str],
                    ) -> tuple[list[dict[str, Any]], dict[str, OnlineLearner], dict[str, int]]:
        """Phase 2: each learned arbiter with its own theta and critic, learning online (a pretrained
        one, ``dcsc_state``, from the pretrained arbiter and value critic); then
        ``dcsc_frozen`` (if validated) from the ``arbiter.form`` arbiter, its confidences frozen
        at their collaboration means. Returns the rows, the learners and each one's update count."""
        frozen_source = learned_method(self.arbiter.form)
        needed = {m for m in methods if METHODS[m].kind in ("learned", "pretrained")} | (
            {frozen_source} if "dcsc_frozen" in methods else set())
        episodes: list[dict[str, Any]] = []
        learners: dict[str, OnlineLearner] = {}
        means: dict[str, tuple[float, float]] = {}
        for method in sorted(needed, key=METHOD_NAMES.index):
            policy = self.policy(method)
            if METHODS[method].kind == "pretrained":
                learners[method] = self.state_arbiter.learner(policy)
                if self.warmup is not None and self.warmup.refit_state_arbiter:
                    self.state_arbiter.check_refittable()
                    learners[method].fit(self.calibration_frames, **authority_fit_settings(self.state_arbiter.settings),
                                         seed=run_seed(self.protocol.seed, self.pretrain_seed, "operator_alone",
                                                       "state_arbiter"))
            else:
                learners[method] = self.learner(policy)
            result = self.play("collaboration", method, seeds, learners[method].policy, update=learners[method])
            episodes += self.rows("collaboration", method, seeds, result)
            means[method] = (result.frames["machine_confidence"].mean().item(),
                             result.frames["human_confidence"].mean().item())
        updates = {method: len(learner.history) for method, learner in learners.items()}
        if "dcsc_frozen" in methods:
            frozen = FrozenConfidenceArbiter(copy.deepcopy(learners[frozen_source].policy["arbiter"]),
                                             *means[frozen_source])
            learners["dcsc_frozen"] = self.learner(self.policy("dcsc_frozen", frozen))
            learners["dcsc_frozen"].critic.load_state_dict(learners[frozen_source].critic.state_dict())
        return episodes, learners, updates

    def validate(self, seeds: Sequence[int], methods: Sequence[str], learners: Mapping[str, OnlineLearner], *,
                 trace: bool) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """Phase 3: every method on the validation scenarios (the learned ones still learning).
        Returns the rows and, with ``trace``, every frame of scenario 0 of each method."""
        episodes: list[dict[str, Any]] = []
        traces: list[dict[str, Any]] = []
        operator_alone: EpisodeBatch | None = None  # the operator's validation run, once played
        for method in methods:
            if METHODS[method].kind == "sweep":
                for beta in self.arbiter.constant_betas:
                    if operator_alone is not None and plays_operator_alone(
                            beta, discrete=self.task.discrete, mode=self.protocol.shared_action == "mode"):
                        result = self.reuse_operator_run(operator_alone, f"constant/{beta}", beta)
                    else:
                        result = self.play("validation", f"constant/{beta}", seeds,
                                           self.policy("constant", constant_beta=beta))
                    episodes += self.rows("validation", "constant", seeds, result, constant_beta=float(beta))
                continue
            learner = learners.get(method)
            policy = self.policy(method) if learner is None else learner.policy
            result = self.play("validation", method, seeds, policy, update=learner, trace=trace)
            if method == "operator":
                operator_alone = result
            episodes += self.rows("validation", method, seeds, result)
            traces += self.traced("validation", method, seeds, result)
        return episodes, traces


def run_cell(
    task: Task,
    operator: HumanOperator,
    machine_net: torch.nn.Module,
    critic_net: torch.nn.Module,
    *,
    operator_name: str,
    pretrain_seed: int,
    human: Mapping[str, Any],
    machine: MachineSettings,
    arbiter: ArbiterSettings,
    online: Mapping[str, Any],
    warmup: WarmupSettings,
    protocol: ProtocolSettings | None = None,
    scenarios: Scenarios | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    trace: bool = False,
    progress: Callable[[str], None] | None = None,
    expert_q: torch.nn.Module | None = None,
    copilot: TrainedCopilot | None = None,
    state_arbiter: PretrainedArbiter | None = None,
) -> CellResult:
    """The protocol for one (task, operator, pretrained machine): calibrate, collaborate, validate.

    1. **calibrate** — the operator alone on ``scenarios.operator_alone``: HULA's
       threshold (the 90th percentile of the machine's uncertainty seen, unless
       ``arbiter.hula_threshold`` is set) and the unit of the machine's uncertainty
       (:func:`calibrated_uncertainty_scale`, when ``protocol.calibrate_machine``); the
       machine alone on ``scenarios.machine_alone`` (may be empty); the critic's warm-up
       on both partners' transitions (``warmup``);
    2. **collaborate** — each learned arbiter (``dcsc``, ``dcsc_centred``) on
       ``scenarios.collaboration``, theta and its own copy of the critic learning online
       (Algorithm 1);
    3. **validate** — every method on ``scenarios.validation`` (groups of
       ``protocol.group_size``); the learned arbiters keep learning online; ``constant``
       runs once per beta of ``arbiter.constant_betas``, except that a beta which plays
       the operator alone exactly (beta 0; with the discrete mode every beta < 1/2,
       :func:`~dcsc_torchrl.policy.plays_operator_alone`) takes the episodes of the
       ``operator`` run when that ran before it; ``dcsc_frozen`` starts from the
       ``arbiter.form`` arbiter's theta after collaboration, its confidences frozen at
       their collaboration means; ``ida`` acts on a frozen copy of the critic as its
       warm-up left it (Algorithm 1's Q, before any collaboration); ``ida_expert`` on a
       frozen copy of ``expert_q``; ``reddy`` is ``copilot``'s own shared policy (its Q
       network the machine, its tolerance rule the arbiter); ``dcsc_state`` starts
       collaboration from a copy of ``state_arbiter`` and its value critic, both
       fine-tuned online (:class:`~dcsc_torchrl.online.PolicyGradientLearner`).

    Args:
        task: the registered task (:data:`dcsc_torchrl.tasks.TASKS`).
        operator: any :class:`HumanOperator`; its ``reset(seed)`` is called at the start of
            every run, with a seed that is the same for every method of the cell.
        machine_net, critic_net: the pretrained actor and critic (the critic is copied, not trained).
        operator_name: the ``operator`` column of the rows.
        pretrain_seed: the machine's pretraining seed (the ``pretrain_seed`` column; seeds the runs).
        human: :class:`HumanConfidenceTransform`'s keywords (Eqs. 6-9).
        machine, arbiter, warmup: the settings above.
        protocol: the runs' settings (:class:`ProtocolSettings`'s defaults when ``None``).
        online: :class:`OnlineLearner`'s keywords (Algorithm 1's step sizes, gamma, tau, ...).
        scenarios: the seeds of each phase; :meth:`Scenarios.standard` when ``None``.
        methods: the methods validated, names of :data:`METHODS`.
        trace: record every frame of scenario 0 for each method validated.
        progress: called with a short line as each run starts (``"validation: hula"``).
        expert_q: an expert's Q network (the task's critic shape: ``Q(s, .)`` or ``Q(s, a)``),
            which method ``ida_expert`` reads; required when ``methods`` names it.
        copilot: Reddy et al.'s trained copilot, which method ``reddy`` runs; required when
            ``methods`` names it, and refused when it was trained with ``operator_name``.
        state_arbiter: the pretrained state-dependent arbiter method ``dcsc_state`` starts
            from; required when ``methods`` names it, and refused when its pool holds
            ``operator_name`` or it was pretrained next to another machine.

    Every run seeds torch with :func:`run_seed`, so its rows do not depend on which
    cells or methods ran before it.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}: expected names of {', '.join(METHOD_NAMES)}")
    check_task_methods(task, methods)
    if "ida_expert" in methods and expert_q is None:
        raise ValueError("method ida_expert reads an expert's Q: pass expert_q (e.g. a converged machine's critic)")
    if "reddy" in methods:
        if copilot is None:
            raise ValueError("method reddy runs a trained copilot: pass copilot (dcsc copilot trains one)")
        copilot.check_evaluated_next_to(operator_name)
    if "dcsc_state" in methods:
        if state_arbiter is None:
            raise ValueError("method dcsc_state starts from a pretrained arbiter: pass state_arbiter "
                             "(dcsc arbiter pretrains one)")
        state_arbiter.check_evaluated_next_to(operator_name, machine_net)
        if warmup.refit_state_arbiter:
            state_arbiter.check_refittable()
    if "ida" in methods and online.get("theta_critic") == "authority":
        raise ValueError("method ida reads Q(s, a): it cannot run with online.theta_critic=authority, "
                         "whose critic is Q(s, beta)")
    scenarios = Scenarios.standard() if scenarios is None else scenarios
    protocol = ProtocolSettings() if protocol is None else protocol
    base = {"task": task.name, "operator": operator_name, "pretrain_seed": pretrain_seed}
    cell = ProtocolCell(task, operator, machine_net, base=base, pretrain_seed=pretrain_seed, human=human, machine=machine,
                 arbiter=arbiter, online=online, protocol=protocol, progress=progress, expert_q=expert_q,
                 copilot=copilot, state_arbiter=state_arbiter)
    episodes, calibration = cell.calibrate(scenarios, critic_net, warmup)
    collaboration, learners, collaboration_updates = cell.collaborate(scenarios.collaboration, methods)
    validation, traces = cell.validate(scenarios.validation, methods, learners, trace=trace)
    theta = [{**base, "method": method,
              "phase": "collaboration" if h["update"] <= collaboration_updates.get(method, 0) else "validation", **h}
             for method, learner in learners.items() for h in learner.history]
    return CellResult(episodes + collaboration + validation, traces, theta, cell.hula_threshold, calibration)
