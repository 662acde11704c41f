"""A simulated pilot for TargetLunarLander: knows the pad, flies with human traits (docs/operators.md)."""

from __future__ import annotations

import torch
from gymnasium.envs.box2d.lunar_lander import FPS
from tensordict import TensorDictBase

from dcsc_torchrl.humans.traits import PRESETS, OperatorTraits, SimulatedHuman
from envs.target_lunar_lander import target_heuristic

__all__ = ["SimulatedPilot"]

N_KEYS = 4
"""TargetLunarLander's keys: 0 no-op, 1 left engine, 2 main engine, 3 right engine."""


OBSERVATION_RATES = ((0, 2, 0.5), (1, 3, 1.125), (4, 5, 2.5))
"""(position index, velocity index, rate): ``d obs[position] / dt = rate * obs[velocity]``
per second in gymnasium's LunarLander units (x: ``vx (W/2) / FPS`` against ``x / (W/2)``
with W/2 = 10 m gives 50 / 10 / 10 = 0.5; y: 50 / 6.67 / 6.67 = 1.125; the angle: the
angular velocity is reported as ``20 omega / FPS``, so 50 / 20 = 2.5)."""


class SimulatedPilot(SimulatedHuman):
    """The paper's LunarLander operator (§6.1: "the human has accurate knowledge of the landing target").

    Its controller is :func:`envs.target_lunar_lander.target_heuristic`, which reads
    the pad's x from ``observation[..., 8]``; the traits (decision interval, noise, lag,
    ex-Gaussian RT, lapses) are :class:`~dcsc_torchrl.humans.traits.OperatorTraits`,
    run by :class:`~dcsc_torchrl.humans.traits.SimulatedHuman`. The workload that
    stretches its RT is the lander's speed plus its tilt,
    ``hypot(obs[2], obs[3]) + |obs[4]|`` (normalised units and radians).

    Args:
        traits: the pilot's traits (default: the ``expert`` preset).
        observation_key: where the 9-value TargetLunarLander observation is read.

    Examples:
        >>> from tensordict import TensorDict
        >>> pilot = SimulatedPilot.from_preset("noisy")
        >>> pilot.reset(0)
        >>> td = TensorDict({"observation": torch.zeros(3, 9),
        ...                  "is_init": torch.ones(3, 1, dtype=torch.bool)}, [3])
        >>> out = pilot(td)
        >>> out["human_action"].shape, out["human_decided"].all().item()
        (torch.Size([3, 4]), True)
    """

    n_choices = N_KEYS

    def __init__(
        self, traits: OperatorTraits | None = None, *, observation_key: str = "observation"
    ) -> None:
        super().__init__(PRESETS["expert"] if traits is None else traits, frame_seconds=1.0 / FPS)
        self.observation_key = observation_key
        self.in_keys = (observation_key,)

    def plan(self, tensordict: TensorDictBase) -> torch.Tensor:
        observations = tensordict.get(self.observation_key).detach().cpu().numpy()
        keys = [target_heuristic(obs) for obs in observations]
        return torch.tensor(keys, dtype=torch.int64, device=tensordict.device)

    def anticipate(self, perceived: TensorDictBase, delay: torch.Tensor) -> TensorDictBase:
        """A constant-velocity guess of the present: the lander's x, y and tilt carried
        forward ``delay`` seconds at the velocities seen (:data:`OBSERVATION_RATES`);
        the velocities themselves (and gravity, thrust) are not predicted."""
        obs = perceived.get(self.observation_key).clone()
        for position, velocity, rate in OBSERVATION_RATES:
            obs[..., position] += rate * obs[..., velocity] * delay.to(obs.dtype)
        return perceived.clone(False).set(self.observation_key, obs)

    def workload(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs = tensordict.get(self.observation_key)
        return torch.hypot(obs[..., 2], obs[..., 3]) + obs[..., 4].abs()

    def action(self, choice: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.one_hot(choice, N_KEYS)
