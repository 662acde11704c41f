"""The two tasks' environments as batched TorchRL envs, built the same way by every recipe.

LunarLander: :class:`TargetLunarLanderBatch`, ``N`` :class:`dcsc_torchrl.envs.TargetLunarLander` stepped
by one native TorchRL call (written for speed: TorchRL's ``GymWrapper`` over a gymnasium
``SyncVectorEnv`` spent more per call on its wrapper and info-dict reader than on the
physics; docs/records/tuning_log.md, "Speed against Stable-Baselines3"). UAV: the native batched
:class:`dcsc_torchrl.envs.UAVPathPlanningEnv`. Both end with ``RewardSum`` and ``StepCounter``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import Compose, EnvBase, RewardSum, StepCounter, Transform, TransformedEnv

import dcsc_torchrl.envs  # noqa: F401  (registers the dcsc/* gymnasium ids)
from dcsc_torchrl.envs.target_lunar_lander import TargetLunarLander
from dcsc_torchrl.envs.uav import UAVPathPlanningEnv

LUNAR_ID = "dcsc/TargetLunarLander-v0"
LUNAR_INFO_KEYS = ("success", "crashed", "landed_outside")
UAV_INFO_KEYS = ("success", "collision", "out_of_bounds", "path_length")


class TargetLunarLanderBatch(EnvBase):
    """``num_envs`` TargetLunarLanders as one native batched TorchRL env (discrete actions).

    Keys, all of batch ``[num_envs]``: ``observation`` ``[9]`` (gymnasium's eight values and
    the pad's x), one-hot ``action`` ``[4]`` (no-op, left, main, right engine), ``reward``
    ``[1]``, ``done`` / ``terminated`` / ``truncated`` ``[1]`` and the episode flags
    ``success`` / ``crashed`` / ``landed_outside`` (bools, ``[]``: the env's ``info``).

    It plays the same episodes as gymnasium's ``SyncVectorEnv`` of the registered id under
    TorchRL's ``GymWrapper`` (tested frame by frame): ``set_seed(s)`` resets env ``i`` with
    seed ``s + i``, every later reset draws from that env's own RNG, and an episode is
    truncated after ``max_steps`` frames (the id's ``TimeLimit``, 1000). A done env is reset
    when the collector (or ``rollout``) asks for it through ``"_reset"``. A step whose input
    holds ``"_step"`` (TorchRL's partial steps) moves only the envs it marks True; the
    others hold (same observation, reward 0, not done, their frame count unchanged).

    Args:
        num_envs: the envs stepped by one call.
        random_pad: ``False`` keeps the pad at the centre (the standard task).
        max_steps: the frames after which an episode is truncated (default: the id's 1000).
        render_mode: the landers' gymnasium render mode: ``None`` (every run of the
            protocol), or ``"rgb_array"``, whose :meth:`render` draws env 0 for a person
            flying it (``dcsc study``; the physics, and so every episode, is the same).

    Examples:
        >>> env = TargetLunarLanderBatch(3, random_pad=False)
        >>> _ = env.set_seed(0)
        >>> env.rollout(5)["next", "observation"].shape
        torch.Size([3, 5, 9])
    """

    def __init__(self, num_envs: int, *, random_pad: bool = True, max_steps: int | None = None,
                 render_mode: str | None = None) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        max_steps = gym.spec(LUNAR_ID).max_episode_steps if max_steps is None else max_steps
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        super().__init__(batch_size=torch.Size([num_envs]))
        self.max_steps = int(max_steps)
        self._envs = [TargetLunarLander(random_pad=random_pad, render_mode=render_mode) for _ in range(num_envs)]
        self._observation = np.zeros((num_envs, 9), dtype=np.float32)
        self._elapsed = np.zeros(num_envs, dtype=np.int64)
        space = self._envs[0].observation_space
        batch = self.batch_size

        def flag(*shape: int) -> Categorical:
            return Categorical(2, shape=(*batch, *shape), dtype=torch.bool)

        self.action_spec = OneHot(4, shape=(*batch, 4), dtype=torch.int64)
        self.observation_spec = Composite(
            observation=Bounded(torch.as_tensor(space.low).expand(*batch, 9).clone(),
                                torch.as_tensor(space.high).expand(*batch, 9).clone(), shape=(*batch, 9)),
            **{key: flag() for key in LUNAR_INFO_KEYS},
            shape=batch,
        )
        self.reward_spec = Unbounded((*batch, 1))
        self.done_spec = Composite(done=flag(1), terminated=flag(1), truncated=flag(1), shape=batch)

    def _start_episode(self, i: int, seed: int | None = None) -> None:
        self._observation[i], _ = self._envs[i].reset(seed=seed)
        self._elapsed[i] = 0

    def _set_seed(self, seed: int | None) -> None:
        for i in range(len(self._envs)):
            self._start_episode(i, None if seed is None else seed + i)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        rows = range(len(self._envs)) if reset is None else reset.reshape(len(self._envs), -1).any(-1).nonzero()
        for i in map(int, rows):
            self._start_episode(i)
        false = torch.zeros((*self.batch_size, 1), dtype=torch.bool)
        return TensorDict(
            {"observation": torch.from_numpy(self._observation.copy()),
             **{key: false.squeeze(-1).clone() for key in LUNAR_INFO_KEYS},
             **{key: false.clone() for key in ("done", "terminated", "truncated")}},
            batch_size=self.batch_size,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get("action").argmax(-1).tolist()
        n = len(self._envs)
        stepped = tensordict.get("_step", None)  # TorchRL's partial steps: the others hold
        stepped = np.ones(n, dtype=bool) if stepped is None else stepped.reshape(n).numpy(force=True)
        reward = np.zeros(n, dtype=np.float32)
        terminated = np.zeros(n, dtype=bool)
        flags = {key: np.zeros(n, dtype=bool) for key in LUNAR_INFO_KEYS}
        for i in stepped.nonzero()[0]:
            self._observation[i], reward[i], terminated[i], _, info = self._envs[i].step(actions[i])
            for key, flag in flags.items():
                flag[i] = info[key]
        self._elapsed += stepped
        terminated_tensor = torch.from_numpy(terminated).unsqueeze(-1)
        truncated = torch.from_numpy(self._elapsed >= self.max_steps).unsqueeze(-1)
        return TensorDict(
            {"observation": torch.from_numpy(self._observation.copy()),
             "reward": torch.from_numpy(reward).unsqueeze(-1),
             **{key: torch.from_numpy(flag) for key, flag in flags.items()},
             "done": terminated_tensor | truncated, "terminated": terminated_tensor, "truncated": truncated},
            batch_size=self.batch_size,
        )

    def render(self) -> np.ndarray | None:
        """Env 0's frame (``H x W x 3`` uint8) with ``render_mode="rgb_array"``, else ``None``."""
        return self._envs[0].render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self._envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)


def make_lunar_env(
    num_envs: int,
    *,
    random_pad: bool = True,
    max_steps: int | None = None,
    transforms: list[Transform] | None = None,
    render_mode: str | None = None,
) -> TransformedEnv:
    """``num_envs`` TargetLunarLanders stepped by one TorchRL call (:class:`TargetLunarLanderBatch`),
    then ``transforms`` (e.g. the operator's), ``RewardSum`` and ``StepCounter``.

    ``max_steps`` overrides the 1000-frame timeout; ``render_mode="rgb_array"`` draws env 0
    for a person (``env.base_env.render()``; docs/envs.md).
    """
    base = TargetLunarLanderBatch(num_envs, random_pad=random_pad, max_steps=max_steps, render_mode=render_mode)
    return _with_episode_transforms(base, transforms)


def make_uav_env(
    num_envs: int,
    *,
    scenario_seeds: list[int] | None = None,
    device: str | torch.device = "cpu",
    max_steps: int | None = None,
    collision_reward: float | None = None,
    transforms: list[Transform] | None = None,
) -> TransformedEnv:
    """``num_envs`` UAV scenarios as one native batched TorchRL env (+ transforms, RewardSum, StepCounter).

    ``max_steps`` overrides the 500-step horizon, ``collision_reward`` the env's -50.
    """
    base: EnvBase = UAVPathPlanningEnv(
        num_envs,
        scenario_seeds=scenario_seeds,
        device=device,
        **({} if max_steps is None else {"horizon": max_steps}),
        **({} if collision_reward is None else {"collision_reward": collision_reward}),
    )
    return _with_episode_transforms(base, transforms)


def _with_episode_transforms(base: EnvBase, transforms: list[Transform] | None) -> TransformedEnv:
    """``base`` followed by ``transforms``, then ``RewardSum`` and ``StepCounter`` (both tasks' envs)."""
    return TransformedEnv(base, Compose(*(transforms or []), RewardSum(), StepCounter()))
