"""Reference forms of the IIFDS pieces the library computes fused (tests only).

The field itself (:func:`dcsc_torchrl.envs.iifds.iifds_velocity`) applies each sphere's
modulation matrix to a vector without forming it; these return the paper's objects as
printed, so the tests can compare the two.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dcsc_torchrl.envs.iifds import _modulation_terms


def sphere_gamma(position: Tensor, centre: Tensor, radius: Tensor) -> Tensor:
    """Sphere surface function ``Γ = ||p - c||^2 / R^2`` (< 1 inside, 1 on, > 1 outside).

    Args:
        position: ``[..., 3]``.
        centre: ``[..., 3]`` (broadcast with ``position``).
        radius: ``[...]``, positive.

    Returns:
        ``Γ`` of shape ``[...]``.
    """
    return (position - centre).square().sum(-1) / radius.square()


def sphere_normal(position: Tensor, centre: Tensor, radius: Tensor) -> Tensor:
    """Gradient of the sphere surface function, ``n = ∇Γ = 2 (p - c) / R^2``.

    Args:
        position: ``[..., 3]``.
        centre: ``[..., 3]``.
        radius: ``[...]``, positive.

    Returns:
        ``n`` of shape ``[..., 3]``; zero at the centre (the field uses the unit normal
        from :func:`tangent_basis`, which picks ``+z`` there).
    """
    return 2 * (position - centre) / radius.square().unsqueeze(-1)


def modulation_matrix(
    position: Tensor,
    goal: Tensor,
    centre: Tensor,
    radius: Tensor,
    rho0: Tensor,
    sigma0: Tensor,
    tau: Tensor,
) -> Tensor:
    """Modulation matrix of one sphere, ``M = I - n n^T / (Γ^(1/ρ) n^T n) + t n^T / (Γ^(1/σ) ||t|| ||n||)``.

    The repulsive term (second) removes the flow's component along the normal near the
    surface; the tangential term (third) turns it along ``t = cos(τ) t1_hat + sin(τ)
    t2_hat``. ``ρ = ρ0 exp(1 - 1/(d_g d_s))`` and ``σ = σ0 exp(1 - 1/(d_g d_s))`` with
    ``d_s = ||p - c|| - R`` and ``d_g = ||p - g||``; ``ρ0``, ``σ0`` are floored at
    ``COEFFICIENT_FLOOR``. Whether the flow moves away from the obstacle (``M = I``) is
    decided in :func:`iifds_velocity`, which applies ``M`` to a vector without forming it.

    Args:
        position: UAV position ``[..., 3]``.
        goal: ``[..., 3]``.
        centre: obstacle centre ``[..., 3]``.
        radius: ``[...]``.
        rho0: repulsive response coefficient ``[...]`` (action 0, in [0, 3]).
        sigma0: tangential response coefficient ``[...]`` (action 1, in [0, 3]).
        tau: tangent direction angle ``[...]`` (action 2, in [0, 3]).

    Returns:
        ``M`` of shape ``[..., 3, 3]``.
    """
    _, n_hat, tangent, repulsive, tangential = _modulation_terms(position, goal, centre, radius, rho0, sigma0, tau)
    n_row = n_hat.unsqueeze(-2)
    identity = torch.eye(3, dtype=position.dtype, device=position.device)
    return (
        identity
        - repulsive[..., None, None] * n_hat.unsqueeze(-1) * n_row
        + tangential[..., None, None] * tangent.unsqueeze(-1) * n_row
    )
