"""The UAV operator's look-ahead as one compiled loop: every (env, candidate) rollout of the
IIFDS flow, fused (numba), on the host.

:meth:`SimulatedOperator.score <dcsc_torchrl.humans.uav_operator.SimulatedOperator.score>`
rolls the flow of :func:`dcsc_torchrl.envs.iifds.iifds_step` ``horizon`` steps for each of
``G`` candidate actions of ``N`` envs against ``K`` obstacles. As torch operations that is
about 150 small tensor operations per step, each a pass over ``[N, G, K, 3]`` (docs/scaling.md
measured the operator at 70% of a UAV cell); here each rollout is one loop with no
temporaries. It computes the same equations in float64 (the torch path runs in float32), so
its scores agree with :func:`dcsc_torchrl.envs.iifds.iifds_step`'s to float32 rounding
(``tests/test_operators.py`` compares them), not bit for bit.

Why numba, not numpy or torch: the work is many small passes; numpy pays its per-call
cost on each of them as torch does (a few microseconds), while a compiled loop keeps each
rollout's values in registers. The first call compiles (a few seconds), cached on disk
beside this file when it is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from dcsc_torchrl.envs.iifds import (
    _EPS,
    _EXP_LIMIT,
    _FACTOR_LOG_LIMIT,
    _LOG_GAMMA_FLOOR,
    _WEIGHT_FLOOR,
    COEFFICIENT_FLOOR,
    OBSTACLE_VELOCITY_DECAY,
    SPEED_CAP,
)

_TINY32 = float(np.finfo(np.float32).tiny)  # the torch path floors Γ at float32's tiny before its log


@numba.njit(cache=True, error_model="numpy")
def _inverse_gamma_power(scaled_log_gamma: float, coefficient0: float) -> float:
    """``1 / Γ^(1/ρ)`` (:func:`dcsc_torchrl.envs.iifds._inverse_gamma_power`)."""
    return math.exp(-max(scaled_log_gamma / max(coefficient0, COEFFICIENT_FLOOR), -_FACTOR_LOG_LIMIT))


@numba.njit(cache=True, error_model="numpy")
def _step(p: np.ndarray, goal: np.ndarray, centres: np.ndarray, radii: np.ndarray, velocities: np.ndarray,
          rho0: float, sigma0: float, cos_tau: float, sin_tau: float, dt: float, out: np.ndarray,
          gamma: np.ndarray, turn: np.ndarray) -> None:
    """One Euler step ``p + dt ū`` of :func:`dcsc_torchrl.envs.iifds.iifds_velocity` (``v0 = 1``) into ``out``."""
    n_obstacles = radii.shape[0]
    gx, gy, gz = p[0] - goal[0], p[1] - goal[1], p[2] - goal[2]
    d_goal = math.sqrt(gx * gx + gy * gy + gz * gz)
    to_goal = max(d_goal, _EPS)
    ux, uy, uz = -gx / to_goal, -gy / to_goal, -gz / to_goal
    for k in range(n_obstacles):
        ox, oy, oz = p[0] - centres[k, 0], p[1] - centres[k, 1], p[2] - centres[k, 2]
        distance_sq = ox * ox + oy * oy + oz * oz
        radius_sq = radii[k] * radii[k]
        gamma[k] = distance_sq / radius_sq
        nx, ny, nz = 2.0 * ox / radius_sq, 2.0 * oy / radius_sq, 2.0 * oz / radius_sq
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if length > _EPS:
            nx, ny, nz = nx / length, ny / length, nz / length
        else:
            nx, ny, nz = 0.0, 0.0, 1.0
        horizontal = math.sqrt(nx * nx + ny * ny)
        if horizontal > _EPS:
            cos_phi, sin_phi = nx / horizontal, ny / horizontal
        else:
            cos_phi, sin_phi = 1.0, 0.0
        tx = cos_tau * sin_phi + sin_tau * cos_phi * nz
        ty = -cos_tau * cos_phi + sin_tau * sin_phi * nz
        tz = -sin_tau * horizontal
        d_surface = math.sqrt(distance_sq) - radii[k]
        exponent = min(max(1.0 / (d_goal * d_surface) - 1.0, -_EXP_LIMIT), _EXP_LIMIT)
        scaled = max(math.log(max(gamma[k], _TINY32)), _LOG_GAMMA_FLOOR) * math.exp(exponent)
        repulsive = _inverse_gamma_power(scaled, rho0)
        tangential = _inverse_gamma_power(scaled, sigma0)
        carried = math.exp(-gamma[k] / OBSTACLE_VELOCITY_DECAY)
        rx = ux - carried * velocities[k, 0]
        ry = uy - carried * velocities[k, 1]
        rz = uz - carried * velocities[k, 2]
        along = 0.0 if ox * rx + oy * ry + oz * rz >= 0 else nx * rx + ny * ry + nz * rz
        turn[k, 0] = along * (tangential * tx - repulsive * nx)
        turn[k, 1] = along * (tangential * ty - repulsive * ny)
        turn[k, 2] = along * (tangential * tz - repulsive * nz)
    total = 0.0
    bx, by, bz = 0.0, 0.0, 0.0
    for k in range(n_obstacles):  # obstacle_weights: w_k ∝ Π_{i≠k} e_i / (e_i + e_k)
        own = max(gamma[k] - 1.0, _WEIGHT_FLOOR)
        weight = 1.0
        for i in range(n_obstacles):
            if i != k:
                other = max(gamma[i] - 1.0, _WEIGHT_FLOOR)
                weight *= other / (other + own)
        total += weight
        bx += weight * turn[k, 0]
        by += weight * turn[k, 1]
        bz += weight * turn[k, 2]
    bx, by, bz = ux + bx / total, uy + by / total, uz + bz / total
    cap = SPEED_CAP / max(math.sqrt(bx * bx + by * by + bz * bz), SPEED_CAP)
    out[0] = p[0] + dt * bx * cap
    out[1] = p[1] + dt * by * cap
    out[2] = p[2] + dt * bz * cap


@numba.njit(cache=True, error_model="numpy")
def lookahead_scores(position: np.ndarray, goal: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                     velocities: np.ndarray, grid: np.ndarray, dt: float, arena_low: np.ndarray,
                     arena_high: np.ndarray, goal_radius: float, clearance_margin: float,
                     clearance_weight: float, collision_penalty: float) -> np.ndarray:
    """The operator's score of every candidate of every env, ``[N, G]`` (float64).

    Args:
        position, goal: ``[N, 3]``.
        centres, velocities: the predicted obstacles at ``time + h DT``, ``[N, H + 1, K, 3]``.
        radii: ``[N, H + 1, K]``.
        grid: the candidates (rho0, sigma0, tau), ``[G, 3]``.
        dt: seconds per step; ``H`` steps are rolled.
        arena_low, arena_high: the arena's corners, ``[3]``.
        goal_radius, clearance_margin, clearance_weight, collision_penalty: as
            :class:`~dcsc_torchrl.humans.uav_operator.SimulatedOperator`.
    """
    n_envs, n_candidates, horizon = position.shape[0], grid.shape[0], centres.shape[1] - 1
    n_obstacles = radii.shape[2]
    scores = np.empty((n_envs, n_candidates))
    p, moved = np.empty(3), np.empty(3)
    gamma, turn = np.empty(n_obstacles), np.empty((n_obstacles, 3))
    for n in range(n_envs):
        g = goal[n]
        start = math.sqrt((position[n, 0] - g[0]) ** 2 + (position[n, 1] - g[1]) ** 2 + (position[n, 2] - g[2]) ** 2)
        for c in range(n_candidates):
            rho0, sigma0, tau = grid[c, 0], grid[c, 1], grid[c, 2]
            cos_tau, sin_tau = math.cos(tau), math.sin(tau)
            p[:] = position[n]
            closest, clearance = start, math.inf
            reached, failed = False, False
            for h in range(horizon):
                _step(p, g, centres[n, h], radii[n, h], velocities[n, h], rho0, sigma0, cos_tau, sin_tau, dt,
                      moved, gamma, turn)
                surface = math.inf
                for k in range(n_obstacles):
                    dx = moved[0] - centres[n, h + 1, k, 0]
                    dy = moved[1] - centres[n, h + 1, k, 1]
                    dz = moved[2] - centres[n, h + 1, k, 2]
                    surface = min(surface, math.sqrt(dx * dx + dy * dy + dz * dz) - radii[n, h + 1, k])
                outside = False
                for d in range(3):
                    outside |= moved[d] < arena_low[d] or moved[d] > arena_high[d]
                if not reached:
                    clearance = min(clearance, surface)
                    failed |= surface <= 0 or outside
                distance = math.sqrt((moved[0] - g[0]) ** 2 + (moved[1] - g[1]) ** 2 + (moved[2] - g[2]) ** 2)
                closest = min(closest, distance)
                reached |= distance <= goal_radius
                p[:] = g if reached else moved
            shortfall = max(clearance_margin - clearance, 0.0)
            scores[n, c] = (start - closest) - clearance_weight * shortfall - collision_penalty * failed
    return scores
