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

:class:`OperatorTraits` holds the parameters and :data:`PRESETS` the named surrogate
pilots; the RT law is :mod:`~dcsc_torchrl.humans.reaction_time`, the per-environment
random streams :mod:`~dcsc_torchrl.humans.streams`, and the decision loop both
:class:`~dcsc_torchrl.humans.SimulatedPilot` and :class:`~dcsc_torchrl.humans.SimulatedOperator`
run (they add only their controller) :mod:`~dcsc_torchrl.humans.decision_loop`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["MAX_PERCEPTION_DELAY", "PRESETS", "OperatorTraits"]


@dataclass(frozen=True)
class OperatorTraits:
    """The traits of a simulated person (docs/operators.md); every field is a parameter.

    RT per decision is ex-Gaussian: ``RT = rt_mu (1 + workload_gain * workload)
    + rt_sigma * N(0, 1) + rt_tau * Exp(1)``, floored at 0, so at zero workload its mean
    is ``rt_mu + rt_tau`` and its variance ``rt_sigma^2 + rt_tau^2``.

    Attributes:
        decision_interval: seconds between decisions (rounded to whole frames, at least
            one: 0 decides every frame); the key is held in between.
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
        lapses: a decision slower than ``lapse_threshold`` delays the next one (a person);
            ``False``: the RT is drawn and reported (so b_h has something to read) but
            never changes what the operator does (the literature's surrogate pilots).
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
    lapses: bool = True

    def __post_init__(self) -> None:
        checks = {
            "decision_interval": self.decision_interval >= 0,
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
    "surrogate_expert": OperatorTraits(decision_interval=0.0, perceive_delayed=False, lapses=False),
    "surrogate_noisy": OperatorTraits(decision_interval=0.0, perceive_delayed=False, lapses=False, eps=0.3),
    "surrogate_laggy": OperatorTraits(decision_interval=0.0, perceive_delayed=False, lapses=False, lag=0.85),
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
frame pair: an explicit upper bound, not a person.

The ``surrogate_*`` presets are the peers' surrogate pilots exactly as their papers define
them, so our numbers can stand beside theirs (docs/operators.md): the undelayed
controller queried every frame (``surrogate_expert``), corrupted with a uniformly random
choice with probability 0.3 on every frame (``surrogate_noisy``: the diffusion shared
autonomy of Yoneda et al., 2023; Reddy et al., 2018, corrupt with 0.15 per factor) or
repeating its previous choice with probability 0.85 on every frame (``surrogate_laggy``:
Yoneda et al.; Reddy et al. use 0.8). They draw the expert's RTs for b_h to read, but
have no lapses: nothing of a person's timing changes what they press."""
