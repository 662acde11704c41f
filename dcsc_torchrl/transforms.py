"""The human side of DC-SC as environment transforms.

From the agent's point of view the operator's action is part of what it observes, so
the operator lives on the environment side:

- :class:`HumanOperatorTransform` asks an operator (simulated or a person) for its
  action on every frame and writes ``human_action``, ``human_rt``, ``human_decided``;
- :class:`HumanConfidenceTransform` keeps the operator's knowledge level per
  environment (Eq. 6, updated on decision frames) and writes ``knowledge`` and
  ``human_confidence`` (Eq. 9);
- :class:`FirstEpisodeOnly` stops stepping an environment once its first episode is
  over (TorchRL's partial steps), for runs that record one episode per environment.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs.transforms import Transform

from dcsc_torchrl.checks import check_in_range, check_values, defer_check
from dcsc_torchrl.confidence import human_confidence, knowledge_update


@runtime_checkable
class HumanOperator(Protocol):
    """What an operator is.

    ``__call__`` receives the environment's TensorDict for the whole batch: every
    observation key the env writes (``observation`` holds the full state, the target
    included) plus ``is_init`` (``[*batch, 1]`` bool, True on an episode's first
    frame, where the operator must drop what it held). It returns a TensorDict with
    ``human_action`` (one-hot ``[*batch, n]`` or ``[*batch, d]``), ``human_rt``
    (``[*batch, 1]`` seconds) and ``human_decided`` (``[*batch, 1]`` bool: a new
    decision on this frame). Where a call concerns only part of the batch, the
    TensorDict also holds ``"_step"`` (``[*batch]`` bool): on a partial reset True for
    the envs reset, on a partial step (TorchRL's partial steps, e.g. under
    :class:`FirstEpisodeOnly`) True for the envs stepped. For the others the call is
    no new frame: their answer is not used, and an operator that keeps time per env
    (:class:`~dcsc_torchrl.humans.traits.SimulatedHuman`) leaves them where they were.
    """

    def reset(self, seed: int | None) -> None:
        """Re-seeds the operator's random state and forgets everything it held."""

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Decides the operator's action for every environment of the batch."""


def _reset_mask(transform: Transform, tensordict: TensorDictBase, batch_shape: torch.Size) -> torch.Tensor:
    """The ``[*batch, 1]`` bool mask of the environments being reset."""
    reset = None
    if tensordict is not None:
        reset = tensordict.get(transform.parent.reset_keys[0], None)
    if reset is None:
        return torch.ones(*batch_shape, 1, dtype=torch.bool)
    return reset.reshape(*batch_shape, 1)


def _check_one_hot(name: str, action: torch.Tensor) -> None:
    """Refuses a frame of ``action`` ``[*batch, n]`` that is not one-hot (one 1, the rest 0); no device sync."""
    rows = ((action == 0) | (action == 1)).all(-1) & (action.sum(-1) == 1)
    requirement = "must be one-hot for a OneHot action spec (one 1, the rest 0)"
    if action.device.type != "cpu":
        defer_check(f"{name} {requirement}: a frame on {action.device} was not (read back without a sync)", rows.all())
    elif not bool(rows.all()):
        index = tuple(int(i) for i in (~rows).nonzero()[0])
        raise ValueError(f"{name} {requirement}, got {action[index].tolist()} at batch index {index}")


class HumanOperatorTransform(Transform):
    """Writes the operator's decision keys on every frame (reset and step).

    This is where the env's frame and the operator's answer enter, so they are checked
    here, on every frame, at one reduction per tensor and no device sync
    (:func:`~dcsc_torchrl.checks.check_values`): the observation the operator is shown
    must be finite (so a NaN from the env is named as such, not as a NaN RT),
    ``human_action`` must have the action spec's shape, be finite (a NaN is never cast to
    an integer) and, for a ``OneHot`` spec, be one-hot; ``human_rt`` finite and ``>= 0``;
    ``human_decided`` a bool tensor (a float is never read as a decision).

    Args:
        operator: any :class:`HumanOperator`.
        seed: the operator's seed, used at the first reset (``set_seed`` re-seeds).
        action_key: the env's action key; ``human_action`` gets its spec.
        out_keys: ``human_action``, ``human_rt``, ``human_decided``.

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from dcsc_torchrl.humans import RandomOperator
        >>> env = TransformedEnv(GymEnv("LunarLander-v3"),
        ...                      HumanOperatorTransform(RandomOperator(n_actions=4), seed=0))
        >>> td = env.reset()
        >>> sorted(k for k in td.keys() if k.startswith("human"))
        ['human_action', 'human_decided', 'human_rt']
    """

    def __init__(
        self,
        operator: HumanOperator,
        *,
        seed: int | None = None,
        action_key: str = "action",
        out_keys: tuple[str, str, str] = ("human_action", "human_rt", "human_decided"),
    ) -> None:
        if not isinstance(operator, HumanOperator):
            raise TypeError(
                f"operator must have reset(seed) and __call__(tensordict); got {type(operator).__name__}"
            )
        super().__init__(in_keys=["observation"], out_keys=list(out_keys))
        self.operator = operator
        self.seed = seed
        self.action_key = action_key
        self._seeded = False
        self._action_shape_dtype: tuple[torch.Size, torch.dtype] | None = None

    def set_seed(self, seed: int | None) -> None:
        """Re-seeds the operator (its RNG state is its own, not the env's)."""
        self.seed = seed
        self.operator.reset(seed)
        self._seeded = True

    def _ask(self, tensordict: TensorDictBase, is_init: torch.Tensor,
             stepped: torch.Tensor | None = None) -> TensorDictBase:
        if not self._seeded:
            self.set_seed(self.seed)
        for key in self.in_keys:
            observation = tensordict.get(key, None)
            if observation is not None:
                check_values(f"the env's {key!r} (before the operator saw it)", observation)
        query = tensordict.copy()
        query.set("is_init", is_init)
        if stepped is not None:
            query.set("_step", stepped.reshape(query.batch_size))
        answer = self.operator(query)
        action_key, rt_key, decided_key = self.out_keys
        operator = type(self.operator).__name__
        for key in self.out_keys:
            if answer.get(key, None) is None:
                raise KeyError(f"the operator ({operator}) did not answer {key!r}")
        if self._action_shape_dtype is None:  # a spec lookup is slow: once, not every frame
            spec = self.parent.full_action_spec[self.action_key]
            self._action_shape_dtype = (spec.shape, spec.dtype, isinstance(spec, OneHot))
        shape, dtype, one_hot = self._action_shape_dtype
        action = answer.get(action_key)
        if action.shape != shape:
            raise ValueError(f"the operator's {action_key} has shape {tuple(action.shape)}, expected {tuple(shape)}")
        check_values(f"the operator's {action_key} ({operator})", action)
        if one_hot:
            _check_one_hot(f"the operator's {action_key} ({operator})", action)
        rt = check_values(f"the operator's {rt_key} ({operator})", answer.get(rt_key), 0.0)
        decided = answer.get(decided_key)
        if decided.dtype != torch.bool:
            raise ValueError(f"the operator's {decided_key} ({operator}) must be a bool tensor, got {decided.dtype}")
        tensordict.set(action_key, action.to(dtype))
        tensordict.set(rt_key, rt.to(torch.get_default_dtype()).reshape(*tensordict.batch_size, 1))
        tensordict.set(decided_key, decided.reshape(*tensordict.batch_size, 1))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        reset = _reset_mask(self, tensordict, tensordict_reset.batch_size)
        # a partial reset is no new frame for the envs that go on: only those reset take part
        return self._ask(tensordict_reset, reset, None if reset.all() else reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        is_init = torch.zeros(*next_tensordict.batch_size, 1, dtype=torch.bool, device=next_tensordict.device)
        return self._ask(next_tensordict, is_init, tensordict.get("_step", None))

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._action_shape_dtype = None  # the specs are being (re)built
        action_key, rt_key, decided_key = self.out_keys
        shape = observation_spec.shape
        device = observation_spec.device
        observation_spec[action_key] = self.parent.full_action_spec[self.action_key].clone()
        observation_spec[rt_key] = Unbounded(shape=(*shape, 1), device=device)
        observation_spec[decided_key] = Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device)
        return observation_spec


class HumanConfidenceTransform(Transform):
    """Keeps the operator's knowledge k per env (Eq. 6) and writes b_h(k) (Eq. 9).

    k starts at ``k0`` on every episode reset (a new scenario is a new task), or carries
    over when ``persist=True``; it is updated by :func:`knowledge_update` only on frames
    where ``human_decided`` is true, with that decision's ``human_rt``. ``knowledge`` is
    declared in the observation and state specs (like TorchRL's ``StepCounter``), so it
    survives partial resets and ``SerialEnv``.

    Args:
        p: probability of an impossible task (Eq. 7), in [0, 1).
        eta: eta of Eq. 7, in (0, 1).
        delta1: delta_1 of Eq. 8, > 0.
        K: the knowledge cap of Eq. 6 (task difficulty), > 0.
        t_d: upper limit of a normal reaction time in seconds, > 0.
        k0: knowledge at an episode's start, in [0, K].
        mode: ``"decay"`` (default) or ``"paper"``, see :func:`knowledge_update`.
        k_floor: floor for mode ``"paper"``.
        cap: ``"min"`` (default: Eq. 6's first case caps k at K, so a late decision still
            lowers it) or ``"absorbing"`` (the strict reading), see :func:`knowledge_update`.
        persist: carry k across episodes instead of restarting at k0.
        in_keys: ``human_rt``, ``human_decided``.
        out_keys: ``knowledge``, ``human_confidence``.
    """

    def __init__(
        self,
        p: float = 0.1,
        eta: float = 0.6,
        delta1: float = 2.0,
        K: float = 15.0,
        t_d: float = 1.0,
        k0: float = 0.01,
        mode: str = "decay",
        *,
        k_floor: float = 1e-3,
        cap: str = "min",
        persist: bool = False,
        in_keys: tuple[str, str] = ("human_rt", "human_decided"),
        out_keys: tuple[str, str] = ("knowledge", "human_confidence"),
    ) -> None:
        super().__init__(in_keys=list(in_keys), out_keys=list(out_keys))
        check_in_range("p", p, 0.0, 1.0, low_inclusive=True, high_inclusive=False)
        check_in_range("eta", eta, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
        check_in_range("delta1", delta1, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        check_in_range("K", K, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        check_in_range("t_d", t_d, 0.0, float("inf"), low_inclusive=False, high_inclusive=False)
        check_in_range("k0", k0, 0.0, K, low_inclusive=True, high_inclusive=True)
        if mode not in ("decay", "paper"):
            raise ValueError(f"mode must be 'decay' or 'paper', got {mode!r}")
        if cap not in ("min", "absorbing"):
            raise ValueError(f"cap must be 'min' or 'absorbing', got {cap!r}")
        self.p, self.eta, self.delta1 = p, eta, delta1
        self.K, self.t_d, self.k0 = K, t_d, k0
        self.mode, self.k_floor, self.cap, self.persist = mode, k_floor, cap, persist

    def _write(self, tensordict: TensorDictBase, knowledge: torch.Tensor) -> TensorDictBase:
        knowledge_key, confidence_key = self.out_keys
        tensordict.set(knowledge_key, knowledge)
        tensordict.set(confidence_key, human_confidence(knowledge, self.p, self.eta, self.delta1))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        reset = _reset_mask(self, tensordict, batch)
        fresh = torch.full((*batch, 1), float(self.k0), device=reset.device)
        previous = None if tensordict is None else tensordict.get(self.out_keys[0], None)
        if previous is None:
            knowledge = fresh
        elif self.persist:
            knowledge = previous.reshape(*batch, 1)
        else:
            knowledge = torch.where(reset, fresh, previous.reshape(*batch, 1))
        return self._write(tensordict_reset, knowledge)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        knowledge_key = self.out_keys[0]
        previous = tensordict.get(knowledge_key, None)
        if previous is None:
            raise KeyError(
                f"{knowledge_key!r} is missing from the step input: step with the TensorDict "
                "returned by reset()/step_mdp so the knowledge level is carried"
            )
        rt_key, decided_key = self.in_keys
        decided = next_tensordict.get(decided_key)
        updated = knowledge_update(
            previous, next_tensordict.get(rt_key), self.K, self.t_d, mode=self.mode, k_floor=self.k_floor,
            cap=self.cap,
        )
        return self._write(next_tensordict, torch.where(decided, updated, previous))

    def _knowledge_spec(self, shape: torch.Size, device: torch.device | None) -> Bounded:
        return Bounded(0.0, float(self.K), shape=(*shape, 1), device=device)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        knowledge_key, confidence_key = self.out_keys
        shape, device = observation_spec.shape, observation_spec.device
        observation_spec[knowledge_key] = self._knowledge_spec(shape, device)
        observation_spec[confidence_key] = Bounded(0.0, 1.0, shape=(*shape, 1), device=device)
        return observation_spec

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        if input_spec["full_state_spec"] is None:
            input_spec["full_state_spec"] = Composite(shape=input_spec.shape, device=input_spec.device)
        input_spec["full_state_spec"][self.out_keys[0]] = self._knowledge_spec(input_spec.shape, input_spec.device)
        return input_spec


class FirstEpisodeOnly(Transform):
    """Steps each env of a batch through its first episode only, then holds it.

    A batch of scenarios played until the last one ends (one recorded episode per env,
    :func:`~dcsc_torchrl.episodes.run_scenarios`) would otherwise go on stepping the
    envs already done: a collector resets them and they play a second episode nobody
    reads. Once an env's first episode is done, this transform leaves it out of every
    later step through TorchRL's partial steps: it writes ``"_step"`` (False for that
    env) into the step input, as :class:`~torchrl.envs.transforms.ConditionalSkip`
    does, and the batched envs of this project step only the envs it marks (a held env
    keeps its state, reward 0, not done), while :class:`HumanOperatorTransform` passes
    it on to the operator, which skips its planning there. The envs still running
    see exactly what they would without it: the policy still acts on the whole batch and
    every random stream is per env.

    For runs whose later frames matter (DC-SC's online updates learn from every frame)
    leave it out. A full reset (no ``"_reset"`` entry) starts every env afresh.

    Examples:
        >>> from dcsc_torchrl.batched_envs import make_uav_env
        >>> env = make_uav_env(2, scenario_seeds=[0, 1], max_steps=3, transforms=[FirstEpisodeOnly()])
        >>> times = env.rollout(5, break_when_any_done=False)["next", "time"][0].squeeze(-1)
        >>> [round(t, 1) for t in times.tolist()]  # three steps, the reset, then held there
        [0.1, 0.2, 0.3, 0.0, 0.0]
    """

    def __init__(self) -> None:
        super().__init__()
        self._over: torch.Tensor | None = None

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        full = tensordict is None or tensordict.get(self.parent.reset_keys[0], None) is None
        if full or self._over is None:
            self._over = torch.zeros(tensordict_reset.batch_size, dtype=torch.bool, device=tensordict_reset.device)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._over = self._over | next_tensordict.get("done").reshape(self._over.shape)
        return next_tensordict

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._over is not None and self._over.any():
            tensordict.set("_step", tensordict.get("_step", True) & ~self._over)
        return tensordict
