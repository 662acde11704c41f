"""A simulated UAV operator: foresees the obstacles, picks IIFDS coefficients."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from dcsc_torchrl.envs.iifds import iifds_step
from dcsc_torchrl.envs.uav import (
    ACTION_HIGH,
    ARENA_HIGH,
    ARENA_LOW,
    DT,
    GOAL_RADIUS,
    obstacle_states,
)
from dcsc_torchrl.humans.decision_loop import SimulatedHuman
from dcsc_torchrl.humans.lookahead import lookahead_scores
from dcsc_torchrl.humans.streams import _GOLDEN, _mix, _shift_right, _signed
from dcsc_torchrl.humans.traits import PRESETS, OperatorTraits

__all__ = ["DEFAULT_GRID", "SimulatedOperator"]

DEFAULT_GRID = tuple(itertools.product((0.5, 1.5, 2.5), (0.5, 1.5, 2.5), (0.0, 1.5, 3.0)))
"""The (rho0, sigma0, tau) candidates: 3 x 3 x 3 points of the action box [0, 3]^3 (tau
0, 1.5 and 3 turn the flow round one side of an obstacle, over or under it, and round the
other side)."""
_ARENA_LOW, _ARENA_HIGH = np.array(ARENA_LOW), np.array(ARENA_HIGH)  # the compiled look-ahead's arena


class SimulatedOperator(SimulatedHuman):
    """The paper's UAV operator (§6.1: "the human can anticipate the trajectories of moving obstacles").

    At a decision it tries every (rho0, sigma0, tau) of a small grid by rolling the
    IIFDS flow (:func:`dcsc_torchrl.envs.iifds.iifds_step`) forward ``horizon`` steps against the
    obstacles' predicted positions (:func:`dcsc_torchrl.envs.uav.obstacle_states` of the env's
    ``obstacle_params`` at ``time + h * DT``), every env x candidate at once (on the host one
    compiled loop, :mod:`dcsc_torchrl.humans.lookahead`; on a device torch operations,
    :meth:`rollout_scores`), and keeps the best score. Its foresight is imperfect: it sees each obstacle ``k`` moving with
    the velocity error ``e_k ~ N(0, lookahead_noise^2 I)`` (m/s), redrawn at every
    decision, so the centre it predicts ``s`` seconds ahead is ``c_k(t + s) + e_k s``,
    off by ``lookahead_noise * s * sqrt(3)`` on average: the farther ahead, the worse::

        score = progress - clearance_weight * max(0, clearance_margin - clearance)
                - collision_penalty * failed

    where ``progress`` is how much closer to the goal the rollout comes, ``clearance``
    the smallest surface distance along it, and ``failed`` a collision or leaving the
    arena before the goal. The traits (decision interval, noise picking a random grid
    point, lag, ex-Gaussian RT, lapses) are those of
    :class:`~dcsc_torchrl.humans.traits.SimulatedHuman`; the workload that stretches
    its RT is how far the UAV is inside ``near`` of the nearest obstacle surface,
    ``clamp(near - d_s, 0, near)``.

    Args:
        traits: the operator's traits (default: the ``expert`` preset).
        grid: the candidate actions, ``[G, 3]`` in ``[0, 3]`` (default :data:`DEFAULT_GRID`).
        horizon: rollout steps (of ``DT`` seconds) per candidate, >= 1.
        lookahead_noise: standard deviation (m/s, per axis) of the velocity error of its
            predictions, >= 0; 0 is perfect foresight.
        collision_penalty: score lost by a rollout that collides or leaves the arena.
        clearance_margin: surface distance below which clearance costs score.
        clearance_weight: score per unit of clearance below the margin.
        near: surface distance inside which the workload grows.

    Examples:
        >>> from tensordict import TensorDict
        >>> from envs.uav import UAVPathPlanningEnv
        >>> env = UAVPathPlanningEnv(scenario_seeds=[0, 1])
        >>> td = env.reset().set("is_init", torch.ones(2, 1, dtype=torch.bool))
        >>> operator = SimulatedOperator.from_preset("expert")
        >>> operator.reset(0)
        >>> operator(td)["human_action"].shape
        torch.Size([2, 3])
    """

    def __init__(
        self,
        traits: OperatorTraits | None = None,
        *,
        grid: Sequence[Sequence[float]] | torch.Tensor | None = None,
        horizon: int = 30,
        lookahead_noise: float = 0.2,
        collision_penalty: float = 100.0,
        clearance_margin: float = 1.5,
        clearance_weight: float = 4.0,
        near: float = 2.0,
    ) -> None:
        super().__init__(PRESETS["expert"] if traits is None else traits, frame_seconds=DT)
        grid = torch.as_tensor(DEFAULT_GRID if grid is None else grid, dtype=torch.float32)
        if grid.ndim != 2 or grid.shape[-1] != 3 or len(grid) == 0:
            raise ValueError(f"grid must have shape [G, 3], got {tuple(grid.shape)}")
        if not ((grid >= 0) & (grid <= ACTION_HIGH)).all():
            raise ValueError(f"grid actions must lie in [0, {ACTION_HIGH}]")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if not lookahead_noise >= 0:
            raise ValueError(f"lookahead_noise must be >= 0, got {lookahead_noise}")
        if not near > 0:
            raise ValueError(f"near must be > 0, got {near}")
        self.grid = grid
        self._host_grid = grid.double().numpy()  # what the compiled look-ahead reads, made once
        self.n_choices = len(grid)
        self.horizon = int(horizon)
        self.collision_penalty = float(collision_penalty)
        self.clearance_margin = float(clearance_margin)
        self.clearance_weight = float(clearance_weight)
        self.near = float(near)
        self.lookahead_noise = float(lookahead_noise)
        self._noise_key = 0
        self.in_keys = ("position", "goal", "time", "obstacle_params", "scenario_seed")

    def reset(self, seed: int | None) -> None:
        """Re-seeds the decision streams and the prediction errors (``None``: a fresh seed)."""
        if seed is None:
            seed = int(torch.randint(2**62, ()))
        super().reset(seed)
        self._noise_key = int(_mix(torch.tensor(_signed((int(seed) + 1) % (1 << 64)))))

    def prediction_error(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The velocity error ``e [N, K, 3]`` of each obstacle's prediction (m/s).

        A hash of (operator seed, scenario seed, frame), so the same decision sees the same
        error in any batch, and a decision made on a delayed observation sees the error of
        that observation's frame.
        """
        params = tensordict.get("obstacle_params")
        n_envs, n_obstacles = params.shape[0], params.shape[-2]
        frame = torch.round(tensordict.get("time").reshape(n_envs) / DT).long()
        seed = tensordict.get("scenario_seed").reshape(n_envs).long()
        key = _mix(self._noise_key + _GOLDEN * _mix(seed + _GOLDEN * frame))
        draw = torch.arange(2 * n_obstacles * 3, device=params.device)
        bits = _mix(key.unsqueeze(-1) + _GOLDEN * (draw + 1))
        u = 1.0 - _shift_right(bits, 11).to(torch.float64) * 2.0**-53  # (0, 1]
        u1, u2 = u.reshape(n_envs, 2, n_obstacles, 3).unbind(1)
        z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * torch.pi * u2)
        return (self.lookahead_noise * z).to(params.dtype)

    def predicted_obstacles(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The obstacles as the operator foresees them at ``time + h DT``, ``h = 0..horizon``: centres and
        velocities ``[N, horizon + 1, K, 3]`` (off by :meth:`prediction_error`), radii ``[N, horizon + 1, K]``."""
        now = tensordict.get("time")
        steps = torch.arange(self.horizon + 1, device=now.device, dtype=now.dtype)
        centres, velocities, radii = obstacle_states(tensordict.get("obstacle_params").unsqueeze(1), now + DT * steps)
        if self.lookahead_noise > 0:
            error = self.prediction_error(tensordict).unsqueeze(1)  # [N, 1, K, 3]
            centres = centres + error * (DT * steps)[None, :, None, None]
            velocities = velocities + error
        return centres, velocities, radii

    def score(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Scores of every grid action for every env of a flat batch, ``[N, G]``."""
        position, goal = tensordict.get("position"), tensordict.get("goal")
        centres, velocities, radii = self.predicted_obstacles(tensordict)
        if position.device.type != "cpu":
            return self.rollout_scores(position, goal, centres, radii, velocities)
        # on the host, one compiled loop: the same equations in float64 (dcsc_torchrl.humans.lookahead)
        host = [x.detach().double().contiguous().numpy() for x in (position, goal, centres, radii, velocities)]
        scores = lookahead_scores(*host, self._host_grid, DT, _ARENA_LOW, _ARENA_HIGH, GOAL_RADIUS,
                                  self.clearance_margin, self.clearance_weight, self.collision_penalty)
        return torch.from_numpy(scores).to(position.dtype)

    def rollout_scores(self, position: torch.Tensor, goal: torch.Tensor, centres: torch.Tensor, radii: torch.Tensor,
                       velocities: torch.Tensor) -> torch.Tensor:
        """:meth:`score` as torch operations batched over envs x candidates, ``[N, G]``: the path on a
        device (on the host :meth:`score` runs the compiled loop, tested against this).

        Args:
            position, goal: ``[N, 3]``.
            centres, velocities: the obstacles predicted at ``time + h DT``, ``[N, horizon + 1, K, 3]``.
            radii: ``[N, horizon + 1, K]``.
        """
        n_envs, device = position.shape[0], position.device
        grid = self.grid.to(device)
        shape = (n_envs, self.n_choices)
        rho0, sigma0, tau = (column.expand(shape) for column in grid.T)
        goal = goal.unsqueeze(1).expand(*shape, 3)
        arena_low = torch.tensor(ARENA_LOW, device=device)
        arena_high = torch.tensor(ARENA_HIGH, device=device)

        p = position.unsqueeze(1).expand(*shape, 3)
        start_distance = (p - goal).norm(dim=-1)
        closest = start_distance
        clearance = torch.full(shape, float("inf"), device=device)
        reached = torch.zeros(shape, dtype=torch.bool, device=device)
        failed = torch.zeros(shape, dtype=torch.bool, device=device)
        for h in range(self.horizon):
            moved = iifds_step(
                p,
                goal,
                centres[:, h].unsqueeze(1),
                radii[:, h].unsqueeze(1),
                velocities[:, h].unsqueeze(1),
                rho0,
                sigma0,
                tau,
                DT,
            )
            surface = (moved.unsqueeze(-2) - centres[:, h + 1].unsqueeze(1)).norm(dim=-1)
            surface = (surface - radii[:, h + 1].unsqueeze(1)).amin(-1)
            outside = ((moved < arena_low) | (moved > arena_high)).any(-1)
            flying = ~reached
            clearance = torch.where(flying, torch.minimum(clearance, surface), clearance)
            failed |= flying & ((surface <= 0) | outside)
            distance = (moved - goal).norm(dim=-1)
            closest = torch.minimum(closest, distance)
            reached |= distance <= GOAL_RADIUS
            p = torch.where(reached.unsqueeze(-1), goal, moved)
        shortfall = (self.clearance_margin - clearance).clamp_min(0.0)
        return (
            (start_distance - closest)
            - self.clearance_weight * shortfall
            - self.collision_penalty * failed.to(shortfall.dtype)
        )

    def plan(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self.score(tensordict).argmax(-1)

    def workload(self, tensordict: TensorDictBase) -> torch.Tensor:
        centres, _, radii = obstacle_states(
            tensordict.get("obstacle_params"), tensordict.get("time").squeeze(-1)
        )
        offset = tensordict.get("position").unsqueeze(-2) - centres
        surface = (offset.norm(dim=-1) - radii).amin(-1)
        return (self.near - surface).clamp(0.0, self.near)

    def action(self, choice: torch.Tensor) -> torch.Tensor:
        return self.grid.to(choice.device)[choice]
