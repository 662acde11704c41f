"""A simulated pilot for TargetLunarLander: knows the pad, flies with human traits (docs/operators.md)."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from gymnasium.envs.box2d.lunar_lander import FPS
from tensordict import TensorDictBase

from dcsc_torchrl.envs.target_lunar_lander import heuristic_key, target_heuristic
from dcsc_torchrl.humans.decision_loop import SimulatedHuman
from dcsc_torchrl.humans.traits import PRESETS, OperatorTraits

__all__ = ["SimulatedPilot"]

N_KEYS = 4
"""TargetLunarLander's keys: 0 no-op, 1 left engine, 2 main engine, 3 right engine."""


OBSERVATION_RATES = ((0, 2, 0.5), (1, 3, 1.125), (4, 5, 2.5))
"""(position index, velocity index, rate): ``d obs[position] / dt = rate * obs[velocity]``
per second in gymnasium's LunarLander units (x: ``vx (W/2) / FPS`` against ``x / (W/2)``
with W/2 = 10 m gives 50 / 10 / 10 = 0.5; y: 50 / 6.67 / 6.67 = 1.125; the angle: the
angular velocity is reported as ``20 omega / FPS``, so 50 / 20 = 2.5)."""

VELOCITIES = (2, 3, 5)
"""The observation's velocities (vx, vy, angular) that a key changes."""

INTERNAL_MODEL = np.array(
    [
        [[-0.000048, -0.026530, -0.002521], [0.000059, -0.000021, -0.001191], [0.000043, -0.000072, 0.002419]],
        [[-0.000556, -0.026015, 0.055948], [0.000417, -0.007029, -0.003824], [-0.009375, -0.000453, -0.016680]],
        [[-0.000920, -0.026200, 0.003892], [-0.070050, -0.001059, -0.001166], [0.001049, 0.046149, -0.004048]],
        [[-0.000423, -0.024846, -0.034024], [0.000438, 0.005180, -0.009415], [0.010293, -0.001727, -0.005563]],
    ]
)
"""The pilot's internal model of the lander, ``[key, feature, velocity]``: one frame's change
of (vx, vy, angular velocity) in observation units is ``[1, sin(angle), cos(angle)] @
INTERNAL_MODEL[key]`` in flight (gravity, and each engine's push along or across the
lander's axis). Least squares over 20,000 flying frames (``tests/internal_model_fit.py``'s
``fit_internal_model`` with its defaults; ``tests/test_operators.py`` refits and compares): what a practised person
knows of the engines, not the simulator (no engine dispersion, leg springs or terrain)."""


def _features(obs: np.ndarray) -> np.ndarray:
    """The internal model's features ``[1, sin(angle), cos(angle)]`` of observations ``[..., 9]``
    (what :data:`INTERNAL_MODEL` is fitted on; :func:`_predict_row` computes them per row)."""
    angle = obs[..., 4]
    return np.stack([np.ones_like(angle), np.sin(angle), np.cos(angle)], -1)


@numba.njit(cache=True)
def _predict_row(obs: np.ndarray, key: int, out: np.ndarray) -> None:
    """:func:`predict_frame` for one row (float64) into ``out``."""
    out[:] = obs
    for position, velocity, rate in OBSERVATION_RATES:
        out[position] += rate * obs[velocity] / FPS
    sin_angle, cos_angle = math.sin(obs[4]), math.cos(obs[4])
    for column in range(len(VELOCITIES)):
        out[VELOCITIES[column]] += (INTERNAL_MODEL[key, 0, column] + sin_angle * INTERNAL_MODEL[key, 1, column]
                                    + cos_angle * INTERNAL_MODEL[key, 2, column])
    if out[1] <= 0.0:
        out[1] = 0.0
        out[3] = max(out[3], 0.0)
        out[6] = 1.0
        out[7] = 1.0


@numba.njit(cache=True)
def _predict_frames(obs: np.ndarray, keys: np.ndarray) -> np.ndarray:
    nxt = np.empty_like(obs)
    for row in range(obs.shape[0]):
        _predict_row(obs[row], keys[row], nxt[row])
    return nxt


def predict_frame(obs: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """The internal model's next frame for observations ``[N, 9]`` (float64) under keys ``[N]``.

    Positions move at the velocities seen (:data:`OBSERVATION_RATES`), the velocities
    change as :data:`INTERNAL_MODEL` says, and the lander stops at the pad's height
    (``y = 0``): below it the model puts it on its legs (``y = 0``, no downward speed,
    both leg flags set), as a person knows the ground stops a fall.
    """
    return _predict_frames(np.ascontiguousarray(obs, dtype=np.float64), np.ascontiguousarray(keys, dtype=np.int64))


@numba.njit(cache=True)
def _carry_forward(guess: np.ndarray, issued: np.ndarray, delay: np.ndarray) -> None:
    """Steps row ``i`` of ``guess`` (in place) ``delay[i]`` frames with the keys ``issued[i]``."""
    scratch = np.empty(guess.shape[1])
    for row in range(guess.shape[0]):
        for frame in range(delay[row]):
            _predict_row(guess[row], issued[row, frame], scratch)
            guess[row] = scratch


@numba.njit(cache=True)
def _plan_keys(obs: np.ndarray, period: int) -> np.ndarray:
    """The controller's key on each of ``period`` frames of the internal model, from ``obs`` (rows)."""
    keys = np.empty((obs.shape[0], period), dtype=np.int64)
    frame_now, scratch = np.empty(obs.shape[1]), np.empty(obs.shape[1])
    for row in range(obs.shape[0]):
        frame_now[:] = obs[row]
        for frame in range(period):
            keys[row, frame] = heuristic_key(frame_now)
            _predict_row(frame_now, keys[row, frame], scratch)
            frame_now[:] = scratch
    return keys


class SimulatedPilot(SimulatedHuman):
    """The paper's LunarLander operator (§6.1: "the human has accurate knowledge of the landing target").

    Its controller is :func:`dcsc_torchrl.envs.target_lunar_lander.target_heuristic`, which reads
    the pad's x from ``observation[..., 8]``; the traits (decision interval, noise, lag,
    ex-Gaussian RT, lapses) are :class:`~dcsc_torchrl.humans.traits.OperatorTraits`,
    run by :class:`~dcsc_torchrl.humans.traits.SimulatedHuman`. The workload that
    stretches its RT is the lander's speed plus its tilt,
    ``hypot(obs[2], obs[3]) + |obs[4]|`` (normalised units and radians).

    A pilot that acts on the past (``traits.perceive_delayed``) flies by intermittent
    predictive control (Gawthrop, Loram, Lakie and Gollee, 2011): at a decision it
    carries the frame it saw one RT ago to the present through its internal model
    (:func:`predict_frame`) with the keys it pressed since (:meth:`anticipate`, a Smith
    predictor), then plans the keys of the coming decision interval by running the
    controller on the model's frames, and presses them open-loop until it decides again.
    The ``scripted`` upper bound (undelayed) runs the controller on the current frame and
    holds that key for its two frames.

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
        obs = tensordict.get(self.observation_key).detach().cpu().numpy().astype(np.float64)
        if not self.traits.perceive_delayed:
            return torch.as_tensor(target_heuristic(obs), device=tensordict.device)
        return torch.as_tensor(_plan_keys(np.ascontiguousarray(obs), self.decision_period), device=tensordict.device)

    def anticipate(
        self, perceived: TensorDictBase, issued: torch.Tensor, delay: torch.Tensor
    ) -> TensorDictBase:
        """The present as the internal model predicts it: the frame seen ``delay`` frames
        ago stepped through :func:`predict_frame` with the keys the pilot pressed since
        (its own keys: in shared control the key applied may differ, and the model does
        not know it)."""
        obs = perceived.get(self.observation_key)
        guess = np.ascontiguousarray(obs.detach().cpu().numpy(), dtype=np.float64)
        _carry_forward(guess, np.ascontiguousarray(issued.cpu().numpy()), np.ascontiguousarray(delay.cpu().numpy()))
        guess = torch.as_tensor(guess, dtype=obs.dtype, device=obs.device)
        return perceived.clone(False).set(self.observation_key, guess)

    def workload(self, tensordict: TensorDictBase) -> torch.Tensor:
        obs = tensordict.get(self.observation_key)
        return torch.hypot(obs[..., 2], obs[..., 3]) + obs[..., 4].abs()

    def action(self, choice: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.one_hot(choice, N_KEYS)
