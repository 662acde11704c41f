"""The task registry: everything the project knows about a task, in one typed entry.

A :class:`Task` says how to build the task's batched env, its simulated operator and its
pretrained machine, what kind of action the machine outputs, which keys the env writes,
how its frames are traced and labelled, and which recipe pretrains it. No other code asks
which task it runs (``if task == ...``): it reads the entry. A third task is one more
entry in :data:`TASKS` (docs/architecture.md, "Adding a task").

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
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pathlib import Path

    import pandas as pd
    import torch
    from torch import nn
    from torchrl.envs import Transform, TransformedEnv

    from dcsc_torchrl.transforms import HumanOperator


@dataclass(frozen=True)
class Task:
    """One task of the project.

    Args:
        name: the task's name on the command line, in CSVs and checkpoints.
        title: the task's name in reports and figures.
        machine_label: what the machine alone is called in tables (its pretraining algorithm).
        discrete: ``True``: the machine outputs key probabilities (``MCDropoutPolicy(output="probs")``)
            and the arbiter one beta; ``False``: a continuous action, one beta per dimension.
        action_dims: the arbiter's beta (and theta) dimensions.
        action_names: the continuous action's components (trace columns ``beta_<name>``, ...);
            empty for a discrete action.
        info_keys: what the env writes besides the reward (``success`` first).
        episode_keys: the per-episode values of ``episodes.csv`` read from the final frame.
        metrics: the report's columns, in order.
        max_steps: the task's own episode limit.
        config: the shared-control recipe's yaml (in ``recipes/``).
        pretrain_recipe: the module that pretrains the machine (``train(cfg) -> Path``).
        checkpoint_modules: the names of the actor and critic state dicts in a checkpoint.
        trace_vectors: vectors of the next frame traced per component, e.g. ``{"position": "xyz"}``.
        action_labels: the components' axis labels in figures (default: their names).
        plot_trajectories: ``(trace, scenario seed, path, title) -> path``, the figure of the traced
            paths, for a task whose frames have positions (``None``: no such figure).
        authority_rule: the task's rule-based switch, the ``rule`` method
            (:class:`~dcsc_torchrl.arbiters.RuleArbiter`): ``observation [*batch, obs] -> [*batch]``
            bool, where the machine holds the controls (``None``: the task has none, and the
            protocol skips that method).
        make_envs: ``(scenario_seeds, max_steps, transforms) -> TransformedEnv``, one env per scenario.
        make_operator: ``preset -> HumanOperator``, the simulated operator with a preset's traits.
        make_networks: ``network config group -> (actor, critic)``, the pretraining recipe's networks.
        make_pretraining_envs: ``num_envs -> env``, the batched env the machine is pretrained on.
    """

    name: str
    title: str
    machine_label: str
    discrete: bool
    action_dims: int
    action_names: tuple[str, ...]
    info_keys: tuple[str, ...]
    episode_keys: tuple[str, ...]
    metrics: tuple[str, ...]
    max_steps: int
    config: str
    pretrain_recipe: str
    checkpoint_modules: tuple[str, str]
    make_envs: Callable[[Sequence[int], int | None, Sequence[Transform]], TransformedEnv] = field(repr=False)
    make_operator: Callable[[str], HumanOperator] = field(repr=False)
    make_networks: Callable[[Mapping[str, Any]], tuple[nn.Module, nn.Module]] = field(repr=False)
    make_pretraining_envs: Callable[[int], TransformedEnv] = field(repr=False)
    trace_vectors: Mapping[str, str] = field(default_factory=dict)
    action_labels: tuple[str, ...] = ()
    plot_trajectories: Callable[[pd.DataFrame, int, Path, str], Path] | None = field(default=None, repr=False)
    authority_rule: Callable[[torch.Tensor], torch.Tensor] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not self.action_labels:
            object.__setattr__(self, "action_labels", self.action_names)


def _lunar_envs(scenario_seeds: Sequence[int], max_steps: int | None, transforms: Sequence[Transform]) -> TransformedEnv:
    """TargetLunarLanders with a random pad, env ``i`` playing scenario ``scenario_seeds[i]``.

    The vector env is seeded once (env ``i`` gets ``seed + i``), so the seeds must be
    consecutive.
    """
    from dcsc_torchrl.batched_envs import make_lunar_env

    seeds = list(scenario_seeds)
    if seeds != list(range(seeds[0], seeds[0] + len(seeds))):
        raise ValueError(f"LunarLander scenarios must be consecutive seeds (one vector env seeded once), got {seeds}")
    env = make_lunar_env(len(seeds), random_pad=True, max_steps=max_steps, transforms=list(transforms))
    env.set_seed(seeds[0])
    return env


def _uav_envs(scenario_seeds: Sequence[int], max_steps: int | None, transforms: Sequence[Transform]) -> TransformedEnv:
    """One native batched UAV env, env ``i`` flying scenario ``scenario_seeds[i]``."""
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


def _lunar_networks(network: Mapping[str, Any]) -> tuple[nn.Module, nn.Module]:
    from dcsc_torchrl.networks import LUNAR_QVALUE_DIMS, lunar_actor, lunar_critic

    return (lunar_actor(network["hidden"], network["actor_dropout"]),
            lunar_critic(network["hidden"], 4, obs_dims=LUNAR_QVALUE_DIMS))


def _uav_networks(network: Mapping[str, Any]) -> tuple[nn.Module, nn.Module]:
    from dcsc_torchrl.networks import uav_actor, uav_critic

    return uav_actor(network["hidden"], network["actor_dropout"]), uav_critic(network["hidden"])


def _over_the_pad(observation: torch.Tensor) -> torch.Tensor:
    """Whether the lander is above the pad, within half its half-width of the centre
    (:data:`dcsc_torchrl.envs.target_lunar_lander.PAD_HALF_WIDTH`; docs/records/experiment_log.md)."""
    from dcsc_torchrl.envs.target_lunar_lander import PAD_HALF_WIDTH

    return (observation[..., 0] - observation[..., 8]).abs() < PAD_HALF_WIDTH / 2


def _uav_trajectories(trace: pd.DataFrame, scenario_seed: int, path: Path, title: str) -> Path:
    from dcsc_torchrl.report import plot_uav_trajectories

    return plot_uav_trajectories(trace, scenario_seed, path, title)


TASKS: dict[str, Task] = {
    task.name: task
    for task in (
        Task(
            name="lunarlander", title="LunarLander (moving pad)", machine_label="A2C", discrete=True,
            action_dims=1, action_names=(), info_keys=("success", "crashed", "landed_outside"),
            episode_keys=("success",), metrics=("success", "steps", "return"), max_steps=1000,
            config="shared_control_lunarlander.yaml", pretrain_recipe="recipes.pretrain_a2c_lunarlander",
            checkpoint_modules=("actor", "qvalue"),
            make_envs=_lunar_envs, make_operator=_pilot, make_networks=_lunar_networks,
            make_pretraining_envs=_lunar_pretraining_envs,
            authority_rule=_over_the_pad,
        ),
        Task(
            name="uav", title="UAV path planning", machine_label="DDPG", discrete=False,
            action_dims=3, action_names=("rho", "sigma", "tau"),
            info_keys=("success", "collision", "out_of_bounds", "path_length"),
            episode_keys=("success", "path_length"), metrics=("success", "path_length", "return"), max_steps=500,
            config="shared_control_uav.yaml", pretrain_recipe="recipes.pretrain_ddpg_uav",
            checkpoint_modules=("actor", "critic"), trace_vectors={"position": "xyz"}, action_labels=("ρ0", "σ0", "τ"),
            make_envs=_uav_envs, make_operator=_uav_operator, make_networks=_uav_networks,
            make_pretraining_envs=_uav_pretraining_envs,
            plot_trajectories=_uav_trajectories,
        ),
    )
}
"""Every task, by name."""
TASK_NAMES = tuple(TASKS)


def get_task(name: str) -> Task:
    """The registered task ``name``; a :class:`ValueError` naming the known ones otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}: expected one of {', '.join(TASKS)}")
    return TASKS[name]
