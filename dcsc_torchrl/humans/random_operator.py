"""The simplest operator: a random key (or a random point of the action box) every frame."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase


class RandomOperator:
    """An operator that knows nothing: a uniform random action at every frame.

    It decides on every frame with a reaction time drawn uniformly from ``rt_range``
    seconds. Useful as a baseline and to check a pipeline's plumbing; it follows the
    :class:`~dcsc_torchrl.transforms.HumanOperator` contract.

    Args:
        n_actions: number of discrete actions (one-hot output); or
        action_low, action_high: the box of a continuous action (give both instead).
        rt_range: (low, high) of the uniform reaction time, seconds.

    Examples:
        >>> op = RandomOperator(n_actions=4)
        >>> op.reset(0)
        >>> out = op(TensorDict({"observation": torch.zeros(2, 9)}, [2]))
        >>> out["human_action"].sum(-1)
        tensor([1, 1])
    """

    def __init__(
        self,
        n_actions: int | None = None,
        *,
        action_low: torch.Tensor | None = None,
        action_high: torch.Tensor | None = None,
        rt_range: tuple[float, float] = (0.3, 0.9),
    ) -> None:
        if (n_actions is None) == (action_low is None or action_high is None):
            raise ValueError("give either n_actions (discrete) or action_low and action_high (continuous)")
        if not 0 <= rt_range[0] <= rt_range[1]:
            raise ValueError(f"rt_range must satisfy 0 <= low <= high, got {rt_range!r}")
        self.n_actions = n_actions
        self.low = None if action_low is None else torch.as_tensor(action_low, dtype=torch.float32)
        self.high = None if action_high is None else torch.as_tensor(action_high, dtype=torch.float32)
        self.rt_range = rt_range
        self.generator = torch.Generator()
        self.reset(None)

    def reset(self, seed: int | None) -> None:
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(seed))

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        if self.n_actions is not None:
            keys = torch.randint(self.n_actions, batch, generator=self.generator)
            action = torch.nn.functional.one_hot(keys, self.n_actions)
        else:
            u = torch.rand(*batch, *self.low.shape, generator=self.generator)
            action = self.low + u * (self.high - self.low)
        low, high = self.rt_range
        rt = low + (high - low) * torch.rand(*batch, 1, generator=self.generator)
        decided = torch.ones(*batch, 1, dtype=torch.bool)
        return TensorDict({"human_action": action, "human_rt": rt, "human_decided": decided}, batch)
