"""3-D plot of one UAV episode: the path, the obstacles' tracks, start and goal."""

from __future__ import annotations

import numpy as np
import torch
from matplotlib.figure import Figure
from torch import Tensor

from dcsc_torchrl.envs.uav import ARENA_HIGH, ARENA_LOW, DT, GOAL_RADIUS, obstacle_states

__all__ = ["plot_uav_episode"]


def _sphere(centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    azimuth, polar = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    return (
        centre[0] + radius * np.cos(azimuth) * np.sin(polar),
        centre[1] + radius * np.sin(azimuth) * np.sin(polar),
        centre[2] + radius * np.cos(polar),
    )


def plot_uav_episode(
    path: Tensor | np.ndarray,
    obstacle_params: Tensor,
    goal: Tensor | np.ndarray,
    *,
    dt: float = DT,
    title: str = "UAV episode",
    label: str = "UAV path",
) -> Figure:
    """Draws an episode in 3-D and returns the Figure (no pyplot state; Agg-safe).

    The obstacles' tracks are drawn over the episode's duration, with each obstacle as
    a wire sphere where it is at the end; the goal is drawn with its radius.

    Args:
        path: UAV positions ``[T, 3]``, one per step from the start (``path[0]``).
        obstacle_params: the scenario's ``[K, N_OBSTACLE_PARAMS]``.
        goal: ``[3]``.
        dt: seconds between consecutive positions.
        title: the axes' title.
        label: the path's legend entry.

    Returns:
        The matplotlib Figure (save it with ``fig.savefig(...)``).

    Examples:
        >>> import torch
        >>> from envs.uav import UAVPathPlanningEnv
        >>> env = UAVPathPlanningEnv(scenario_seeds=[0])
        >>> rollout = env.rollout(500, lambda td: td.set("action", torch.ones(1, 3)))
        >>> path = torch.cat([rollout["position"][0], rollout["next", "position"][0, -1:]])
        >>> fig = plot_uav_episode(path, rollout["obstacle_params"][0, 0], rollout["goal"][0, 0])
    """
    path = np.asarray(torch.as_tensor(path).detach().cpu(), dtype=float)
    goal = np.asarray(torch.as_tensor(goal).detach().cpu(), dtype=float)
    params = torch.as_tensor(obstacle_params).detach().cpu().float()
    times = torch.arange(len(path), dtype=torch.float32) * dt
    centres, _, radii = obstacle_states(params, times)  # [T, K, 3], [T, K]
    centres, radii = centres.numpy(), radii[-1].numpy()

    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*path.T, color="tab:blue", linewidth=2, label=label)
    colours = [f"C{i + 1}" for i in range(centres.shape[1])]
    for k, colour in enumerate(colours):
        ax.plot(
            *centres[:, k].T,
            color=colour,
            linestyle="--",
            linewidth=1,
            label=f"obstacle {k + 1} track",
        )
        ax.plot_wireframe(
            *_sphere(centres[-1, k], float(radii[k])), color=colour, linewidth=0.4, alpha=0.6
        )
    ax.scatter(*path[0], color="tab:green", marker="o", s=40, label="start")
    ax.scatter(*goal, color="tab:red", marker="*", s=120, label="goal")
    ax.plot_wireframe(*_sphere(goal, GOAL_RADIUS), color="tab:red", linewidth=0.4)
    ax.set(
        xlim=(ARENA_LOW[0], ARENA_HIGH[0]),
        ylim=(ARENA_LOW[1], ARENA_HIGH[1]),
        zlim=(ARENA_LOW[2], ARENA_HIGH[2]),
        xlabel="x",
        ylabel="y",
        zlabel="z",
        title=title,
    )
    ax.set_box_aspect(np.subtract(ARENA_HIGH, ARENA_LOW))
    ax.legend(loc="upper left", fontsize="small")
    return fig
