"""Interfered fluid dynamical system (IIFDS) around moving spheres, as batched torch functions.

The UAV follows a flow: the attractive flow ``u`` toward the goal is bent around every
obstacle by a modulation matrix ``M`` (a repulsive term that removes the velocity
component into the obstacle, a tangential term that turns it around the obstacle),
shifted by the obstacle's own velocity, and blended over obstacles by weights ``w_k``.

Sources of the formulas:

- Wang, Lyu, Yao, Liang and Liu, "Three-dimensional path planning for unmanned aerial
  vehicle based on interfered fluid dynamical system", Chinese Journal of Aeronautics
  28(1), 2015 — ``Γ``, ``n``, the repulsive and tangential matrices, the tangent plane
  basis ``t1, t2`` and the multi-obstacle weights ``w_k`` / ``M̄ = Σ w_k M_k``.
- Yao, Wang and Su, "Real-time path planning of unmanned aerial vehicle for target
  tracking and obstacle avoidance in complex dynamic environment", Aerospace Science
  and Technology 47, 2015 — moving obstacles, ``ū = M (u - v_p) + v_p`` with
  ``v_p = exp(-Γ/λ) v_obs``, and ``M = I`` once the flow moves away from an obstacle.
- The paper's ref. [42], github.com/ZYunfeii/UAV_Obstacle_Avoiding_DRL
  (``Dynamic_obstacle_avoidance/IIFDS.py``) — the reinforcement-learning form used here:
  the actions are ``(rho0, sigma0, tau)``, ``rho = rho0 exp(1 - 1/(d_g d_s))`` (same for
  sigma), ``t = cos(tau) t1_hat + sin(tau) t2_hat``, ``λ = 8``, ``V0 = 1``, ``dt = 0.1``
  and ``||ū||`` capped at 5.

Shapes: positions are ``[..., 3]``; per-obstacle quantities carry an obstacle dim before
it: centres and velocities ``[..., K, 3]``, radii ``[..., K]`` (e.g. ``[B, K, 3]`` and
``[B, K]`` for a batch of B scenarios); actions are ``[...]``. No function returns NaN
or inf for finite inputs: the normal at an obstacle centre, the tangent basis straight
above or below a centre (``n_x = n_y = 0``), ``rho0 = sigma0 = 0``, a UAV on a surface,
inside an obstacle or at the goal are all handled (see each function).

Examples:
    >>> import torch
    >>> p = torch.tensor([[0.0, 2.0, 5.0]])
    >>> goal = torch.tensor([[10.0, 10.0, 5.5]])
    >>> centres = torch.tensor([[[5.0, 6.0, 5.0], [20.0, 20.0, 20.0]]])
    >>> radii = torch.tensor([[1.0, 1.0]])
    >>> velocities = torch.zeros(1, 2, 3)
    >>> action = torch.tensor([[1.0, 1.5, 1.5]])
    >>> iifds_step(p, goal, centres, radii, velocities, *action.unbind(-1)).shape
    torch.Size([1, 3])
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "COEFFICIENT_FLOOR",
    "OBSTACLE_VELOCITY_DECAY",
    "SPEED_CAP",
    "attractive_flow",
    "iifds_step",
    "iifds_velocity",
    "obstacle_weights",
    "tangent_basis",
    "transported_velocity",
]

COEFFICIENT_FLOOR = 0.1
"""``rho0`` and ``sigma0`` below this are raised to it inside the field."""
SPEED_CAP = 5.0
"""Largest ``||ū||``."""
OBSTACLE_VELOCITY_DECAY = 8.0
"""``λ`` in ``v_p = exp(-Γ/λ) v_obs``: how far out the obstacle's motion carries the flow."""

_EPS = 1e-9
_LOG_GAMMA_FLOOR = -27.0  # log of the smallest Γ used (1e-12): the UAV at a centre
_EXP_LIMIT = 60.0  # bound on the exponent of the distance factor exp(1/(d_g d_s) - 1)
_FACTOR_LOG_LIMIT = 20.0  # 1/Γ^(1/ρ) <= e^20, reached only inside an obstacle
_WEIGHT_FLOOR = 1e-6  # Γ - 1 for a UAV on (or inside) a surface


def tangent_basis(normal: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Unit normal and the unit tangent-plane basis ``t1_hat``, ``t2_hat``.

    ``t1 = [n_y, -n_x, 0]`` and ``t2 = [n_x n_z, n_y n_z, -(n_x^2 + n_y^2)]`` normalised.
    With ``h = sqrt(n_x^2 + n_y^2) / ||n||`` and azimuth ``φ`` of ``n``:
    ``t1_hat = [sin φ, -cos φ, 0]`` and ``t2_hat = [cos φ n_z/||n||, sin φ n_z/||n||, -h]``.
    Where ``n_x = n_y = 0`` (straight above or below the centre) ``φ`` is undefined and
    ``φ = 0`` is used; where ``n = 0`` (at the centre) the normal is taken as ``+z``.
    Both keep the three vectors orthonormal and finite.

    Args:
        normal: ``[..., 3]``.

    Returns:
        ``(n_hat, t1_hat, t2_hat)``, each ``[..., 3]``.
    """
    length = normal.norm(dim=-1, keepdim=True)
    up = torch.zeros_like(normal)
    up[..., 2] = 1.0
    n_hat = torch.where(length > _EPS, normal / length.clamp_min(_EPS), up)
    horizontal = n_hat[..., :2].norm(dim=-1, keepdim=True)
    east = torch.zeros_like(n_hat[..., :2])
    east[..., 0] = 1.0
    azimuth = torch.where(horizontal > _EPS, n_hat[..., :2] / horizontal.clamp_min(_EPS), east)
    cos_phi, sin_phi = azimuth.unbind(-1)
    n_z = n_hat[..., 2]
    t1_hat = torch.stack([sin_phi, -cos_phi, torch.zeros_like(n_z)], dim=-1)
    t2_hat = torch.stack([cos_phi * n_z, sin_phi * n_z, -horizontal.squeeze(-1)], dim=-1)
    return n_hat, t1_hat, t2_hat


def _inverse_gamma_power(scaled_log_gamma: Tensor, coefficient0: Tensor) -> Tensor:
    """``1 / Γ^(1/ρ)`` with ``ρ = max(ρ0, 0.1) exp(1 - 1/(d_g d_s))``, computed in log space.

    ``Γ^(1/ρ) = exp(ln Γ exp(1/(d_g d_s) - 1) / ρ0)``; ``scaled_log_gamma`` is
    ``ln Γ exp(1/(d_g d_s) - 1)`` from :func:`_scaled_log_gamma` (shared by ``ρ`` and ``σ``).
    The result is bounded by ``e^20`` (inside an obstacle only).
    """
    log_power = scaled_log_gamma / coefficient0.clamp_min(COEFFICIENT_FLOOR)
    return torch.exp(-log_power.clamp_min(-_FACTOR_LOG_LIMIT))


def _scaled_log_gamma(gamma: Tensor, d_surface: Tensor, d_goal: Tensor) -> Tensor:
    """``ln Γ exp(1/(d_g d_s) - 1)``: the exponent of ``Γ^(1/ρ)`` times ``ρ0``.

    The inner exponent is bounded to ``±60`` (``d_g d_s → 0``: the UAV on a surface or at
    the goal, where ``ρ → 0`` and the term vanishes outside the obstacle), and ``ln Γ`` is
    floored at ``ln 1e-12`` (the UAV at a centre).
    """
    exponent = (1.0 / (d_goal * d_surface) - 1.0).clamp(-_EXP_LIMIT, _EXP_LIMIT)
    log_gamma = gamma.clamp_min(torch.finfo(gamma.dtype).tiny).log().clamp_min(_LOG_GAMMA_FLOOR)
    return log_gamma * exponent.exp()


def _modulation_terms(position: Tensor, goal: Tensor, centre: Tensor, radius: Tensor, rho0: Tensor,
                      sigma0: Tensor, tau: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The parts of ``M = I - r n_hat n_hat^T + s t n_hat^T``: ``(Γ, n_hat, t, r, s)``.

    ``r = 1/Γ^(1/ρ)`` (repulsive), ``s = 1/Γ^(1/σ)`` (tangential), ``t = cos(τ) t1_hat +
    sin(τ) t2_hat`` (a unit vector: ``||t|| = 1``, so the paper's ``t n^T / (||t|| ||n||)``
    is ``t n_hat^T``). Shapes as :func:`iifds_velocity`'s per-obstacle arguments.
    """
    # Γ = ||p - c||^2 / R^2 and n = ∇Γ = 2 (p - c) / R^2 from one offset: this runs 30 times
    # per decision of the UAV operator's look-ahead
    offset = position - centre
    distance_sq = offset.square().sum(-1)
    gamma = distance_sq / radius.square()
    n_hat, t1_hat, t2_hat = tangent_basis(2 * offset / radius.square().unsqueeze(-1))
    tangent = torch.cos(tau).unsqueeze(-1) * t1_hat + torch.sin(tau).unsqueeze(-1) * t2_hat
    d_surface = distance_sq.sqrt() - radius
    d_goal = (position - goal).norm(dim=-1)
    scaled = _scaled_log_gamma(gamma, d_surface, d_goal)
    return gamma, n_hat, tangent, _inverse_gamma_power(scaled, rho0), _inverse_gamma_power(scaled, sigma0)


def obstacle_weights(gamma: Tensor) -> Tensor:
    """Blending weights ``w_k ∝ Π_{i≠k} (Γ_i - 1) / ((Γ_i - 1) + (Γ_k - 1))``, normalised.

    The nearest obstacle (smallest ``Γ - 1``) dominates; a single obstacle gets weight 1.
    ``Γ - 1`` is floored at ``1e-6`` so a UAV on or inside a surface gives finite weights.

    Args:
        gamma: ``[..., K]``.

    Returns:
        ``w`` of shape ``[..., K]``, summing to 1 over the last dim.
    """
    excess = (gamma - 1).clamp_min(_WEIGHT_FLOOR)
    others = excess.unsqueeze(-2)  # [..., 1, K]: index i
    own = excess.unsqueeze(-1)  # [..., K, 1]: index k
    ratios = others / (others + own)
    eye = torch.eye(gamma.shape[-1], dtype=torch.bool, device=gamma.device)
    weights = torch.where(eye, torch.ones_like(ratios), ratios).prod(-1)
    return weights / weights.sum(-1, keepdim=True)


def attractive_flow(position: Tensor, goal: Tensor, v0: float = 1.0) -> Tensor:
    """Initial flow toward the goal, ``u = -V0 (p - g) / ||p - g||`` (zero at the goal).

    Args:
        position: ``[..., 3]``.
        goal: ``[..., 3]``.
        v0: flow speed ``V0``.

    Returns:
        ``u`` of shape ``[..., 3]``.
    """
    offset = position - goal
    return -v0 * offset / offset.norm(dim=-1, keepdim=True).clamp_min(_EPS)


def transported_velocity(gamma: Tensor, velocity: Tensor) -> Tensor:
    """Share of an obstacle's velocity carried by the flow, ``v_p = exp(-Γ/λ) v_obs``.

    Args:
        gamma: ``[..., K]``.
        velocity: obstacle velocity ``[..., K, 3]``.

    Returns:
        ``v_p`` of shape ``[..., K, 3]``.
    """
    return torch.exp(-gamma / OBSTACLE_VELOCITY_DECAY).unsqueeze(-1) * velocity


def iifds_velocity(
    position: Tensor,
    goal: Tensor,
    centres: Tensor,
    radii: Tensor,
    velocities: Tensor,
    rho0: Tensor,
    sigma0: Tensor,
    tau: Tensor,
    v0: float = 1.0,
) -> Tensor:
    """Modulated flow ``ū`` around K moving spheres, with ``||ū||`` capped at ``SPEED_CAP``.

    Per obstacle, ``ū_k = M_k (u - v_p,k) + v_p,k`` with ``M_k = I`` where the relative
    flow already leaves the obstacle (``n_k · (u - v_p,k) >= 0``), blended as
    ``ū = Σ_k w_k ū_k``: for static obstacles Wang et al.'s ``ū = M̄ u`` with
    ``M̄ = Σ_k w_k M_k``, for one obstacle Yao et al.'s ``ū = M (u - v_p) + v_p``. ``M_k``
    is applied without forming it: ``M_k x = x + (n_hat_k · x)(s_k t_k - r_k n_hat_k)``
    (:func:`modulation_matrix`'s terms), so ``ū = u + Σ_k w_k (n_hat_k · (u - v_p,k))
    (s_k t_k - r_k n_hat_k)``, a few vector operations per obstacle instead of 3 x 3 products.

    Args:
        position: UAV position ``[..., 3]``.
        goal: ``[..., 3]``.
        centres: ``[..., K, 3]``.
        radii: ``[..., K]``.
        velocities: obstacle velocities ``[..., K, 3]``.
        rho0: ``[...]``.
        sigma0: ``[...]``.
        tau: ``[...]``.
        v0: attractive flow speed ``V0``.

    Returns:
        ``ū`` of shape ``[..., 3]``.
    """
    u = attractive_flow(position, goal, v0)
    p_k = position.unsqueeze(-2)
    gamma, n_hat, tangent, repulsive, tangential = _modulation_terms(
        p_k, goal.unsqueeze(-2), centres, radii, rho0.unsqueeze(-1), sigma0.unsqueeze(-1), tau.unsqueeze(-1)
    )
    relative = u.unsqueeze(-2) - transported_velocity(gamma, velocities)  # u - v_p,k
    leaving = ((p_k - centres) * relative).sum(-1) >= 0  # n_k · (u - v_p,k) >= 0: M_k = I
    # M_k x = x + (n_hat · x)(s t - r n_hat), so ū_k = M_k (u - v_p,k) + v_p,k = u + that turn
    along = torch.where(leaving, 0.0, (n_hat * relative).sum(-1))
    turn = along.unsqueeze(-1) * (tangential.unsqueeze(-1) * tangent - repulsive.unsqueeze(-1) * n_hat)
    weights = obstacle_weights(gamma)
    u_bar = u + (weights.unsqueeze(-1) * turn).sum(-2)  # Σ_k w_k ū_k with Σ_k w_k = 1
    speed = u_bar.norm(dim=-1, keepdim=True)
    return u_bar * (SPEED_CAP / speed.clamp_min(SPEED_CAP))


def iifds_step(
    position: Tensor,
    goal: Tensor,
    centres: Tensor,
    radii: Tensor,
    velocities: Tensor,
    rho0: Tensor,
    sigma0: Tensor,
    tau: Tensor,
    dt: float = 0.1,
    v0: float = 1.0,
) -> Tensor:
    """One Euler step along the modulated flow, ``p' = p + dt ū``.

    Args:
        position: UAV position ``[..., 3]``.
        goal: ``[..., 3]``.
        centres: ``[..., K, 3]``, the obstacles at the current time.
        radii: ``[..., K]``.
        velocities: ``[..., K, 3]``.
        rho0: ``[...]``.
        sigma0: ``[...]``.
        tau: ``[...]``.
        dt: step in seconds.
        v0: attractive flow speed ``V0``.

    Returns:
        ``p'`` of shape ``[..., 3]``.
    """
    return position + dt * iifds_velocity(
        position, goal, centres, radii, velocities, rho0, sigma0, tau, v0
    )
