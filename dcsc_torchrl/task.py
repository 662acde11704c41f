"""The type of a task: everything the library knows about one task, in one typed entry.

A :class:`Task` says how to build the task's batched env, its simulated operator and its
pretrained machine, what kind of action the machine outputs, which keys the env writes,
and how its frames are traced and labelled. No code asks which task it runs
(``if task == ...``): it reads the entry. The library's modules take a ``Task``; the
registry that fills the entries with the library's factories is :mod:`dcsc_torchrl.tasks`,
on top of the library (nothing below imports it), and which recipe pretrains a task is
the application's table (:mod:`dcsc_torchrl.recipes.registry`).

This module imports neither torch nor gymnasium.
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
        checkpoint_modules: the names of the actor and critic state dicts in a checkpoint.
        trace_vectors: vectors of the next frame traced per component, e.g. ``{"position": "xyz"}``.
        action_labels: the components' axis labels in figures (default: their names).
        plot_trajectories: ``(trace, scenario seed, path, title, label) -> path``, the figure of the
            traced paths, each method named by ``label(method)``, for a task whose frames have
            positions (``None``: no such figure).
        authority_rule: the task's rule-based switch, the ``rule`` method
            (:class:`~dcsc_torchrl.arbiters.RuleArbiter`): ``observation [*batch, obs] -> [*batch]``
            bool, where the machine holds the controls (``None``: the task has none, and the
            protocol skips that method).
        make_envs: ``(scenario_seeds, max_steps, transforms, *, render=False) -> TransformedEnv``, one env per
            scenario; with ``render`` the base env's ``render()`` (where it has one) draws env 0 for
            :attr:`make_person`'s window.
        make_operator: ``preset -> HumanOperator``, the simulated operator with a preset's traits.
        make_networks: ``network config group -> (actor, critic)``, the pretraining recipe's networks.
        make_pretraining_envs: ``num_envs -> env``, the batched env the machine is pretrained on.
        make_person: ``t_d -> HumanOperator``, a person at the controls in a window (``dcsc study``;
            ``t_d`` of Eq. 6: no change of the controls for longer is a slow decision).
        make_copilot_network: ``hidden -> CopilotQNetwork`` (:mod:`dcsc_torchrl.copilot`), Reddy et al.'s copilot Q network on
            what the task lets it see and its finite action set (:mod:`dcsc_torchrl.copilot`);
            ``None``: the task has no copilot, and no ``reddy`` method.
        make_copilot_envs: ``(num_envs, transforms) -> env``, fresh scenarios drawn as the
            evaluation draws them (never a validation seed), the copilot's training envs.
        state_coordinates: ``observation [*batch, obs] -> {name: [*batch]}``, the two
            coordinates of the state a figure of beta over the state is drawn against
            (LunarLander: x minus the pad's x, and altitude); ``None``: no such figure.
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
    checkpoint_modules: tuple[str, str]
    make_envs: Callable[..., TransformedEnv] = field(repr=False)
    make_operator: Callable[[str], HumanOperator] = field(repr=False)
    make_networks: Callable[[Mapping[str, Any]], tuple[nn.Module, nn.Module]] = field(repr=False)
    make_pretraining_envs: Callable[[int], TransformedEnv] = field(repr=False)
    make_person: Callable[[float], HumanOperator] = field(repr=False)
    trace_vectors: Mapping[str, str] = field(default_factory=dict)
    action_labels: tuple[str, ...] = ()
    plot_trajectories: Callable[[pd.DataFrame, int, Path, str, Callable[[str], str]], Path] | None = field(default=None, repr=False)
    authority_rule: Callable[[torch.Tensor], torch.Tensor] | None = field(default=None, repr=False)
    make_copilot_network: Callable[[Sequence[int]], nn.Module] | None = field(default=None, repr=False)
    make_copilot_envs: Callable[[int, Sequence[Transform]], TransformedEnv] | None = field(default=None, repr=False)
    state_coordinates: Callable[[torch.Tensor], dict[str, torch.Tensor]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not self.action_labels:
            object.__setattr__(self, "action_labels", self.action_names)
