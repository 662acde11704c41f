"""The decision loop every simulated operator runs (docs/operators.md): decision interval,
perception delay, noise, lag, reaction times and lapses around a task's controller."""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from typing import Any, TypeVar

import torch
from tensordict import TensorDict, TensorDictBase

from dcsc_torchrl.humans.reaction_time import ex_gaussian_rt
from dcsc_torchrl.humans.streams import EnvStreams
from dcsc_torchrl.humans.traits import MAX_PERCEPTION_DELAY, PRESETS, OperatorTraits

_Operator = TypeVar("_Operator", bound="SimulatedHuman")


@dataclasses.dataclass
class _LoopState:
    """Every env's place in its decision loop, ``[N]`` tensors (``plan`` ``[N, decision_period]``,
    ``issued`` ``[N, memory_frames]``, each ``seen`` entry ``[N, memory_frames, ...]``)."""

    choice: torch.Tensor
    """The key (choice) pressed now."""
    plan: torch.Tensor
    """The choices of the current decision interval, one per frame."""
    since: torch.Tensor
    """Frames since the last decision."""
    issued: torch.Tensor
    """Ring of the choices made on the remembered frames."""
    rt: torch.Tensor
    """The last decision's reaction time (s)."""
    wait: torch.Tensor
    """Frames until the next decision."""
    age: torch.Tensor
    """Frames since the episode's start."""
    slot: torch.Tensor
    """Where the current frame sits in the rings."""
    seen: dict[str, torch.Tensor]
    """Ring of the frames seen, per env key."""


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
        self._state: _LoopState | None = None

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

    def _fresh_state(self, frame: dict[str, torch.Tensor], device: torch.device | None) -> _LoopState:
        n_envs = next(iter(frame.values())).shape[0]

        def zeros(*shape: int, dtype: torch.dtype = torch.int64) -> torch.Tensor:
            return torch.zeros(n_envs, *shape, dtype=dtype, device=device)

        return _LoopState(
            choice=zeros(), plan=zeros(self.decision_period), since=zeros(), issued=zeros(self.memory_frames),
            rt=zeros(dtype=torch.get_default_dtype()), wait=zeros(), age=zeros(), slot=zeros(),
            seen={key: value.unsqueeze(1).expand(n_envs, self.memory_frames, *value.shape[1:]).clone()
                  for key, value in frame.items()},
        )

    def _remember(self, frame: dict[str, torch.Tensor], restart: torch.Tensor, active: torch.Tensor) -> None:
        """Stores the current frame of the ``active`` envs in their ring of past frames; counts
        their frames since reset."""
        state = self._state
        state.slot = torch.where(active, (state.slot + 1) % self.memory_frames, state.slot)
        rows = active.nonzero().squeeze(-1)
        slots = state.slot[rows]
        for key, value in frame.items():
            state.seen[key][rows, slots] = value[rows]
        state.age = torch.where(restart, 0, state.age + active.long())

    def _perceived(self, rows: torch.Tensor, rt: torch.Tensor) -> TensorDictBase:
        """What the deciding envs ``rows`` saw one RT ago, carried forward by :meth:`anticipate`."""
        state = self._state
        delay = torch.round(rt / self.frame_seconds).long()
        delay = torch.minimum(delay.clamp_max(self.memory_frames - 1), state.age[rows])
        slots = (state.slot[rows] - delay) % self.memory_frames
        since = torch.arange(int(delay.max()), device=delay.device)
        issued_slots = (slots.unsqueeze(-1) + since) % self.memory_frames
        issued = state.issued[rows.unsqueeze(-1), issued_slots]
        seen = TensorDict({key: value[rows, slots] for key, value in state.seen.items()}, [len(rows)],
                          device=rows.device)
        return self.anticipate(seen, issued, delay)

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
        n_envs, device = batch.numel(), tensordict.device
        n_batch_dims = len(batch)

        def flat(key: str) -> torch.Tensor:
            value = tensordict.get(key)
            return value.reshape(n_envs, *value.shape[n_batch_dims:])

        restart = flat("is_init").reshape(n_envs)
        frame = {key: flat(key) for key in self.in_keys}
        if self.streams is None:
            self.reset(None)
        stepped = tensordict.get("_step", None)  # TorchRL's partial steps: the others stand still
        active = torch.ones_like(restart) if stepped is None else stepped.reshape(n_envs) | restart
        if self._state is None or self._state.choice.shape[0] != n_envs:
            self._state = self._fresh_state(frame, device)
            restart = active = torch.ones_like(restart)
        state = self._state
        self._remember(frame, restart, active)
        u = self.streams.uniform(torch.Size([n_envs]), device, active)

        wait = torch.where(restart, 0, state.wait)
        decide = (wait <= 0) & active
        if decide.any():
            rows = decide.nonzero().squeeze(-1)
            u_rows = u[rows]
            period = self.decision_period
            now = TensorDict({key: value[rows] for key, value in frame.items()}, [len(rows)], device=device)
            rt = ex_gaussian_rt(self.traits, self.workload(now), u_rows[:, 3:])
            random_choice = (u_rows[:, 2] * self.n_choices).long().clamp_max(self.n_choices - 1)
            planned = self.plan(self._perceived(rows, rt))
            if planned.dim() == 1:
                planned = planned.unsqueeze(-1).expand(-1, period)
            new = torch.where((u_rows[:, 1] < self.traits.eps).unsqueeze(-1), random_choice.unsqueeze(-1), planned)
            lagged = (u_rows[:, 0] < self.traits.lag) & ~restart[rows]
            held = state.choice[rows].unsqueeze(-1).expand(-1, period)
            state.plan[rows] = torch.where(lagged.unsqueeze(-1), held, new)
            state.since[rows] = 0
            state.rt[rows] = rt.to(state.rt.dtype)
            wait[rows] = period
            if self.traits.lapses:
                excess = (rt - self.traits.lapse_threshold).clamp_min(0.0)
                wait[rows] += torch.round(excess / self.frame_seconds).long()
        step = state.since.clamp_max(self.decision_period - 1).unsqueeze(-1)
        choice = torch.where(active, state.plan.gather(-1, step).squeeze(-1), state.choice)
        state.choice = choice
        state.issued.scatter_(1, state.slot.unsqueeze(-1), choice.unsqueeze(-1))
        state.since = state.since + active.long()
        state.wait = wait - active.long()

        return TensorDict(
            {
                "human_action": self.action(choice).reshape(*batch, -1),
                "human_rt": state.rt.reshape(*batch, 1).clone(),
                "human_decided": decide.reshape(*batch, 1),
            },
            batch,
            device=device,
        )
