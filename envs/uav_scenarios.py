"""The UAV task's geometry and its scenarios: the arena, the obstacles' parametric motions
(:class:`ObstacleParam`, :func:`obstacle_states`) and the seeded scenario family
(:class:`ObstacleFamily`, :func:`sample_scenarios`); docs/envs.md."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import torch
from torch import Tensor

DT = 0.1
"""Seconds per step."""
V0 = 1.0
"""Speed of the attractive flow."""
HORIZON = 500
"""Steps before truncation."""
ACTION_HIGH = 3.0
"""Actions ``(rho0, sigma0, tau)`` live in ``[0, ACTION_HIGH]``."""
GOAL = (10.0, 10.0, 5.5)
START_CORNER = (0.0, 2.0, 5.0)
START_SPREAD = 3.0
"""The start is ``START_CORNER + U(0, START_SPREAD)^3``."""
GOAL_RADIUS = 0.2
ARENA_LOW = (-2.0, -2.0, 0.0)
ARENA_HIGH = (14.0, 14.0, 11.0)
"""Leaving ``[ARENA_LOW, ARENA_HIGH]`` ends the episode."""
CORRIDOR_LOW = (0.0, 0.0, 3.0)
CORRIDOR_HIGH = (10.0, 10.0, 8.0)
"""Obstacle motions are anchored in this 10 x 10 x 5 box between start and goal."""
N_OBSTACLES = 8
"""Obstacles per scenario (fixed, so scenarios batch): four crossing pairs."""

_FRESH_SEED_LOW = 2**31  # fresh scenarios never replay the validation seeds 0..49
_FRESH_SEED_HIGH = 2**62
_CANDIDATES = 4  # candidate scenarios drawn at once per seed (about 60% are fair)
_MAX_BLOCKS = 100
_START_CLEARANCE = 1.0  # surface distance from the start during the first second
_GOAL_CLEARANCE = 0.5  # surface distance from the goal over the whole horizon


class ObstacleParam(IntEnum):
    """Layout of the last dim of ``obstacle_params`` (``[..., K, N_OBSTACLE_PARAMS]``).

    Position at time ``t`` (seconds), with ``R(ψ)`` the rotation by ``HEADING`` in the
    horizontal plane and ``θ(t) = PHASE + ANGULAR_SPEED t + SWING sin(SWING_RATE t)``::

        xy(t) = CENTRE_xy + R(ψ) [AXIS_A cos θ(t), AXIS_B sin θ(t)]
                + [DRIFT_X, DRIFT_Y] (t - CROSS_TIME)
        z(t)  = CENTRE_Z + BOB_AMPLITUDE sin(BOB_RATE t + BOB_PHASE)
                + DRIFT_Z (t - CROSS_TIME)

    Circles (``AXIS_A = AXIS_B``), ellipses, straight passes (zero axes, a drift that
    crosses ``CENTRE`` at ``CROSS_TIME``) and arcs that reverse (``ANGULAR_SPEED = 0``,
    ``SWING > 0``) are all points of this one family.
    """

    CENTRE_X = 0
    CENTRE_Y = 1
    CENTRE_Z = 2
    RADIUS = 3
    AXIS_A = 4
    AXIS_B = 5
    HEADING = 6
    PHASE = 7
    ANGULAR_SPEED = 8
    SWING = 9
    SWING_RATE = 10
    DRIFT_X = 11
    DRIFT_Y = 12
    CROSS_TIME = 13
    BOB_AMPLITUDE = 14
    BOB_RATE = 15
    BOB_PHASE = 16
    DRIFT_Z = 17


N_OBSTACLE_PARAMS = len(ObstacleParam)


def obstacle_states(obstacle_params: Tensor, t: Tensor | float) -> tuple[Tensor, Tensor, Tensor]:
    """Obstacle centres, velocities and radii at time ``t`` (pure, batched, differentiable).

    Args:
        obstacle_params: ``[..., K, N_OBSTACLE_PARAMS]``, laid out as :class:`ObstacleParam`.
        t: time in seconds (``step * DT``), a float or a tensor broadcastable with
            ``obstacle_params.shape[:-2]``: params ``[K, P]`` with ``t`` ``[T]`` give T
            times of one scenario; params ``[B, K, P]`` with ``t`` ``[B]`` one time per
            scenario; params ``[B, 1, K, P]`` with ``t`` ``[B, T]`` T times per scenario.

    Returns:
        ``(centres [..., K, 3], velocities [..., K, 3], radii [..., K])``.

    Examples:
        >>> params = sample_scenario(0).obstacle_params
        >>> centres, velocities, radii = obstacle_states(params, 2.5)
        >>> centres.shape, radii.shape
        (torch.Size([8, 3]), torch.Size([8]))
        >>> times = torch.arange(0, 5, 0.1)
        >>> obstacle_states(params, times)[0].shape
        torch.Size([50, 8, 3])
    """
    p = obstacle_params.unbind(-1)
    t = torch.as_tensor(t, dtype=obstacle_params.dtype, device=obstacle_params.device)
    t = t.unsqueeze(-1)  # broadcast over the obstacle dim
    swing_angle = p[ObstacleParam.SWING_RATE] * t
    theta = (
        p[ObstacleParam.PHASE]
        + p[ObstacleParam.ANGULAR_SPEED] * t
        + p[ObstacleParam.SWING] * torch.sin(swing_angle)
    )
    theta_rate = p[ObstacleParam.ANGULAR_SPEED] + p[ObstacleParam.SWING] * p[
        ObstacleParam.SWING_RATE
    ] * torch.cos(swing_angle)
    cos_h, sin_h = torch.cos(p[ObstacleParam.HEADING]), torch.sin(p[ObstacleParam.HEADING])
    a_cos = p[ObstacleParam.AXIS_A] * torch.cos(theta)
    b_sin = p[ObstacleParam.AXIS_B] * torch.sin(theta)
    a_dcos = -p[ObstacleParam.AXIS_A] * torch.sin(theta) * theta_rate
    b_dsin = p[ObstacleParam.AXIS_B] * torch.cos(theta) * theta_rate
    drift_time = t - p[ObstacleParam.CROSS_TIME]
    bob_angle = p[ObstacleParam.BOB_RATE] * t + p[ObstacleParam.BOB_PHASE]
    x = p[ObstacleParam.CENTRE_X] + cos_h * a_cos - sin_h * b_sin
    y = p[ObstacleParam.CENTRE_Y] + sin_h * a_cos + cos_h * b_sin
    centres = torch.stack(
        [
            x + p[ObstacleParam.DRIFT_X] * drift_time,
            y + p[ObstacleParam.DRIFT_Y] * drift_time,
            p[ObstacleParam.CENTRE_Z]
            + p[ObstacleParam.BOB_AMPLITUDE] * torch.sin(bob_angle)
            + p[ObstacleParam.DRIFT_Z] * drift_time,
        ],
        dim=-1,
    )
    velocities = torch.stack(
        [
            cos_h * a_dcos - sin_h * b_dsin + p[ObstacleParam.DRIFT_X],
            sin_h * a_dcos + cos_h * b_dsin + p[ObstacleParam.DRIFT_Y],
            p[ObstacleParam.BOB_AMPLITUDE] * p[ObstacleParam.BOB_RATE] * torch.cos(bob_angle)
            + p[ObstacleParam.DRIFT_Z],
        ],
        dim=-1,
    )
    radii = p[ObstacleParam.RADIUS].expand(centres.shape[:-1])
    return centres, velocities, radii


@dataclass(frozen=True)
class UAVScenario:
    """Scenarios: where the UAV starts, where it goes, how the obstacles move.

    Every field has the same leading batch dims ``[...]`` (``[S]`` for S scenarios).

    Attributes:
        seed: int64 ``[...]``, the scenario seeds.
        start: ``[..., 3]``.
        goal: ``[..., 3]``.
        obstacle_params: ``[..., K, N_OBSTACLE_PARAMS]`` (see :class:`ObstacleParam`).
    """

    seed: Tensor
    start: Tensor
    goal: Tensor
    obstacle_params: Tensor


class _Draw(IntEnum):
    """The uniform numbers in [0, 1) each obstacle of a candidate scenario consumes."""

    SLOT = 0
    LATERAL = 1
    VERTICAL = 2
    MOTION = 3
    RADIUS = 4
    SPEED = 5
    TURN = 6
    HEADING = 7
    PHASE = 8
    ORBIT = 9
    ELLIPSE_A = 10
    ELLIPSE_RATIO = 11
    ARC_RADIUS = 12
    ARC_SWING = 13
    PASS_ANGLE = 14
    CROSS_TIME = 15
    BOB_AMPLITUDE = 16
    BOB_RATE = 17
    BOB_PHASE = 18
    CLIMB = 19


class _Motion(IntEnum):
    CIRCLE = 0
    ELLIPSE = 1
    STRAIGHT_PASS = 2
    REVERSING_ARC = 3


@dataclass(frozen=True)
class ObstacleFamily:
    """The ranges the obstacle motions are drawn from (see :func:`sample_scenarios`).

    The defaults are the task's calibrated family (docs/envs.md, "Scenarios"): crossing
    pairs of fast, climbing or diving passes timed to meet the UAV near the straight
    line. ``ObstacleFamily(speed=(0.5, 1.5), radius=(0.6, 1.2), lateral=1.5,
    vertical=1.0, intercept=None, climb=0.0, crossing=0.0)`` with 4 obstacles is the
    earlier, mild family of circles, ellipses, passes and arcs.

    Attributes:
        speed: obstacle speed range (the UAV flies at about 1).
        radius: sphere radius range.
        lateral: largest sideways offset of an anchor from the start-goal line.
        vertical: largest vertical offset of an anchor from that line.
        intercept: a straight pass crosses its anchor when a UAV flying the straight line
            at ``INTERCEPT_SPEED`` would be there, give or take ``U(-intercept, intercept)``
            seconds; ``None`` draws the crossing time uniformly in 3..10 s instead.
        motion_weights: relative frequencies of circle, ellipse, straight pass, arc.
        climb: largest angle (rad) of a straight pass above or below the horizontal.
        bob: largest amplitude of the vertical bobbing.
        crossing: probability that obstacles ``2j`` and ``2j + 1`` are a crossing pair:
            two straight passes from opposite sides through the same anchor at the same
            time (the second copies the first's anchor and crossing time).
    """

    speed: tuple[float, float] = (1.5, 2.5)
    radius: tuple[float, float] = (1.6, 2.2)
    lateral: float = 0.5
    vertical: float = 0.5
    intercept: float | None = 0.5
    motion_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    climb: float = 1.2
    bob: float = 0.8
    crossing: float = 1.0

    def __post_init__(self) -> None:
        checks = {
            "speed": 0 <= self.speed[0] <= self.speed[1],
            "radius": 0 < self.radius[0] <= self.radius[1],
            "lateral": self.lateral >= 0,
            "vertical": self.vertical >= 0,
            "intercept": self.intercept is None or self.intercept >= 0,
            "crossing": 0 <= self.crossing <= 1,
            "climb": 0 <= self.climb < math.pi / 2,
            "bob": self.bob >= 0,
            "motion_weights": len(self.motion_weights) == len(_Motion)
            and min(self.motion_weights) >= 0
            and sum(self.motion_weights) > 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"invalid ObstacleFamily {name}={getattr(self, name)!r}")


INTERCEPT_SPEED = 0.8
"""Speed (along the start-goal line) at which an intercepting pass expects the UAV."""


def _obstacles_from_uniforms(draws: Tensor, family: ObstacleFamily) -> Tensor:
    """Obstacle motions ``[..., K, N_OBSTACLE_PARAMS]`` from uniforms ``[..., K, len(_Draw)]``.

    Anchors are stratified along the line from the centre of the start box to the goal
    (obstacle k in the k-th K-th of 20%..80% of the way), shifted up to
    ``family.lateral`` sideways and ``family.vertical`` vertically, and clipped into the
    corridor. Each obstacle is a circle (orbit radius 1..2.5), an ellipse (semi-axes
    1.5..3 and 0.3..0.6 of that), a straight pass across the line or an arc (radius 2..4)
    swinging 0.6..1.2 rad either way of its anchor, in proportions
    ``family.motion_weights``, at a speed in ``family.speed``, with a radius in
    ``family.radius`` and vertical bobbing of amplitude 0..0.8 at 0.5..2 rad/s.
    """

    def draw(field: _Draw, low: float, high: float) -> Tensor:
        return low + (high - low) * draws[..., field]

    n_obstacles = draws.shape[-2]
    n_pairs = n_obstacles // 2
    # crossing pairs: the pair's first obstacle decides (its MOTION draw), both pass
    paired = torch.zeros(draws.shape[:-1], dtype=torch.bool)
    paired[..., 1 : 2 * n_pairs : 2] = draws[..., 0 : 2 * n_pairs : 2, _Draw.MOTION] < family.crossing
    partner = torch.arange(n_obstacles) - (torch.arange(n_obstacles) % 2)

    def pair(values: Tensor) -> Tensor:
        """``values [..., K]`` with a crossing pair's second obstacle given its first's."""
        return torch.where(paired, values[..., partner], values)

    start_mid = torch.tensor(START_CORNER) + START_SPREAD / 2
    line = torch.tensor(GOAL) - start_mid
    across = torch.tensor([-line[1], line[0], 0.0]) / line[:2].norm()
    fraction = 0.2 + 0.6 * (torch.arange(n_obstacles) + draws[..., _Draw.SLOT]) / n_obstacles
    anchor = (
        start_mid
        + pair(fraction).unsqueeze(-1) * line
        + pair(draw(_Draw.LATERAL, -family.lateral, family.lateral)).unsqueeze(-1) * across
        + pair(draw(_Draw.VERTICAL, -family.vertical, family.vertical)).unsqueeze(-1)
        * torch.tensor([0.0, 0.0, 1.0])
    )
    anchor = anchor.clamp(torch.tensor(CORRIDOR_LOW), torch.tensor(CORRIDOR_HIGH))

    cumulative = torch.tensor(family.motion_weights).cumsum(0)
    cumulative = cumulative / cumulative[-1]
    motion = torch.searchsorted(cumulative, draws[..., _Draw.MOTION].contiguous(), right=True)
    motion = motion.clamp_max(len(_Motion) - 1)
    crossing = paired | paired.roll(-1, -1)  # both members of a crossing pair
    motion = torch.where(crossing, _Motion.STRAIGHT_PASS, motion)
    is_circle, is_ellipse = motion == _Motion.CIRCLE, motion == _Motion.ELLIPSE
    is_pass, is_arc = motion == _Motion.STRAIGHT_PASS, motion == _Motion.REVERSING_ARC
    speed = draw(_Draw.SPEED, *family.speed)
    turn = torch.where(draws[..., _Draw.TURN] < 0.5, -1.0, 1.0)
    turn = torch.where(paired, -pair(turn), turn)  # the pair comes from opposite sides
    heading = draw(_Draw.HEADING, 0.0, 2 * math.pi)
    phase = draw(_Draw.PHASE, 0.0, 2 * math.pi)
    zero = torch.zeros_like(speed)

    ellipse_a = draw(_Draw.ELLIPSE_A, 1.5, 3.0)
    arc_radius = draw(_Draw.ARC_RADIUS, 2.0, 4.0)
    arc_swing = draw(_Draw.ARC_SWING, 0.6, 1.2)
    axis_a = torch.where(is_circle, draw(_Draw.ORBIT, 1.0, 2.5), arc_radius)
    axis_a = torch.where(is_ellipse, ellipse_a, torch.where(is_pass, zero, axis_a))
    axis_b = torch.where(is_ellipse, ellipse_a * draw(_Draw.ELLIPSE_RATIO, 0.3, 0.6), axis_a)
    orbiting = is_circle | is_ellipse
    angular_speed = torch.where(orbiting, turn * speed / axis_a.clamp_min(1.0), zero)
    swing = torch.where(is_arc, arc_swing, zero)
    swing_rate = torch.where(is_arc, speed / (arc_radius * arc_swing), zero)

    pass_angle = torch.atan2(across[1], across[0]) + draw(_Draw.PASS_ANGLE, -0.5, 0.5)
    pass_angle = pass_angle + math.pi * (turn < 0)
    climb = draw(_Draw.CLIMB, -family.climb, family.climb)
    direction = torch.stack(
        [
            torch.cos(pass_angle) * torch.cos(climb),
            torch.sin(pass_angle) * torch.cos(climb),
            torch.sin(climb),
        ],
        -1,
    )
    drift = torch.where(is_pass.unsqueeze(-1), speed.unsqueeze(-1) * direction, 0.0)
    if family.intercept is None:
        cross_time = draw(_Draw.CROSS_TIME, 3.0, 10.0)
    else:
        arrival = ((anchor - start_mid) * line).sum(-1) / line.norm() / INTERCEPT_SPEED
        cross_time = arrival + draw(_Draw.CROSS_TIME, -family.intercept, family.intercept)
    cross_time = pair(cross_time)
    # An arc swings about the point it passes at θ = PHASE: its anchor.
    arc_offset = arc_radius.unsqueeze(-1) * torch.stack(
        [torch.cos(heading + phase), torch.sin(heading + phase)], -1
    )
    centre_xy = anchor[..., :2] - torch.where(is_arc.unsqueeze(-1), arc_offset, 0.0)

    fields = {
        ObstacleParam.CENTRE_X: centre_xy[..., 0],
        ObstacleParam.CENTRE_Y: centre_xy[..., 1],
        ObstacleParam.CENTRE_Z: anchor[..., 2],
        ObstacleParam.RADIUS: draw(_Draw.RADIUS, *family.radius),
        ObstacleParam.AXIS_A: axis_a,
        ObstacleParam.AXIS_B: axis_b,
        ObstacleParam.HEADING: heading,
        ObstacleParam.PHASE: phase,
        ObstacleParam.ANGULAR_SPEED: angular_speed,
        ObstacleParam.SWING: swing,
        ObstacleParam.SWING_RATE: swing_rate,
        ObstacleParam.DRIFT_X: drift[..., 0],
        ObstacleParam.DRIFT_Y: drift[..., 1],
        ObstacleParam.CROSS_TIME: torch.where(is_pass, cross_time, zero),
        ObstacleParam.BOB_AMPLITUDE: draw(_Draw.BOB_AMPLITUDE, 0.0, family.bob),
        ObstacleParam.BOB_RATE: draw(_Draw.BOB_RATE, 0.5, 2.0),
        ObstacleParam.BOB_PHASE: draw(_Draw.BOB_PHASE, 0.0, 2 * math.pi),
        ObstacleParam.DRIFT_Z: drift[..., 2],
    }
    return torch.stack([fields[param] for param in ObstacleParam], dim=-1)


FAMILY = ObstacleFamily()
"""The obstacle family of the task (calibrated: see docs/envs.md)."""


def _min_surface_distance(point: Tensor, obstacle_params: Tensor, times: Tensor) -> Tensor:
    """Smallest surface distance ``[...]`` from ``point [..., 3]`` to any obstacle at ``times``."""
    centres, _, radii = obstacle_states(obstacle_params.unsqueeze(-3), times)
    distance = (centres - point[..., None, None, :]).norm(dim=-1) - radii
    return distance.flatten(-2).min(-1).values


def sample_scenarios(
    seeds: Sequence[int] | Tensor,
    n_obstacles: int = N_OBSTACLES,
    family: ObstacleFamily | None = None,
) -> UAVScenario:
    """The scenarios of some seeds: start ``(0, 2, 5) + U(0, 3)^3``, goal ``GOAL``, K obstacles.

    Scenario ``seed`` uses only ``torch.Generator().manual_seed(seed)``, so it is the same
    wherever and in whatever batch it is drawn. From it come blocks of
    ``_CANDIDATES`` candidate scenarios (uniforms, turned into motions by
    :func:`_obstacles_from_uniforms` for all seeds at once); the first candidate in which
    no obstacle comes within 1.0 of the start during the first second nor within 0.5 of
    the goal over the horizon is the scenario.

    Args:
        seeds: S scenario seeds (the validation scenarios are seeds 0..49).
        n_obstacles: obstacles per scenario.

    Returns:
        A :class:`UAVScenario` with leading dim S (float32 CPU tensors).

    Raises:
        ValueError: if ``n_obstacles < 1``.

    Examples:
        >>> scenarios = sample_scenarios([0, 1, 2])
        >>> scenarios.start.shape, scenarios.obstacle_params.shape
        (torch.Size([3, 3]), torch.Size([3, 8, 18]))
    """
    if n_obstacles < 1:
        raise ValueError(f"n_obstacles must be >= 1, got {n_obstacles}")
    family = FAMILY if family is None else family
    seeds = torch.as_tensor(seeds, dtype=torch.int64).reshape(-1)
    generators = [torch.Generator().manual_seed(seed) for seed in seeds.tolist()]
    n_draws = 3 + n_obstacles * len(_Draw)
    goal = torch.tensor(GOAL)
    early = torch.arange(0.0, 1.0 + DT / 2, DT)
    horizon = torch.arange(0.0, HORIZON * DT + DT / 2, 0.5)
    start = torch.empty(len(seeds), 3)
    params = torch.empty(len(seeds), n_obstacles, N_OBSTACLE_PARAMS)
    pending = torch.arange(len(seeds))
    for _ in range(_MAX_BLOCKS):
        if not len(pending):
            return UAVScenario(seeds, start, goal.expand(len(seeds), 3).clone(), params)
        draws = torch.stack(
            [torch.rand(_CANDIDATES, n_draws, generator=generators[i]) for i in pending.tolist()]
        )
        cand_start = torch.tensor(START_CORNER) + START_SPREAD * draws[..., :3]
        cand_params = _obstacles_from_uniforms(
            draws[..., 3:].reshape(*draws.shape[:2], n_obstacles, -1), family
        )
        fair = (_min_surface_distance(cand_start, cand_params, early) >= _START_CLEARANCE) & (
            _min_surface_distance(goal, cand_params, horizon) >= _GOAL_CLEARANCE
        )
        found = fair.any(-1)
        first = fair.long().argmax(-1)
        rows = torch.arange(len(pending))
        start[pending[found]] = cand_start[rows, first][found]
        params[pending[found]] = cand_params[rows, first][found]
        pending = pending[~found]
    raise RuntimeError(f"no fair scenario for seeds {seeds[pending].tolist()}")


def sample_scenario(seed: int, n_obstacles: int = N_OBSTACLES) -> UAVScenario:
    """The scenario of one seed (see :func:`sample_scenarios`), without a batch dim.

    Args:
        seed: the scenario seed.
        n_obstacles: obstacles in the scenario.

    Returns:
        A :class:`UAVScenario` with ``start [3]``, ``obstacle_params [K, P]``.
    """
    batch = sample_scenarios([seed], n_obstacles)
    return UAVScenario(batch.seed[0], batch.start[0], batch.goal[0], batch.obstacle_params[0])
