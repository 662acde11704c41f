"""One UAV scenario as a gymnasium env (``dcsc/UAVPathPlanning-v0``)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from dcsc_torchrl.envs.uav_env import UAVPathPlanningEnv
from dcsc_torchrl.envs.uav_scenarios import ACTION_HIGH


class UAVPathPlanningGymEnv(gym.Env):
    """One UAV scenario as a gymnasium env (``dcsc/UAVPathPlanning-v0``).

    A thin wrapper around a batch-1 :class:`UAVPathPlanningEnv`: float32 observation
    ``(9,)``, action ``Box(0, 3, (3,))``, ``info`` with ``success``, ``collision``,
    ``out_of_bounds`` (numpy bools), ``path_length`` (float32) and ``scenario_seed``
    (int64), numpy scalars so that TorchRL's ``auto_register_info_dict`` reads them.
    Truncation at ``HORIZON`` steps is the env's own.

    Args:
        scenario_seed: fly this scenario at every reset; if ``None``, every reset draws
            a fresh scenario from ``self.np_random`` (so ``reset(seed=s)`` is
            reproducible).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, scenario_seed: int | None = None) -> None:
        self.scenario_seed = scenario_seed
        self._env = UAVPathPlanningEnv(
            1, scenario_seeds=None if scenario_seed is None else [scenario_seed], seed=0
        )
        self.observation_space = spaces.Box(-np.inf, np.inf, (9,), np.float32)
        self.action_space = spaces.Box(0.0, ACTION_HIGH, (3,), np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Starts the scenario (a fresh one from ``self.np_random`` unless fixed).

        Args:
            seed: seeds ``self.np_random``.
            options: unused; accepted for the gymnasium API.

        Returns:
            The first observation and the info dict.
        """
        super().reset(seed=seed)
        if self.scenario_seed is None:
            self._env.set_seed(int(self.np_random.integers(2**62)))
        self._env.reset()
        return self._observe(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Moves the UAV one ``DT`` along the flow shaped by ``action = (rho0, sigma0, tau)``.

        Args:
            action: ``(3,)`` in ``[0, 3]``.

        Returns:
            ``(obs, reward, terminated, truncated, info)``.
        """
        env = self._env
        action = torch.from_numpy(np.asarray(action, dtype=np.float32).reshape(1, 3))
        reward = float(env.advance(action))
        terminated = bool(env._success | env._collision | env._out_of_bounds)
        return self._observe(), reward, terminated, bool(env._truncated), self._info()

    def _observe(self) -> np.ndarray:
        return self._env.observation()[0].numpy()

    def _info(self) -> dict[str, Any]:
        env = self._env
        # copies: the env's state changes in place at the next step
        return {
            "success": np.bool_(env._success[0].item()),
            "collision": np.bool_(env._collision[0].item()),
            "out_of_bounds": np.bool_(env._out_of_bounds[0].item()),
            "path_length": np.float32(env._path_length[0].item()),
            "scenario_seed": np.int64(env._seed[0].item()),
        }
