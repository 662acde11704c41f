"""UAV path planning among moving spheres (the paper's continuous task), batched in torch.

A UAV flies from a start to the goal through ``N_OBSTACLES`` moving spherical obstacles,
steered by the IIFDS flow of :mod:`dcsc_torchrl.envs.iifds` whose coefficients ``(rho0, sigma0, tau)``
are the actions. This is the scenario of the paper's ref. [42]
(github.com/ZYunfeii/UAV_Obstacle_Avoiding_DRL) with these changes: every
obstacle shapes the flow (weighted), collisions end the episode, and a seed draws the
whole scenario (start and obstacle motions) from a family of parametric motions.

One module per job; this one gathers their names (as TorchRL's ``envs/transforms``
package does):

- :mod:`~dcsc_torchrl.envs.uav_scenarios` — the arena, :func:`obstacle_states` (centres,
  velocities and radii at time ``t`` from a scenario's trajectory parameters: the one
  function an operator needs to predict them), and the seeded scenario family
  (:func:`sample_scenarios` / :func:`sample_scenario`).
- :mod:`~dcsc_torchrl.envs.uav_env` — the reward (:func:`step_reward`) and
  :class:`UAVPathPlanningEnv`, the native TorchRL env, a batch of N scenarios.
- :mod:`~dcsc_torchrl.envs.uav_gym` — :class:`UAVPathPlanningGymEnv`, one scenario as a
  gymnasium env (``dcsc/UAVPathPlanning-v0``).
- :mod:`~dcsc_torchrl.envs.uav_constant` — the best constant IIFDS coefficients on a set
  of scenarios (a reference for the benchmarks and tests).

Examples:
    >>> import torch
    >>> env = UAVPathPlanningEnv(scenario_seeds=range(4))
    >>> td = env.reset()
    >>> td["observation"].shape, td["obstacle_params"].shape
    (torch.Size([4, 9]), torch.Size([4, 8, 18]))
    >>> rollout = env.rollout(10, lambda td: td.set("action", torch.ones(4, 3)))
    >>> rollout["next", "reward"].shape
    torch.Size([4, 10, 1])
"""

from __future__ import annotations

from dcsc_torchrl.envs.uav_constant import (
    BEST_CONSTANT_ACTION,
    BEST_CONSTANT_SEEDS,
    CONSTANT_GRID,
    best_constant_action,
    constant_action_outcomes,
)
from dcsc_torchrl.envs.uav_env import (
    COLLISION_REWARD,
    GOAL_REWARD,
    PROGRESS_REWARD,
    THREAT_COST,
    THREAT_MARGIN,
    TIME_COST,
    UAVPathPlanningEnv,
    step_reward,
)
from dcsc_torchrl.envs.uav_gym import (
    UAVPathPlanningGymEnv,
)
from dcsc_torchrl.envs.uav_scenarios import (
    ACTION_HIGH,
    ARENA_HIGH,
    ARENA_LOW,
    CORRIDOR_HIGH,
    CORRIDOR_LOW,
    DT,
    FAMILY,
    GOAL,
    GOAL_RADIUS,
    HORIZON,
    N_OBSTACLE_PARAMS,
    N_OBSTACLES,
    START_CORNER,
    START_SPREAD,
    V0,
    ObstacleFamily,
    ObstacleParam,
    UAVScenario,
    obstacle_states,
    sample_scenario,
    sample_scenarios,
)

__all__ = [
    "ACTION_HIGH",
    "ARENA_HIGH",
    "ARENA_LOW",
    "BEST_CONSTANT_ACTION",
    "BEST_CONSTANT_SEEDS",
    "COLLISION_REWARD",
    "CONSTANT_GRID",
    "CORRIDOR_HIGH",
    "CORRIDOR_LOW",
    "DT",
    "FAMILY",
    "GOAL",
    "GOAL_RADIUS",
    "GOAL_REWARD",
    "HORIZON",
    "N_OBSTACLES",
    "N_OBSTACLE_PARAMS",
    "ObstacleFamily",
    "ObstacleParam",
    "PROGRESS_REWARD",
    "START_CORNER",
    "START_SPREAD",
    "THREAT_COST",
    "THREAT_MARGIN",
    "TIME_COST",
    "UAVPathPlanningEnv",
    "UAVPathPlanningGymEnv",
    "UAVScenario",
    "V0",
    "best_constant_action",
    "constant_action_outcomes",
    "obstacle_states",
    "sample_scenario",
    "sample_scenarios",
    "step_reward",
]
