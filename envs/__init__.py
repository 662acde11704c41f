"""The two DC-SC tasks, registered with gymnasium on import.

- ``dcsc/TargetLunarLander-v0``: :class:`TargetLunarLander` (discrete, 9-dim
  observation with the pad's x), 1000-frame time limit; :func:`target_heuristic` is a
  pilot that lands on the moved pad.
- ``dcsc/UAVPathPlanning-v0``: :class:`UAVPathPlanningGymEnv`, one scenario of the
  batched TorchRL env :class:`UAVPathPlanningEnv`.

See ``docs/envs.md``.
"""

from gymnasium.envs.registration import register, registry

from dcsc_torchrl.envs.iifds import iifds_step, iifds_velocity
from dcsc_torchrl.envs.target_lunar_lander import TargetLunarLander, target_heuristic
from dcsc_torchrl.envs.uav import (
    BEST_CONSTANT_ACTION,
    N_OBSTACLE_PARAMS,
    N_OBSTACLES,
    ObstacleFamily,
    ObstacleParam,
    UAVPathPlanningEnv,
    UAVPathPlanningGymEnv,
    UAVScenario,
    best_constant_action,
    constant_action_outcomes,
    obstacle_states,
    sample_scenario,
    sample_scenarios,
)
from dcsc_torchrl.envs.uav_plot import plot_uav_episode

__all__ = [
    "BEST_CONSTANT_ACTION",
    "N_OBSTACLES",
    "N_OBSTACLE_PARAMS",
    "ObstacleFamily",
    "ObstacleParam",
    "TargetLunarLander",
    "UAVPathPlanningEnv",
    "UAVPathPlanningGymEnv",
    "UAVScenario",
    "best_constant_action",
    "constant_action_outcomes",
    "iifds_step",
    "iifds_velocity",
    "obstacle_states",
    "plot_uav_episode",
    "sample_scenario",
    "sample_scenarios",
    "target_heuristic",
]

if "dcsc/TargetLunarLander-v0" not in registry:
    register(
        id="dcsc/TargetLunarLander-v0",
        entry_point="dcsc_torchrl.envs.target_lunar_lander:TargetLunarLander",
        max_episode_steps=1000,
    )
if "dcsc/UAVPathPlanning-v0" not in registry:
    register(id="dcsc/UAVPathPlanning-v0", entry_point="dcsc_torchrl.envs.uav:UAVPathPlanningGymEnv")
