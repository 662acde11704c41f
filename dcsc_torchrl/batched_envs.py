"""The two tasks' environments as batched TorchRL envs, built the same way by every recipe.

Building a vector env, ``GymWrapper`` runs a dummy rollout and logs two INFO lines
("info_dict_reader does not have specs", "check_env_specs succeeded!"), dozens per run:
:func:`quiet_torchrl` holds TorchRL's logger at WARNING while an env is built, unless
``DCSC_VERBOSE`` is set (``dcsc -v``).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator

import gymnasium as gym
import torch
from gymnasium.vector import AutoresetMode
from torchrl.data import Categorical, Composite
from torchrl.envs import (
    Compose,
    EnvBase,
    GymWrapper,
    RewardSum,
    StepCounter,
    Transform,
    TransformedEnv,
)
from torchrl.envs.libs.gym import default_info_dict_reader

import envs  # noqa: F401  (registers the dcsc/* gymnasium ids)
from envs.uav import UAVPathPlanningEnv

LUNAR_ID = "dcsc/TargetLunarLander-v0"
LUNAR_INFO_KEYS = ("success", "crashed", "landed_outside")
UAV_INFO_KEYS = ("success", "collision", "out_of_bounds", "path_length")


@contextlib.contextmanager
def quiet_torchrl() -> Iterator[None]:
    """TorchRL's INFO lines silenced inside the block (kept when ``DCSC_VERBOSE`` is set)."""
    logger = logging.getLogger("torchrl")
    level = logger.level
    if not os.environ.get("DCSC_VERBOSE"):
        logger.setLevel(max(level, logging.WARNING))
    try:
        yield
    finally:
        logger.setLevel(level)


def make_lunar_env(
    num_envs: int,
    *,
    random_pad: bool = True,
    max_steps: int | None = None,
    transforms: list[Transform] | None = None,
) -> TransformedEnv:
    """``num_envs`` TargetLunarLanders stepped by one TorchRL call.

    A gymnasium ``SyncVectorEnv`` (same-step autoreset, as TorchRL expects) under
    ``GymWrapper``, with ``success`` / ``crashed`` / ``landed_outside`` read from
    ``info``, then ``transforms`` (e.g. the operator's), ``RewardSum`` and
    ``StepCounter``. ``render_mode`` stays ``None`` (docs/envs.md: flame particles pile up otherwise). ``max_steps``
    overrides the 1000-frame timeout.
    """
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    vector = gym.make_vec(
        LUNAR_ID,
        num_envs=num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
        random_pad=random_pad,
        disable_env_checker=True,
        **({} if max_steps is None else {"max_episode_steps": max_steps}),
    )
    with quiet_torchrl():
        base = GymWrapper(vector)
    info_spec = Composite(
        {key: Categorical(2, shape=(num_envs,), dtype=torch.bool) for key in LUNAR_INFO_KEYS},
        shape=[num_envs],
    )
    base.set_info_dict_reader(default_info_dict_reader(list(LUNAR_INFO_KEYS), spec=info_spec))
    # GymWrapper already returns a TransformedEnv (TorchRL's VecGymEnvTransform) for a
    # vector env: extend it rather than nesting a second TransformedEnv around it
    for transform in [*(transforms or []), RewardSum(), StepCounter()]:
        base.append_transform(transform)
    return base


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
    return TransformedEnv(base, Compose(*(transforms or []), RewardSum(), StepCounter()))
