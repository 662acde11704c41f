"""Human traits shared by the simulated operators (docs/operators.md), in one place.

A simulated operator is a controller that knows the task (the pad's x, the obstacles'
future positions) wrapped in the traits of a person:

- a decision interval: it re-decides every ``decision_interval`` seconds and holds its
  key between decisions (a person changes keys a few times a second, not at 50 Hz);
- a perception delay: at a decision it acts on what it saw one reaction time ago, i.e. on
  the env's keys of ``round(RT / frame)`` frames before (``perceive_delayed``; an explicit
  upper-bound preset, ``scripted``, acts on the current frame), carried to the present by
  its internal model and the keys it pressed since (an efference copy);
- noise: at a decision it picks a random choice with probability ``eps``;
- lag: at a decision it repeats its previous choice with probability ``lag``;
- a reaction time (RT) per decision, drawn from an ex-Gaussian whose mean grows with the
  workload of the moment (Eq. 6 of the paper reads RT: decisions slower than t_d lower
  the operator's knowledge); a decision whose RT exceeds ``lapse_threshold`` (t_d) is a
  lapse: the operator is overloaded and holds its key for the excess ``RT - t_d`` before
  it decides again.

:class:`OperatorTraits` holds the parameters, :data:`PRESETS` the named surrogate pilots,
:class:`EnvStreams` the per-environment random streams and :class:`SimulatedHuman` the
decision loop both :class:`~dcsc_torchrl.humans.SimulatedPilot` and
:class:`~dcsc_torchrl.humans.SimulatedOperator` run; they add only their controller.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["MAX_PERCEPTION_DELAY", "PRESETS", "EnvStreams", "OperatorTraits", "SimulatedHuman", "ex_gaussian_rt"]

_Operator = TypeVar("_Operator", bound="SimulatedHuman")


@dataclass(frozen=True)
class OperatorTraits:
    """The traits of a simulated person (docs/operators.md); every field is a parameter.

    RT per decision is ex-Gaussian: ``RT = rt_mu (1 + workload_gain * workload)
    + rt_sigma * N(0, 1) + rt_tau * Exp(1)``, floored at 0, so at zero workload its mean
    is ``rt_mu + rt_tau`` and its variance ``rt_sigma^2 + rt_tau^2``.

    Attributes:
        decision_interval: seconds between decisions (rounded to whole frames, at least
            one); the key is held in between.
        eps: probability of a random choice at a decision (action noise), in [0, 1].
        lag: probability of repeating the previous choice at a decision, in [0, 1).
        rt_mu: mean of the Gaussian part of the RT, seconds, >= 0.
        rt_sigma: standard deviation of the Gaussian part, seconds, >= 0.
        rt_tau: mean of the exponential part (the slow tail), seconds, >= 0.
        workload_gain: how much the workload (a task-specific, dimensionless measure
            such as speed and tilt) stretches ``rt_mu``, >= 0.
        lapse_threshold: t_d, seconds, > 0: a decision slower than this is a lapse and
            delays the next decision by ``RT - t_d`` (defaults to the t_d of
            :class:`~dcsc_torchrl.transforms.HumanConfidenceTransform`).
        perceive_delayed: act on the observation of one RT ago (a person) rather than on
            the current one (a scripted controller). The delay is capped at
            :data:`MAX_PERCEPTION_DELAY` seconds and at the frames since the episode began.
    """

    decision_interval: float = 0.2
    eps: float = 0.0
    lag: float = 0.0
    rt_mu: float = 0.35
    rt_sigma: float = 0.05
    rt_tau: float = 0.1
    workload_gain: float = 0.3
    lapse_threshold: float = 1.0
    perceive_delayed: bool = True

    def __post_init__(self) -> None:
        checks = {
            "decision_interval": self.decision_interval > 0,
            "eps": 0 <= self.eps <= 1,
            "lag": 0 <= self.lag < 1,
            "rt_mu": self.rt_mu >= 0,
            "rt_sigma": self.rt_sigma >= 0,
            "rt_tau": self.rt_tau >= 0,
            "workload_gain": self.workload_gain >= 0,
            "lapse_threshold": self.lapse_threshold > 0,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (ok and math.isfinite(value)):
                raise ValueError(f"invalid operator trait {name}={value!r}")


MAX_PERCEPTION_DELAY = 2.0
"""Seconds: the longest perception delay a simulated person acts with (RTs past it act
on the frame of 2 s before; with t_d = 1 s such a decision is a lapse anyway)."""

PRESETS: dict[str, OperatorTraits] = {
    "expert": OperatorTraits(),
    "noisy": OperatorTraits(eps=0.25),
    "laggy": OperatorTraits(lag=0.8),
    "distracted": OperatorTraits(rt_mu=0.4, rt_sigma=0.1, rt_tau=0.2, workload_gain=0.5),
    "scripted": OperatorTraits(decision_interval=0.04, perceive_delayed=False),
}
"""Surrogate pilots in the spirit of the shared-autonomy literature (Reddy et al., 2018):
a competent ``expert``, a ``noisy`` one (random keys with probability 0.25, Reddy et
al.'s noisy pilot), a ``laggy`` one (repeats its previous choice with probability 0.8,
Reddy et al.'s laggy pilot) and a ``distracted`` one (a long RT tail: frequent lapses
past t_d). All four decide every 0.2 s (about the psychological refractory period
between two successive responses, Pashler 1994) and act on what they saw one RT ago;
their RT is ex-Gaussian with mu 0.35 s, sigma 0.05 s and tau 0.1 s (0.4 / 0.1 / 0.2 for
``distracted``), the range of ex-Gaussian fits to choice reaction times (Ratcliff and
Murdock 1976; Luce 1986). ``scripted`` is the undelayed controller re-deciding every
frame pair: an explicit upper bound, not a person."""


def ex_gaussian_rt(
    traits: OperatorTraits, workload: torch.Tensor, uniforms: torch.Tensor
) -> torch.Tensor:
    """Ex-Gaussian reaction times whose Gaussian mean grows with the workload.

    ``RT = rt_mu (1 + workload_gain * workload) + rt_sigma * z + rt_tau * e`` with
    ``z ~ N(0, 1)`` (Box-Muller) and ``e ~ Exp(1)`` (inverse CDF), floored at 0.

    Args:
        traits: the RT parameters.
        workload: ``[...]``, >= 0.
        uniforms: ``[..., 3]`` uniforms in [0, 1) (two for z, one for e).

    Returns:
        RT in seconds, ``[...]``, float32.

    Examples:
        >>> rt = ex_gaussian_rt(OperatorTraits(), torch.zeros(4), torch.full((4, 3), 0.5))
        >>> rt.shape
        torch.Size([4])
    """
    u1, u2, u3 = (1.0 - uniforms).unbind(-1)  # in (0, 1]: finite logs
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    e = -torch.log(u3)
    mu = traits.rt_mu * (1.0 + traits.workload_gain * workload.to(z.dtype))
    return (mu + traits.rt_sigma * z + traits.rt_tau * e).clamp_min(0.0).to(torch.float32)


def _signed(value: int) -> int:
    """A 64-bit constant as the int64 torch stores."""
    return value - (1 << 64) if value >= 1 << 63 else value


_GOLDEN = _signed(0x9E3779B97F4A7C15)
_MIX1 = _signed(0xBF58476D1CE4E5B9)
_MIX2 = _signed(0x94D049BB133111EB)


def _shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def _mix(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64's finaliser (Steele, Lea and Flood, 2014), wrapping int64 arithmetic."""
    x = (x ^ _shift_right(x, 30)) * _MIX1
    x = (x ^ _shift_right(x, 27)) * _MIX2
    return x ^ _shift_right(x, 31)


class EnvStreams:
    """One counter-based random stream per environment (SplitMix64 keyed by seed and env).

    Draw ``j`` of env ``i``'s call ``c`` is a hash of ``(seed, i, c, j)``, where ``c``
    counts the calls in which env ``i`` took part (``active``), so env ``i`` gets the
    same numbers whatever the batch it sits in (its size, its shape, its other envs and
    when they take part), on any device, in one vectorised op.

    Args:
        seed: the operator's seed.
        draws: uniforms per env per call.

    Examples:
        >>> streams = EnvStreams(0, draws=2)
        >>> a = streams.uniform(torch.Size([8]))
        >>> EnvStreams(0, draws=2).uniform(torch.Size([3]))[2].equal(a[2])
        True
    """

    def __init__(self, seed: int, draws: int) -> None:
        self.draws = draws
        self.calls = torch.zeros(0, dtype=torch.int64)
        """Per env, the calls it took part in."""
        self._key = int(_mix(torch.tensor(_signed(int(seed) % (1 << 64)))))

    def uniform(self, batch_shape: torch.Size, device: torch.device | None = None,
                active: torch.Tensor | None = None) -> torch.Tensor:
        """The next ``[*batch_shape, draws]`` uniforms in [0, 1) (float64), one call's worth.

        Only the envs of ``active`` (bool, ``batch_shape``; default all) take part: the
        others get numbers too, but their stream does not move on.
        """
        n_envs = math.prod(batch_shape)
        if len(self.calls) < n_envs:
            self.calls = torch.cat([self.calls, self.calls.new_zeros(n_envs - len(self.calls))])
        env = torch.arange(n_envs, dtype=torch.int64, device=device).unsqueeze(-1)
        draw = torch.arange(self.draws, dtype=torch.int64, device=device)
        env_key = _mix(self._key + _GOLDEN * env)
        counter = self.calls[:n_envs].to(device).unsqueeze(-1) * self.draws + draw
        bits = _mix(env_key + _GOLDEN * (counter + 1)).reshape(*batch_shape, self.draws)
        self.calls[:n_envs] += 1 if active is None else active.reshape(n_envs).to(self.calls.device, torch.int64)
        return _shift_right(bits, 11).to(torch.float64) * 2.0**-53


class SimulatedHuman(ABC):
    """The decision loop of a simulated operator (a :class:`HumanOperator`).

    Per frame, for every env of the batch (any batch shape): an env whose episode
    starts (``is_init``) drops its held choice and decides now; otherwise it decides
    when its decision interval (plus any lapse) has passed. At a decision it draws an RT
    (:func:`ex_gaussian_rt`, workload of the current frame from :meth:`workload`); then,
    with probability ``lag`` it keeps pressing what it pressed last, else with
    probability ``eps`` it picks a random choice, else it takes its controller's
    (:meth:`plan`) on what it perceived: the env's ``in_keys`` of
    ``round(RT / frame_seconds)`` frames before (when ``traits.perceive_delayed``; never
    before the episode's first frame, at most :data:`MAX_PERCEPTION_DELAY` seconds),
    carried to the present by :meth:`anticipate` with the choices it made on the frames
    since. A plan is one choice held until the next decision, or one choice per frame of
    the coming interval (an open-loop key sequence; a lapse holds its last key). Between
    decisions ``human_decided`` is False and the last decision's RT is reported.

    Each env keeps its own clock: a call advances only the envs it steps. Where the
    TensorDict holds ``"_step"`` (TorchRL's partial steps; :class:`HumanOperatorTransform`
    also sends it on a partial reset, True for the envs reset), an env marked False
    stands still: it neither sees a frame nor decides, its held key, its plan and its
    random stream stay where they were, and it answers with its held key. So an env
    behaves the same whichever other envs of its batch finish and restart, and when.

    Every random number comes from :class:`EnvStreams`, so an env behaves the same in
    any batch. Subclasses say what a choice is (``n_choices``, :meth:`action`), how the
    person would choose (:meth:`plan`) and what loads them (:meth:`workload`).

    Args:
        traits: the person's traits.
        frame_seconds: the env's seconds per frame (decision intervals and lapses are
            counted in frames).
    """

    n_choices: int
    """Number of choices (keys, or points of an action grid)."""
    in_keys: tuple[str, ...]
    """The env keys :meth:`plan` and :meth:`workload` read."""

    _draws = 6  # lag, eps, random choice, RT (3)

    def __init__(self, traits: OperatorTraits, *, frame_seconds: float) -> None:
        if not isinstance(traits, OperatorTraits):
            raise TypeError(f"traits must be an OperatorTraits, got {type(traits).__name__}")
        if not frame_seconds > 0:
            raise ValueError(f"frame_seconds must be > 0, got {frame_seconds!r}")
        self.traits = traits
        self.frame_seconds = float(frame_seconds)
        self.streams: EnvStreams | None = None  # seeded by reset, or at the first call
        self._state: TensorDict | None = None

    @classmethod
    def from_preset(cls: type[_Operator], name: str, **kwargs: Any) -> _Operator:
        """The operator with the traits of ``PRESETS[name]``.

        Args:
            name: a key of :data:`PRESETS`.
            **kwargs: fields of :class:`OperatorTraits` override the preset's (e.g.
                ``eps=0.3``); the rest go to the constructor.

        Raises:
            KeyError: unknown preset name (the message lists the presets).
        """
        if name not in PRESETS:
            raise KeyError(f"unknown operator preset {name!r}; presets: {sorted(PRESETS)}")
        fields = {f.name for f in dataclasses.fields(OperatorTraits)}
        overrides = {k: v for k, v in kwargs.items() if k in fields}
        rest = {k: v for k, v in kwargs.items() if k not in fields}
        return cls(dataclasses.replace(PRESETS[name], **overrides), **rest)

    @property
    def decision_period(self) -> int:
        """Frames between two decisions when no lapse intervenes (at least 1)."""
        return max(1, round(self.traits.decision_interval / self.frame_seconds))

    def reset(self, seed: int | None) -> None:
        """Re-seeds every env's stream (``None``: a seed from torch's global RNG) and forgets all."""
        if seed is None:
            seed = int(torch.randint(2**62, ()))
        self.streams = EnvStreams(seed, self._draws)
        self._state = None

    @abstractmethod
    def plan(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The controller's choices for each env of a flat batch, int64 in ``[0, n_choices)``:
        ``[N]`` (held until the next decision) or ``[N, decision_period]`` (one per frame)."""

    @abstractmethod
    def workload(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The workload of each env of a flat batch now, ``[N]``, >= 0 (stretches the RT)."""

    @abstractmethod
    def action(self, choice: torch.Tensor) -> torch.Tensor:
        """``human_action`` of choices ``[N]``: ``[N, n]`` one-hot or ``[N, d]`` float."""

    @property
    def memory_frames(self) -> int:
        """Frames of the past it keeps to perceive with a delay (1: the current frame only)."""
        if not self.traits.perceive_delayed:
            return 1
        return math.ceil(MAX_PERCEPTION_DELAY / self.frame_seconds) + 1

    def _fresh_state(self, frame: TensorDictBase) -> TensorDict:
        n_envs = frame.batch_size[0]
        return TensorDict(
            {
                "choice": torch.zeros(n_envs, dtype=torch.int64),
                "plan": torch.zeros(n_envs, self.decision_period, dtype=torch.int64),
                "since": torch.zeros(n_envs, dtype=torch.int64),
                "issued": torch.zeros(n_envs, self.memory_frames, dtype=torch.int64),
                "rt": torch.zeros(n_envs),
                "wait": torch.zeros(n_envs, dtype=torch.int64),
                "age": torch.zeros(n_envs, dtype=torch.int64),
                "slot": torch.zeros(n_envs, dtype=torch.int64),  # where the env's current frame sits in the ring
                "seen": frame.unsqueeze(1).expand(n_envs, self.memory_frames).clone(),
            },
            [n_envs],
            device=frame.device,
        )

    def _remember(self, frame: TensorDictBase, restart: torch.Tensor, active: torch.Tensor) -> None:
        """Stores the current frame of the ``active`` envs in their ring of past frames; counts
        their frames since reset."""
        state = self._state
        state["slot"] = torch.where(active, (state["slot"] + 1) % self.memory_frames, state["slot"])
        rows = active.nonzero().squeeze(-1)
        state["seen"][rows, state["slot"][rows]] = frame[rows]
        state["age"] = torch.where(restart, 0, state["age"] + active.long())

    def _perceived(self, rows: torch.Tensor, rt: torch.Tensor) -> TensorDictBase:
        """What the deciding envs ``rows`` saw one RT ago, carried forward by :meth:`anticipate`."""
        state = self._state
        delay = torch.round(rt / self.frame_seconds).long()
        delay = torch.minimum(delay.clamp_max(self.memory_frames - 1), state["age"][rows])
        slots = (state["slot"][rows] - delay) % self.memory_frames
        since = torch.arange(int(delay.max()), device=delay.device)
        issued_slots = (slots.unsqueeze(-1) + since) % self.memory_frames
        issued = state["issued"][rows.unsqueeze(-1), issued_slots]
        return self.anticipate(state["seen"][rows, slots], issued, delay)

    def anticipate(
        self, perceived: TensorDictBase, issued: torch.Tensor, delay: torch.Tensor
    ) -> TensorDictBase:
        """The person's guess of the present from a frame seen ``delay`` frames ago.

        People compensate their own delay with an internal model of what they steer,
        fed with a copy of the commands they sent since (the Smith predictor of Miall,
        Weir, Wolpert and Stein, 1993). The default guesses nothing: the stale frame is
        taken for the present. Operators override it with their task's forward model.

        Args:
            perceived: the frame seen, batch ``[N]``.
            issued: ``[N, max(delay)]`` int64, the operator's own choices on the frames
                since, oldest first: ``issued[i, j]`` for ``j < delay[i]`` (the rest is
                padding).
            delay: ``[N]`` int64, frames between the perceived frame and the present.
        """
        return perceived

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Decides (or holds) for every env; see the class docstring.

        Args:
            tensordict: the env's keys for the whole batch plus ``is_init``.

        Returns:
            ``human_action``, ``human_rt`` ``[*batch, 1]`` and ``human_decided``
            ``[*batch, 1]`` for the batch.
        """
        batch = tensordict.batch_size
        missing = [key for key in (*self.in_keys, "is_init") if key not in tensordict.keys()]
        if missing:
            raise KeyError(f"{type(self).__name__} reads {missing}, which the env did not write")
        flat = tensordict.select(*self.in_keys, "is_init").reshape(-1)
        n_envs, device = flat.batch_size[0], tensordict.device
        restart = flat.get("is_init").reshape(n_envs)
        frame = flat.select(*self.in_keys)
        if self.streams is None:
            self.reset(None)
        stepped = tensordict.get("_step", None)  # TorchRL's partial steps: the others stand still
        active = torch.ones_like(restart) if stepped is None else stepped.reshape(n_envs) | restart
        if self._state is None or self._state.batch_size[0] != n_envs:
            self._state = self._fresh_state(frame)
            restart = active = torch.ones_like(restart)
        state = self._state
        self._remember(frame, restart, active)
        u = self.streams.uniform(torch.Size([n_envs]), device, active)

        wait = torch.where(restart, 0, state["wait"])
        decide = (wait <= 0) & active
        if decide.any():
            rows = decide.nonzero().squeeze(-1)
            u_rows = u[rows]
            period = self.decision_period
            rt = ex_gaussian_rt(self.traits, self.workload(frame[rows]), u_rows[:, 3:])
            random_choice = (u_rows[:, 2] * self.n_choices).long().clamp_max(self.n_choices - 1)
            planned = self.plan(self._perceived(rows, rt))
            if planned.dim() == 1:
                planned = planned.unsqueeze(-1).expand(-1, period)
            new = torch.where((u_rows[:, 1] < self.traits.eps).unsqueeze(-1), random_choice.unsqueeze(-1), planned)
            lagged = (u_rows[:, 0] < self.traits.lag) & ~restart[rows]
            held = state["choice"][rows].unsqueeze(-1).expand(-1, period)
            state["plan"][rows] = torch.where(lagged.unsqueeze(-1), held, new)
            state["since"][rows] = 0
            state["rt"][rows] = rt
            excess = (rt - self.traits.lapse_threshold).clamp_min(0.0)
            lapse = torch.round(excess / self.frame_seconds).long()
            wait[rows] = period + lapse
        step = state["since"].clamp_max(self.decision_period - 1).unsqueeze(-1)
        choice = torch.where(active, state["plan"].gather(-1, step).squeeze(-1), state["choice"])
        state["choice"] = choice
        state["issued"].scatter_(1, state["slot"].unsqueeze(-1), choice.unsqueeze(-1))
        state["since"] = state["since"] + active.long()
        state["wait"] = wait - active.long()

        return TensorDict(
            {
                "human_action": self.action(choice).reshape(*batch, -1),
                "human_rt": state["rt"].reshape(*batch, 1).clone(),
                "human_decided": decide.reshape(*batch, 1),
            },
            batch,
            device=device,
        )
