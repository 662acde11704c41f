"""Where each task's yaml configs are: the application's table (imports no torch).

The library's :class:`~dcsc_torchrl.task.Task` says how to build a task; this table says
which yaml configures its shared-control protocol and which its pretraining recipe. The
yamls ship inside the package (``dcsc_torchrl/recipes/*.yaml``, the repository's
``recipes/``), so the ``dcsc`` command checks a config before torch loads.

Examples:
    >>> CONFIGS["uav"].pretrain.name
    'pretrain_ddpg_uav.yaml'
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

RECIPES_DIR = Path(__file__).parent
"""The folder of the recipes and their yamls."""
SWEEP_CONFIG = RECIPES_DIR / "sweep.yaml"
MAP_CONFIG = RECIPES_DIR / "map.yaml"


@dataclass(frozen=True)
class TaskConfigs:
    """A task's yamls: its shared-control protocol (over ``shared_control.yaml``), its pretraining
    and Reddy et al.'s copilot (``dcsc copilot``, over ``copilot.yaml``)."""

    protocol: Path
    pretrain: Path
    copilot: Path


CONFIGS: dict[str, TaskConfigs] = {
    "lunarlander": TaskConfigs(RECIPES_DIR / "shared_control_lunarlander.yaml",
                               RECIPES_DIR / "pretrain_a2c_lunarlander.yaml", RECIPES_DIR / "copilot_lunarlander.yaml"),
    "uav": TaskConfigs(RECIPES_DIR / "shared_control_uav.yaml", RECIPES_DIR / "pretrain_ddpg_uav.yaml",
                       RECIPES_DIR / "copilot_uav.yaml"),
}
"""Every task's configs, by task name (the names of :data:`dcsc_torchrl.tasks.TASKS`)."""
