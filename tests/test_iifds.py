"""IIFDS field: formulas, multi-obstacle blending, batching and finiteness at the edges."""

import math

import pytest
import torch
from iifds_reference import modulation_matrix, sphere_gamma, sphere_normal

from dcsc_torchrl.envs.iifds import (
    COEFFICIENT_FLOOR,
    SPEED_CAP,
    attractive_flow,
    iifds_step,
    iifds_velocity,
    obstacle_weights,
    tangent_basis,
    transported_velocity,
)

GOAL = torch.tensor([10.0, 10.0, 5.5], dtype=torch.float64)


def _reference_matrix(p, goal, c, r, rho0, sigma0, tau):
    """M of the IIFDS written out directly (generic position, no guards)."""
    n = 2 * (p - c) / r**2
    gamma = float(((p - c) ** 2).sum() / r**2)
    d_s = float((p - c).norm()) - r
    d_g = float((p - goal).norm())
    rho = rho0 * math.exp(1 - 1 / (d_g * d_s))
    sigma = sigma0 * math.exp(1 - 1 / (d_g * d_s))
    nx, ny, nz = n.tolist()
    t1 = torch.tensor([ny, -nx, 0.0], dtype=p.dtype)
    t2 = torch.tensor([nx * nz, ny * nz, -(nx**2 + ny**2)], dtype=p.dtype)
    t = math.cos(tau) * t1 / t1.norm() + math.sin(tau) * t2 / t2.norm()
    return (
        torch.eye(3, dtype=p.dtype)
        - torch.outer(n, n) / (gamma ** (1 / rho) * (n @ n))
        + torch.outer(t, n) / (gamma ** (1 / sigma) * t.norm() * n.norm())
    )


def _scalar(value: float) -> torch.Tensor:
    return torch.tensor(value, dtype=torch.float64)


def test_sphere_gamma_is_one_on_the_surface():
    centre = torch.tensor([1.0, 2.0, 3.0])
    on_surface = centre + 1.5 * torch.tensor([0.6, 0.0, 0.8])
    assert sphere_gamma(on_surface, centre, torch.tensor(1.5)) == pytest.approx(1.0)
    assert sphere_gamma(centre + 3.0, centre, torch.tensor(1.5)) > 1.0


def test_sphere_normal_is_the_gradient_of_gamma():
    p = torch.tensor([1.3, -0.4, 2.2], dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([0.5, 0.1, 1.0], dtype=torch.float64)
    radius = _scalar(0.8)
    (grad,) = torch.autograd.grad(sphere_gamma(p, centre, radius), p)
    torch.testing.assert_close(sphere_normal(p.detach(), centre, radius), grad)


@pytest.mark.parametrize(
    "normal",
    [[0.3, -1.2, 0.7], [0.0, 0.0, 2.0], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [1e-12, 0.0, 1.0]],
)
def test_tangent_basis_is_orthonormal_and_finite_at_the_singular_normals(normal):
    n_hat, t1, t2 = tangent_basis(torch.tensor(normal, dtype=torch.float64))
    basis = torch.stack([n_hat, t1, t2])
    assert torch.isfinite(basis).all()
    torch.testing.assert_close(basis @ basis.T, torch.eye(3, dtype=torch.float64))


def test_tangent_basis_matches_the_design_vectors():
    nx, ny, nz = 0.3, -1.2, 0.7
    _, t1, t2 = tangent_basis(torch.tensor([nx, ny, nz], dtype=torch.float64))
    t1_ref = torch.tensor([ny, -nx, 0.0], dtype=torch.float64)
    t2_ref = torch.tensor([nx * nz, ny * nz, -(nx**2 + ny**2)], dtype=torch.float64)
    torch.testing.assert_close(t1, t1_ref / t1_ref.norm())
    torch.testing.assert_close(t2, t2_ref / t2_ref.norm())


@pytest.mark.parametrize("rho0, sigma0, tau", [(1.0, 1.5, 1.5), (0.4, 2.5, 0.3), (3.0, 0.2, 2.9)])
def test_modulation_matrix_matches_the_formula(rho0, sigma0, tau):
    p = torch.tensor([3.1, 4.0, 5.6], dtype=torch.float64)
    centre = torch.tensor([4.0, 5.2, 5.0], dtype=torch.float64)
    radius = 1.0
    matrix = modulation_matrix(
        p, GOAL, centre, _scalar(radius), _scalar(rho0), _scalar(sigma0), _scalar(tau)
    )
    torch.testing.assert_close(
        matrix, _reference_matrix(p, GOAL, centre, radius, rho0, sigma0, tau)
    )


def test_zero_coefficients_are_floored_and_finite():
    p = torch.tensor([3.1, 4.0, 5.6], dtype=torch.float64)
    centre = torch.tensor([4.0, 5.2, 5.0], dtype=torch.float64)
    args = (p, GOAL, centre, _scalar(1.0))
    zero = modulation_matrix(*args, _scalar(0.0), _scalar(0.0), _scalar(1.0))
    floored = modulation_matrix(
        *args, _scalar(COEFFICIENT_FLOOR), _scalar(COEFFICIENT_FLOOR), _scalar(1.0)
    )
    assert torch.isfinite(zero).all()
    torch.testing.assert_close(zero, floored)


def test_obstacle_weights_sum_to_one_and_favour_the_nearest():
    gamma = torch.tensor([[1.2, 4.0, 30.0], [1.0, 1.0, 9.0], [0.2, 2.0, 2.0]])
    weights = obstacle_weights(gamma)
    assert torch.isfinite(weights).all()
    torch.testing.assert_close(weights.sum(-1), torch.ones(3))
    assert weights[0].argmax() == 0 and weights[0, 0] > 0.7
    torch.testing.assert_close(obstacle_weights(torch.tensor([[7.0]])), torch.ones(1, 1))


def test_obstacle_weights_follow_the_product_formula():
    gamma = torch.tensor([1.5, 2.0, 5.0], dtype=torch.float64)
    excess = gamma - 1
    raw = torch.stack(
        [
            math.prod(excess[i] / (excess[i] + excess[k]) for i in range(3) if i != k)
            for k in range(3)
        ]
    )
    torch.testing.assert_close(obstacle_weights(gamma), raw / raw.sum())


def test_an_obstacle_bends_the_flow_less_the_farther_it_is():
    p = torch.tensor([[0.0, 2.0, 5.0]])
    goal = GOAL.float()[None]
    action = torch.tensor([1.0])
    deflections = []
    for distance in [5.0, 10.0, 100.0, 1000.0]:
        centre = p[:, None] + distance * torch.tensor([[[0.6, 0.8, 0.0]]])
        u_bar = iifds_velocity(
            p, goal, centre, torch.ones(1, 1), torch.zeros(1, 1, 3), action, action, action
        )
        deflections.append(float((u_bar - attractive_flow(p, goal)).norm()))
    assert deflections == sorted(deflections, reverse=True)
    assert deflections[-1] < 0.01


def test_an_obstacle_behind_the_uav_does_not_bend_the_flow():
    p = torch.tensor([[5.0, 5.0, 5.0]])
    behind = torch.tensor([[[3.5, 3.5, 5.0]]])
    action = torch.tensor([2.0])
    u_bar = iifds_velocity(
        p,
        GOAL.float()[None],
        behind,
        torch.ones(1, 1),
        torch.zeros(1, 1, 3),
        action,
        action,
        action,
    )
    torch.testing.assert_close(u_bar, attractive_flow(p, GOAL.float()[None]))


def test_single_moving_obstacle_uses_m_times_relative_flow_plus_carried_velocity():
    p = torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)
    centre = torch.tensor([3.2, 4.1, 5.3], dtype=torch.float64)
    velocity = torch.tensor([-0.5, -0.4, 0.2], dtype=torch.float64)
    radius, rho0, sigma0, tau = _scalar(1.0), _scalar(1.0), _scalar(1.5), _scalar(1.5)
    u = attractive_flow(p, GOAL)
    gamma = sphere_gamma(p, centre, radius)
    v_p = transported_velocity(gamma[None], velocity[None])[0]
    matrix = modulation_matrix(p, GOAL, centre, radius, rho0, sigma0, tau)
    expected = matrix @ (u - v_p) + v_p
    u_bar = iifds_velocity(p, GOAL, centre[None], radius[None], velocity[None], rho0, sigma0, tau)
    torch.testing.assert_close(u_bar, expected)
    torch.testing.assert_close(v_p, math.exp(-float(gamma) / 8) * velocity)


def test_static_obstacles_blend_as_m_bar_times_u():
    p = torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)
    centres = torch.tensor([[3.2, 4.1, 5.3], [3.0, 2.0, 6.5]], dtype=torch.float64)
    radii = torch.tensor([1.0, 0.8], dtype=torch.float64)
    rho0, sigma0, tau = _scalar(1.0), _scalar(1.5), _scalar(0.7)
    u = attractive_flow(p, GOAL)
    matrices = modulation_matrix(p[None], GOAL[None], centres, radii, rho0, sigma0, tau)
    approaching = ((p - centres) @ u) < 0
    matrices = torch.where(approaching[:, None, None], matrices, torch.eye(3, dtype=p.dtype))
    weights = obstacle_weights(sphere_gamma(p[None], centres, radii))
    m_bar = (weights[:, None, None] * matrices).sum(0)
    u_bar = iifds_velocity(
        p, GOAL, centres, radii, torch.zeros(2, 3, dtype=p.dtype), rho0, sigma0, tau
    )
    torch.testing.assert_close(u_bar, m_bar @ u)


def test_speed_is_capped():
    p = torch.tensor([[2.0, 3.0, 5.0]])
    centres = torch.tensor([[[2.9, 3.0, 5.0]]])
    fast = torch.tensor([[[-40.0, 10.0, 5.0]]])
    action = torch.tensor([0.0])
    u_bar = iifds_velocity(
        p, GOAL.float()[None], centres, torch.ones(1, 1), fast, action, action, action
    )
    assert u_bar.norm() == pytest.approx(SPEED_CAP)


@pytest.mark.parametrize(
    "position",
    [
        [4.0, 5.0, 7.0],  # straight above the centre: n_x = n_y = 0
        [4.0, 5.0, 3.5],  # straight below, inside
        [4.0, 5.0, 5.0],  # at the centre
        [4.0, 5.0, 6.0],  # on the surface, above the centre
        [5.0, 5.0, 5.0],  # on the surface
        [10.0, 10.0, 5.5],  # at the goal
    ],
)
@pytest.mark.parametrize("coefficients", [(0.0, 0.0, 0.0), (3.0, 3.0, 3.0), (1.0, 1.5, 1.5)])
def test_field_is_finite_at_the_singular_points(position, coefficients):
    p = torch.tensor([position])
    centres = torch.tensor([[[4.0, 5.0, 5.0], [9.0, 9.0, 5.0]]])
    velocities = torch.tensor([[[0.5, -1.0, 0.3], [0.0, 0.0, 0.0]]])
    rho0, sigma0, tau = (torch.tensor([c]) for c in coefficients)
    u_bar = iifds_velocity(
        p, GOAL.float()[None], centres, torch.ones(1, 2), velocities, rho0, sigma0, tau
    )
    assert torch.isfinite(u_bar).all()
    assert u_bar.norm() <= SPEED_CAP + 1e-5


def test_random_inputs_never_give_nan():
    generator = torch.Generator().manual_seed(0)
    batch, n_obstacles = 4096, 4
    p = 12 * torch.rand(batch, 3, generator=generator) - 1
    centres = 12 * torch.rand(batch, n_obstacles, 3, generator=generator) - 1
    radii = 0.2 + 1.5 * torch.rand(batch, n_obstacles, generator=generator)
    velocities = 4 * torch.randn(batch, n_obstacles, 3, generator=generator)
    actions = 3 * torch.rand(batch, 3, generator=generator)
    goal = GOAL.float().expand(batch, 3)
    stepped = iifds_step(p, goal, centres, radii, velocities, *actions.unbind(-1))
    assert stepped.shape == (batch, 3)
    assert torch.isfinite(stepped).all()


def test_extra_batch_dims_broadcast():
    p = torch.rand(2, 5, 3)
    centres = torch.rand(2, 5, 4, 3) + 3
    u_bar = iifds_velocity(
        p,
        GOAL.float(),
        centres,
        torch.ones(2, 5, 4),
        torch.zeros(2, 5, 4, 3),
        torch.ones(2, 5),
        torch.ones(2, 5),
        torch.ones(2, 5),
    )
    assert u_bar.shape == (2, 5, 3)
    flat = iifds_velocity(
        p[1, 3],
        GOAL.float(),
        centres[1, 3],
        torch.ones(4),
        torch.zeros(4, 3),
        torch.tensor(1.0),
        torch.tensor(1.0),
        torch.tensor(1.0),
    )
    torch.testing.assert_close(u_bar[1, 3], flat)


def test_the_flow_goes_around_a_static_obstacle_on_the_straight_line():
    p = torch.tensor([[0.0, 2.0, 5.0]])
    goal = GOAL.float()[None]
    centre = torch.tensor([[[5.0, 6.0, 5.25]]])  # on the start-goal line
    radius = torch.tensor([[1.5]])
    action = torch.tensor([1.0]), torch.tensor([1.5]), torch.tensor([1.5])
    closest = math.inf
    for _ in range(400):
        p = iifds_step(p, goal, centre, radius, torch.zeros(1, 1, 3), *action)
        closest = min(closest, float((p - centre[:, 0]).norm() - radius))
        if (p - goal).norm() < 0.2:
            break
    assert (p - goal).norm() < 0.2
    assert closest > 0.0
