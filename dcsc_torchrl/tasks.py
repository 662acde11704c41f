"""The task registry: one :class:`~dcsc_torchrl.task.Task` entry per task, filled with the
library's factories (envs, operators, networks, figures).

The top of the library: it wires the modules below it and none of them imports it (they
take a ``Task``); the application resolves a task's name here, once, at its door. A third
task is one more entry in :data:`TASKS` (docs/architecture.md, "Adding a task").

This module imports neither torch nor gymnasium: the ``dcsc`` command reads the task
names from it before the libraries load; the factories import what they build on their
first call.

Examples:
    >>> task = get_task("uav")
    >>> task.machine_label, task.action_dims, task.action_names
    ('DDPG', 3, ('rho', 'sigma', 'tau'))
    >>> get_task("lunar")
    Traceback (most recent call last):
    ...
    ValueError: unknown task 'lunar': expected one of lunarlander, uav
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from dcsc_torchrl.task import Task

if TYPE_CHECKING:
    from pathlib import Path

    import pandas as pd
    import torch
    from torch import nn
    from torchrl.envs import Transform, TransformedEnv

    from dcsc_torchrl.copilot import CopilotQNetwork
    from dcsc_torchrl.transforms import HumanOperator


def _lunar_envs(scenario_seeds: Sequence[int], max_steps: int | None, transforms: Sequence[Transform], *,
                render: bool = False) -> TransformedEnv:
    """TargetLunarLanders with a random pad, env ``i`` playing scenario ``scenario_seeds[i]``.

    The vector env is seeded once (env ``i`` gets ``seed + i``), so the seeds must be
    consecutive. ``render``: gymnasium's ``rgb_array`` frames of env 0 (``env.base_env.render()``).
    """
    from dcsc_torchrl.batched_envs import make_lunar_env

    seeds = list(scenario_seeds)
    if seeds != list(range(seeds[0], seeds[0] + len(seeds))):
        raise ValueError(f"LunarLander scenarios must be consecutive seeds (one vector env seeded once), got {seeds}")
    env = make_lunar_env(len(seeds), random_pad=True, max_steps=max_steps, transforms=list(transforms),
                         render_mode="rgb_array" if render else None)
    env.set_seed(seeds[0])
    return env


def _uav_envs(scenario_seeds: Sequence[int], max_steps: int | None, transforms: Sequence[Transform], *,
              render: bool = False) -> TransformedEnv:
    """One native batched UAV env, env ``i`` flying scenario ``scenario_seeds[i]``.

    ``render`` changes nothing: the UAV's person draws its own frame from the TensorDict
    (:class:`~dcsc_torchrl.humans.UAVKeyboardOperator`).
    """
    from dcsc_torchrl.batched_envs import make_uav_env

    return make_uav_env(len(scenario_seeds), scenario_seeds=list(scenario_seeds), max_steps=max_steps,
                        transforms=list(transforms))


def _lunar_pretraining_envs(num_envs: int) -> TransformedEnv:
    """The standard task (pad at the centre), as A2C pretrains on it."""
    from dcsc_torchrl.batched_envs import make_lunar_env

    return make_lunar_env(num_envs, random_pad=False)


def _uav_pretraining_envs(num_envs: int) -> TransformedEnv:
    """Fresh UAV scenarios (never a validation seed), as DDPG pretrains on them."""
    from dcsc_torchrl.batched_envs import make_uav_env

    return make_uav_env(num_envs)


def _pilot(preset: str) -> HumanOperator:
    from dcsc_torchrl.humans import SimulatedPilot

    return SimulatedPilot.from_preset(preset)


def _uav_operator(preset: str) -> HumanOperator:
    from dcsc_torchrl.humans import SimulatedOperator

    return SimulatedOperator.from_preset(preset)


def _lunar_person(t_d: float) -> HumanOperator:
    from dcsc_torchrl.humans import KeyboardPilot

    return KeyboardPilot(t_d=t_d)


def _uav_person(t_d: float) -> HumanOperator:
    from dcsc_torchrl.humans import UAVKeyboardOperator

    return UAVKeyboardOperator(t_d=t_d)


def _lunar_networks(network: Mapping[str, Any]) -> tuple[nn.Module, nn.Module]:
    from dcsc_torchrl.networks import (
        LUNAR_QVALUE_DIMS,
        lunar_actor,
        lunar_critic,
        lunar_machine_dims,
        machine_view,
    )

    obs_dims = lunar_machine_dims(machine_view(network))
    return (lunar_actor(network["hidden"], network["actor_dropout"], obs_dims=obs_dims),
            lunar_critic(network["hidden"], 4, obs_dims=LUNAR_QVALUE_DIMS))


def _uav_networks(network: Mapping[str, Any]) -> tuple[nn.Module, nn.Module]:
    from dcsc_torchrl.networks import uav_actor, uav_critic

    return uav_actor(network["hidden"], network["actor_dropout"]), uav_critic(network["hidden"])


def _over_the_pad(observation: torch.Tensor) -> torch.Tensor:
    """Whether the lander is above the pad, within half its half-width of the centre
    (:data:`dcsc_torchrl.envs.target_lunar_lander.PAD_HALF_WIDTH`; docs/records/experiment_log.md)."""
    from dcsc_torchrl.envs.target_lunar_lander import PAD_HALF_WIDTH

    return (observation[..., 0] - observation[..., 8]).abs() < PAD_HALF_WIDTH / 2


def _lunar_coordinates(observation: torch.Tensor) -> dict[str, torch.Tensor]:
    """Where the lander is against the pad: its x minus the pad's x, and its altitude."""
    return {"x − pad": observation[..., 0] - observation[..., 8], "altitude": observation[..., 1]}


def _uav_coordinates(observation: torch.Tensor) -> dict[str, torch.Tensor]:
    """Where the UAV is against the obstacles and the goal: the distance to the nearest
    obstacle's surface and to the goal (the norms of the observation's first two vectors)."""
    return {"distance to the nearest obstacle": observation[..., 0:3].norm(dim=-1),
            "distance to the goal": observation[..., 3:6].norm(dim=-1)}


def _lunar_copilot_network(hidden: Sequence[int]) -> CopilotQNetwork:
    """Reddy et al.'s LunarLander copilot: the 4 keys, the pad's x masked (deepassist's ``obs[8]``)."""
    import torch

    from dcsc_torchrl.copilot import CopilotQNetwork
    from dcsc_torchrl.networks import LUNAR_MACHINE_VIEWS, LUNAR_OBS_DIMS

    return CopilotQNetwork(hidden, torch.eye(4), in_dims=LUNAR_OBS_DIMS, obs_dims=LUNAR_MACHINE_VIEWS["blind"])


def _uav_copilot_network(hidden: Sequence[int]) -> CopilotQNetwork:
    """The UAV copilot: the simulated operator's 27 ``(rho0, sigma0, tau)`` grid points (a person's
    keys are 9 of them), the whole 9-value observation the DDPG machine reads (the paper's machine
    knows the goal: the pilot's intent here is the way round the obstacles, not where to go)."""
    import torch

    from dcsc_torchrl.copilot import CopilotQNetwork
    from dcsc_torchrl.humans.uav_operator import DEFAULT_GRID

    return CopilotQNetwork(hidden, torch.tensor(DEFAULT_GRID), in_dims=9)


def _lunar_copilot_envs(num_envs: int, transforms: Sequence[Transform]) -> TransformedEnv:
    """TargetLunarLanders with a random pad, as the cells draw them."""
    from dcsc_torchrl.batched_envs import make_lunar_env

    return make_lunar_env(num_envs, random_pad=True, transforms=list(transforms))


def _uav_copilot_envs(num_envs: int, transforms: Sequence[Transform]) -> TransformedEnv:
    """Fresh UAV scenarios (never a validation seed), as DDPG pretrains on them."""
    from dcsc_torchrl.batched_envs import make_uav_env

    return make_uav_env(num_envs, transforms=list(transforms))


def _uav_trajectories(trace: pd.DataFrame, scenario_seed: int, path: Path, title: str,
                      label: Callable[[str], str]) -> Path:
    from dcsc_torchrl.report import plot_uav_trajectories

    return plot_uav_trajectories(trace, scenario_seed, path, title, label)


TASKS: dict[str, Task] = {
    task.name: task
    for task in (
        Task(
            name="lunarlander", title="LunarLander (moving pad)", machine_label="A2C", discrete=True,
            action_dims=1, action_names=(), info_keys=("success", "crashed", "landed_outside"),
            episode_keys=("success",), metrics=("success", "steps", "return"), max_steps=1000,
            checkpoint_modules=("actor", "qvalue"),
            make_envs=_lunar_envs, make_operator=_pilot, make_networks=_lunar_networks,
            make_pretraining_envs=_lunar_pretraining_envs, make_person=_lunar_person,
            authority_rule=_over_the_pad,
            make_copilot_network=_lunar_copilot_network, make_copilot_envs=_lunar_copilot_envs,
            state_coordinates=_lunar_coordinates,
        ),
        Task(
            name="uav", title="UAV path planning", machine_label="DDPG", discrete=False,
            action_dims=3, action_names=("rho", "sigma", "tau"),
            info_keys=("success", "collision", "out_of_bounds", "path_length"),
            episode_keys=("success", "path_length"), metrics=("success", "path_length", "return"), max_steps=500,
            checkpoint_modules=("actor", "critic"), trace_vectors={"position": "xyz"}, action_labels=("ρ0", "σ0", "τ"),
            state_coordinates=_uav_coordinates,
            make_envs=_uav_envs, make_operator=_uav_operator, make_networks=_uav_networks,
            make_pretraining_envs=_uav_pretraining_envs, make_person=_uav_person,
            plot_trajectories=_uav_trajectories,
            make_copilot_network=_uav_copilot_network, make_copilot_envs=_uav_copilot_envs,
        ),
    )
}
"""Every task, by name."""
TASK_NAMES = tuple(TASKS)
COPILOT_TASK_NAMES = tuple(name for name, task in TASKS.items() if task.make_copilot_network is not None)
"""The tasks with Reddy et al.'s copilot (``dcsc copilot TASK``, method ``reddy``)."""


def get_task(name: str) -> Task:
    """The registered task ``name``; a :class:`ValueError` naming the known ones otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}: expected one of {', '.join(TASKS)}")
    return TASKS[name]
