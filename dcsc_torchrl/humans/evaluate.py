"""The operator alone in control (the protocol's calibration phase, docs/architecture.md): its policy and its first episodes."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

__all__ = ["operator_only_episodes", "operator_only_policy"]


def operator_only_policy(
    human_action_key: str = "human_action", action_key: str = "action"
) -> TensorDictModule:
    """A policy that plays the operator's action (``action = human_action``).

    Equivalent to the shared policy with beta = 0 (Eq. 14), without a machine.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = operator_only_policy()(TensorDict({"human_action": torch.tensor([0, 1])}, []))
        >>> td["action"]
        tensor([0, 1])
    """
    return TensorDictModule(nn.Identity(), in_keys=[human_action_key], out_keys=[action_key])


@torch.no_grad()
def operator_only_episodes(
    env: EnvBase, max_steps: int, policy: TensorDictModuleBase | None = None
) -> dict[str, torch.Tensor]:
    """Runs every env of a batch until its first episode ends (or ``max_steps``).

    ``env`` must carry a :class:`~dcsc_torchrl.transforms.HumanOperatorTransform`,
    ``RewardSum`` and ``StepCounter`` (as :func:`dcsc_torchrl.batched_envs.make_lunar_env` and
    :func:`~dcsc_torchrl.batched_envs.make_uav_env` build them) and write ``success``. Seed it
    (``env.set_seed``) before calling for reproducible episodes.

    Args:
        env: a batched env.
        max_steps: frames at most; an episode still running then counts as a failure.
        policy: what acts (default :func:`operator_only_policy`).

    Returns:
        Per env (``[num_envs]``): ``success`` (bool), ``return`` (the episode's reward
        sum) and ``steps`` (its length).
    """
    policy = operator_only_policy() if policy is None else policy
    n_envs = env.batch_size.numel()
    finished = torch.zeros(n_envs, dtype=torch.bool)
    result = {
        "success": torch.zeros(n_envs, dtype=torch.bool),
        "return": torch.zeros(n_envs),
        "steps": torch.zeros(n_envs, dtype=torch.int64),
    }
    td = env.reset()
    for _ in range(max_steps):
        td, next_root = env.step_and_maybe_reset(policy(td))
        step = td.get("next")
        running = ~finished
        done = step.get("done").reshape(n_envs).cpu() | (
            step.get("step_count").reshape(n_envs).cpu() >= max_steps
        )
        values = {
            "success": step.get("success").reshape(n_envs).cpu() & done,
            "return": step.get("episode_reward").reshape(n_envs).cpu(),
            "steps": step.get("step_count").reshape(n_envs).cpu(),
        }
        for key, value in values.items():
            result[key] = torch.where(running, value, result[key])
        finished |= done
        if finished.all():
            break
        td = next_root
    return result
