"""The operator alone in control (the protocol's calibration phase, docs/architecture.md): its policy and its first episodes."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

from dcsc_torchrl.episodes import in_first_episode

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
    rollout = env.rollout(max_steps, policy, break_when_any_done=False, break_when_all_done=True)
    nxt = rollout.get("next")
    done = nxt.get("done").reshape(*rollout.batch_size).cpu()
    done[:, -1] = True  # an episode still running after max_steps ends there, unsuccessful
    end = (done & in_first_episode(done)).int().argmax(-1)
    last = nxt[torch.arange(done.shape[0]), end]
    return {
        "success": last.get("success").reshape(-1).cpu() & last.get("done").reshape(-1).cpu(),
        "return": last.get("episode_reward").reshape(-1).cpu(),
        "steps": last.get("step_count").reshape(-1).cpu(),
    }
