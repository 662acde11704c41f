"""The UAV task as a native, batched TorchRL env: its reward (:func:`step_reward`) and
:class:`UAVPathPlanningEnv`, a batch of scenarios stepped by the IIFDS flow."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dcsc_torchrl.envs.iifds import iifds_step
from dcsc_torchrl.envs.uav_scenarios import (
    _FRESH_SEED_HIGH,
    _FRESH_SEED_LOW,
    ACTION_HIGH,
    ARENA_HIGH,
    ARENA_LOW,
    DT,
    GOAL_RADIUS,
    HORIZON,
    N_OBSTACLE_PARAMS,
    N_OBSTACLES,
    V0,
    ObstacleParam,
    UAVScenario,
    obstacle_states,
    sample_scenarios,
)

THREAT_MARGIN = 0.4
"""Distance from a surface inside which the threat penalty applies."""
PROGRESS_REWARD = 10.0
"""Reward for the whole way: each step earns ``PROGRESS_REWARD (d - d') / d0``."""
TIME_COST = 0.02
"""Cost of every step (so a faster safe arrival scores more)."""
THREAT_COST = 0.05
"""Largest threat cost of a step, ``THREAT_COST (1 - d_s / THREAT_MARGIN)`` of the nearest surface."""
GOAL_REWARD = 10.0
COLLISION_REWARD = -50.0
"""Added on a collision or on leaving the arena. Any failed flight then returns less than
``PROGRESS_REWARD + COLLISION_REWARD`` = -40 and any arrival at least
``PROGRESS_REWARD + GOAL_REWARD - HORIZON (TIME_COST + THREAT_COST)`` = -15 (docs/envs.md)."""


def step_reward(
    position: Tensor,
    moved: Tensor,
    start: Tensor,
    goal: Tensor,
    d_surface: Tensor,
    failed: Tensor,
    success: Tensor,
    collision_reward: float = COLLISION_REWARD,
) -> Tensor:
    """The reward ``[...]`` of a step ``position -> moved`` (all ``[..., 3]``).

    ``PROGRESS_REWARD (d - d') / d0 - TIME_COST - THREAT_COST clamp(1 - min_k d_s,k /
    THREAT_MARGIN, 0, 1) + GOAL_REWARD success + collision_reward failed``, with ``d``,
    ``d'`` the distances to the goal before and after, ``d0`` the start's, and
    ``d_surface [..., K]`` the surface distances after. The progress terms of a flight
    add up to ``PROGRESS_REWARD (1 - d_T / d0)``: exactly ``PROGRESS_REWARD`` on arrival.
    """
    start_distance = (start - goal).norm(dim=-1)
    progress = ((position - goal).norm(dim=-1) - (moved - goal).norm(dim=-1)) / start_distance
    threat = (1.0 - d_surface.amin(-1) / THREAT_MARGIN).clamp(0.0, 1.0)
    return (
        PROGRESS_REWARD * progress
        - TIME_COST
        - THREAT_COST * threat
        + GOAL_REWARD * success.to(progress.dtype)
        + collision_reward * failed.to(progress.dtype)
    )


def _segment_point_distance(a: Tensor, b: Tensor, point: Tensor) -> Tensor:
    """Distance ``[...]`` from ``point`` to the segment ``a -> b`` (all ``[..., 3]``)."""
    ab = b - a
    s = ((point - a) * ab).sum(-1) / ab.square().sum(-1).clamp_min(1e-12)
    closest = a + s.clamp(0.0, 1.0).unsqueeze(-1) * ab
    return (point - closest).norm(dim=-1)


class UAVPathPlanningEnv(EnvBase):
    """Batched UAV path planning with the IIFDS flow (native TorchRL, CPU or GPU).

    Each of the N envs flies one scenario. Per step, with the obstacles at time ``t``:
    ``p' = p + DT ū(p; rho0, sigma0, tau)`` (:func:`dcsc_torchrl.envs.iifds.iifds_step`); the goal
    counts as reached if the segment ``p -> p'`` passes within ``GOAL_RADIUS`` (the UAV
    then stops on the goal); the obstacles move to ``t + DT`` and the new state is
    scored:

    - every step earns ``10 (d - d') / d0`` (progress to the goal), costs 0.02, and up to
      0.05 more inside 0.4 of the nearest surface (:func:`step_reward`);
    - collision (``d_s <= 0`` for any obstacle) or leaving the arena: −50, ends;
    - goal reached (without collision): +10, ends with ``success``;
    - ``horizon`` steps (500): truncated.

    Keys (per env; all float32 unless noted): ``action`` ``[3]`` in ``[0, 3]`` (clipped
    there); ``observation`` ``[9]`` = vector to the nearest obstacle's surface (the one
    with the smallest ``d_s``), vector to the goal, that obstacle's velocity;
    ``success``, ``collision``, ``out_of_bounds`` ``[1]`` bool; ``path_length`` ``[1]``
    (``Σ ||p' - p||``); ``position``, ``goal`` ``[3]``; ``time`` ``[1]`` in seconds
    (``step * DT``); ``obstacle_params`` ``[K, N_OBSTACLE_PARAMS]`` (for
    :func:`obstacle_states`); ``scenario_seed`` ``[1]`` int64; ``reward`` ``[1]``;
    ``done``, ``terminated``, ``truncated`` ``[1]`` bool.

    Args:
        num_envs: batch size N; defaults to ``len(scenario_seeds)``, else 1.
        scenario_seeds: if given, env ``i`` replays scenario ``scenario_seeds[i]`` at
            every reset (the validation scenarios are seeds 0..49); otherwise every reset
            of env ``i`` draws a fresh scenario seed (>= 2**31, so never a validation
            seed) from the env's generator, seeded by :meth:`set_seed`.
        device: where the state and the outputs live (default CPU).
        n_obstacles: obstacles per scenario.
        scenario_fn: maps int64 scenario seeds ``[S]`` to a :class:`UAVScenario` with
            leading dim S (default :func:`sample_scenarios` with ``n_obstacles``); a hook
            for custom scenario families and tests.
        seed: seed of the generator drawing fresh scenario seeds (default: drawn from
            torch's global RNG).
        collision_reward: added on a collision or on leaving the arena (default −50:
            below every arrival, see :func:`step_reward` and docs/envs.md).
        horizon: steps before truncation (500).

    Raises:
        ValueError: on an empty batch or ``num_envs != len(scenario_seeds)``.

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = UAVPathPlanningEnv(8, seed=0)
        >>> check_env_specs(env)
        >>> td = env.reset()
        >>> td["observation"].shape
        torch.Size([8, 9])
    """

    def __init__(
        self,
        num_envs: int | None = None,
        *,
        scenario_seeds: Sequence[int] | None = None,
        device: torch.device | str | None = None,
        n_obstacles: int = N_OBSTACLES,
        scenario_fn: Callable[[Tensor], UAVScenario] | None = None,
        seed: int | None = None,
        collision_reward: float = COLLISION_REWARD,
        horizon: int = HORIZON,
    ) -> None:
        if scenario_seeds is not None:
            scenario_seeds = [int(s) for s in scenario_seeds]
            if num_envs is None:
                num_envs = len(scenario_seeds)
            elif num_envs != len(scenario_seeds):
                raise ValueError(
                    f"num_envs={num_envs} but {len(scenario_seeds)} scenario_seeds were given"
                )
        num_envs = 1 if num_envs is None else num_envs
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        device = torch.device("cpu") if device is None else torch.device(device)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.n_obstacles = n_obstacles
        self.collision_reward = collision_reward
        self.horizon = horizon
        self.scenario_fn = scenario_fn or partial(sample_scenarios, n_obstacles=n_obstacles)
        self._generator = torch.Generator()
        self._set_seed(int(torch.randint(2**62, ())) if seed is None else seed)
        self._make_specs()
        self._init_state()
        fixed = None
        if scenario_seeds is not None:
            fixed = self._load(torch.tensor(scenario_seeds, dtype=torch.int64))
        # The replayed scenarios, if any (buffers too, so that ``env.to`` moves them).
        for name in ("seed", "start", "goal", "obstacle_params"):
            value = None if fixed is None else getattr(fixed, name)
            self.register_buffer(f"_fixed_{name}", value, persistent=False)

    def _make_specs(self) -> None:
        batch, device = self.batch_size, self.device

        def flag() -> Categorical:
            return Categorical(2, shape=(*batch, 1), dtype=torch.bool, device=device)

        self.action_spec = Bounded(0.0, ACTION_HIGH, shape=(*batch, 3), device=device)
        self.observation_spec = Composite(
            observation=Unbounded((*batch, 9), device=device),
            success=flag(),
            collision=flag(),
            out_of_bounds=flag(),
            path_length=Unbounded((*batch, 1), device=device),
            position=Unbounded((*batch, 3), device=device),
            goal=Unbounded((*batch, 3), device=device),
            time=Unbounded((*batch, 1), device=device),
            obstacle_params=Unbounded((*batch, self.n_obstacles, N_OBSTACLE_PARAMS), device=device),
            scenario_seed=Unbounded((*batch, 1), dtype=torch.int64, device=device),
            shape=batch,
            device=device,
        )
        self.reward_spec = Unbounded((*batch, 1), device=device)
        self.done_spec = Composite(
            done=flag(), terminated=flag(), truncated=flag(), shape=batch, device=device
        )

    def _init_state(self) -> None:
        """Per-env state, as non-persistent buffers so that ``env.to(device)`` moves it."""
        n, device = self.batch_size[0], self.device
        state = {
            "_position": torch.zeros(n, 3),
            "_start": torch.zeros(n, 3),
            "_goal": torch.zeros(n, 3),
            "_params": torch.zeros(n, self.n_obstacles, N_OBSTACLE_PARAMS),
            "_seed": torch.zeros(n, dtype=torch.int64),
            "_steps": torch.zeros(n, dtype=torch.int64),
            "_path_length": torch.zeros(n),
            "_success": torch.zeros(n, dtype=torch.bool),
            "_collision": torch.zeros(n, dtype=torch.bool),
            "_out_of_bounds": torch.zeros(n, dtype=torch.bool),
            "_truncated": torch.zeros(n, dtype=torch.bool),
            "_centres": torch.zeros(n, self.n_obstacles, 3),  # obstacles at the current time
            "_velocities": torch.zeros(n, self.n_obstacles, 3),
            "_arena_low": torch.tensor(ARENA_LOW),
            "_arena_high": torch.tensor(ARENA_HIGH),
        }
        for name, value in state.items():
            self.register_buffer(name, value.to(device), persistent=False)

    def _load(self, seeds: Tensor) -> UAVScenario:
        """The scenarios of ``seeds [S]`` from ``scenario_fn``, checked, on the device."""
        scenarios = self.scenario_fn(seeds)
        expected = (len(seeds), self.n_obstacles, N_OBSTACLE_PARAMS)
        if tuple(scenarios.obstacle_params.shape) != expected:
            raise ValueError(
                f"scenario_fn gave obstacle_params of shape "
                f"{tuple(scenarios.obstacle_params.shape)}, expected {expected}"
            )
        return UAVScenario(
            seed=scenarios.seed.to(self.device, torch.int64),
            start=scenarios.start.to(self.device, torch.float32),
            goal=scenarios.goal.to(self.device, torch.float32),
            obstacle_params=scenarios.obstacle_params.to(self.device, torch.float32),
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._generator.manual_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            rows = torch.arange(self.batch_size[0], device=self.device)
        else:
            rows = reset.reshape(self.batch_size[0], -1).any(-1).nonzero().squeeze(-1)
        if rows.numel():
            self._start_episodes(rows)
            centres, velocities, _ = obstacle_states(self._params, self._steps * DT)
            self._centres.copy_(centres)
            self._velocities.copy_(velocities)
        return self._output()

    def _start_episodes(self, rows: Tensor) -> None:
        if self._fixed_seed is not None:
            start, goal = self._fixed_start[rows], self._fixed_goal[rows]
            params, seed = self._fixed_obstacle_params[rows], self._fixed_seed[rows]
        else:
            fresh = torch.randint(
                _FRESH_SEED_LOW, _FRESH_SEED_HIGH, (rows.numel(),), generator=self._generator
            )
            scenarios = self._load(fresh)
            start, goal = scenarios.start, scenarios.goal
            params, seed = scenarios.obstacle_params, scenarios.seed
        self._start[rows] = start
        self._position[rows] = start
        self._goal[rows] = goal
        self._params[rows] = params
        self._seed[rows] = seed
        self._steps[rows] = 0
        self._path_length[rows] = 0.0
        for flag in (self._success, self._collision, self._out_of_bounds, self._truncated):
            flag[rows] = False

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        reward = self.advance(tensordict.get("action"), tensordict.get("_step", None))
        out = self._output()
        out.set("reward", reward.unsqueeze(-1))
        return out

    _MOVING_STATE = ("_position", "_steps", "_path_length", "_success", "_collision", "_out_of_bounds",
                     "_truncated", "_centres", "_velocities")
    """What one step changes (:meth:`advance`), and a held scenario keeps."""

    def advance(self, action: Tensor, stepped: Tensor | None = None) -> Tensor:
        """Moves every scenario (or those of ``stepped``) one step in place and returns the rewards ``[N]``.

        The physics of :meth:`step` without TorchRL's bookkeeping (no done handling, no
        reset); :class:`UAVPathPlanningGymEnv` drives it directly, then reads
        :meth:`observation` and the state.

        Args:
            action: ``[N, 3]``, clipped to ``[0, ACTION_HIGH]``.
            stepped: ``[N]`` bool (TorchRL's partial steps, ``"_step"``), ``None`` for all:
                the scenarios left out keep their state, time included, and earn 0.
        """
        held = None if stepped is None else (~stepped.reshape(-1)).nonzero().squeeze(-1)
        kept = {} if held is None else {name: getattr(self, name)[held].clone() for name in self._MOVING_STATE}
        reward = self._move(action)
        for name, value in kept.items():
            getattr(self, name)[held] = value
        return reward if held is None else reward.index_fill(0, held, 0.0)

    def _move(self, action: Tensor) -> Tensor:
        rho0, sigma0, tau = action.clamp(0.0, ACTION_HIGH).unbind(-1)
        position, goal = self._position, self._goal
        radii = self._params[..., ObstacleParam.RADIUS]
        moved = iifds_step(
            position, goal, self._centres, radii, self._velocities, rho0, sigma0, tau, DT, V0
        )
        reached = _segment_point_distance(position, moved, goal) <= GOAL_RADIUS
        moved = torch.where(reached.unsqueeze(-1), goal, moved)

        self._steps += 1
        centres, velocities, _ = obstacle_states(self._params, self._steps * DT)
        d_surface = (moved.unsqueeze(-2) - centres).norm(dim=-1) - radii
        collision = (d_surface <= 0).any(-1)
        out_of_bounds = ((moved < self._arena_low) | (moved > self._arena_high)).any(-1)
        failed = collision | out_of_bounds
        success = reached & ~failed

        reward = step_reward(
            position, moved, self._start, goal, d_surface, failed, success, self.collision_reward
        )

        self._path_length += (moved - position).norm(dim=-1)
        self._position.copy_(moved)
        self._success.copy_(success)
        self._collision.copy_(collision)
        self._out_of_bounds.copy_(out_of_bounds)
        torch.bitwise_and(self._steps >= self.horizon, ~(failed | success), out=self._truncated)
        self._centres.copy_(centres)
        self._velocities.copy_(velocities)
        return reward

    def observation(self) -> Tensor:
        """The observation ``[N, 9]`` of the current state (see the class docstring)."""
        position, goal = self._position, self._goal
        radii = self._params[..., ObstacleParam.RADIUS]
        offset = self._centres - position.unsqueeze(-2)
        distance = offset.norm(dim=-1)
        nearest = (distance - radii).argmin(-1, keepdim=True)
        gather = nearest.unsqueeze(-1).expand(-1, -1, 3)
        to_centre = offset.gather(-2, gather).squeeze(-2)
        centre_distance = distance.gather(-1, nearest)
        to_surface = (
            to_centre
            * (centre_distance - radii.gather(-1, nearest))
            / (centre_distance.clamp_min(1e-9))
        )
        return torch.cat(
            [to_surface, goal - position, self._velocities.gather(-2, gather).squeeze(-2)],
            dim=-1,
        )

    def _output(self) -> TensorDictBase:
        """Observation and bookkeeping keys of the current state."""
        position, goal = self._position, self._goal
        observation = self.observation()
        terminated = self._success | self._collision | self._out_of_bounds
        # The state tensors are updated in place: the output holds copies.
        return TensorDict(
            {
                "observation": observation,
                "success": self._success.unsqueeze(-1).clone(),
                "collision": self._collision.unsqueeze(-1).clone(),
                "out_of_bounds": self._out_of_bounds.unsqueeze(-1).clone(),
                "path_length": self._path_length.unsqueeze(-1).clone(),
                "position": position.clone(),
                "goal": goal.clone(),
                "time": (self._steps * DT).to(torch.float32).unsqueeze(-1),
                "obstacle_params": self._params.clone(),
                "scenario_seed": self._seed.unsqueeze(-1).clone(),
                "terminated": terminated.unsqueeze(-1),
                "truncated": self._truncated.unsqueeze(-1).clone(),
                "done": (terminated | self._truncated).unsqueeze(-1),
            },
            batch_size=self.batch_size,
            device=self.device,
        )
