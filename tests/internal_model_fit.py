"""How the simulated pilot's internal model of the lander was fitted (tests only: a test
refits it and compares with :data:`dcsc_torchrl.humans.pilot.INTERNAL_MODEL`)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import dcsc_torchrl.envs  # noqa: F401  (registers the ids)
from dcsc_torchrl.envs.target_lunar_lander import target_heuristic
from dcsc_torchrl.humans.pilot import N_KEYS, VELOCITIES, _features


def fit_internal_model(frames: int = 20_000, seed: int = 1_000_000) -> np.ndarray:
    """Fits :data:`~dcsc_torchrl.humans.pilot.INTERNAL_MODEL` from frames of ``dcsc/TargetLunarLander-v0`` in flight.

    The frames come from a pilot that presses a uniformly random key or
    :func:`~dcsc_torchrl.envs.target_lunar_lander.target_heuristic`'s, half and half (so the states
    are those of flying towards a pad), on episodes seeded ``seed, seed + 1, ...``
    (far from the validation scenarios); frames with a leg down are left out.

    Returns:
        ``[4, 3, 3]``: per key, the least-squares map from ``[1, sin(angle), cos(angle)]``
        to one frame's change of (vx, vy, angular velocity).
    """
    env = gym.make("dcsc/TargetLunarLander-v0")
    rng = np.random.default_rng(seed)
    features: list[list[np.ndarray]] = [[] for _ in range(N_KEYS)]
    changes: list[list[np.ndarray]] = [[] for _ in range(N_KEYS)]
    episode, kept = 0, 0
    obs, _ = env.reset(seed=seed)
    while kept < frames:
        key = int(rng.integers(N_KEYS)) if rng.random() < 0.5 else target_heuristic(obs)
        next_obs, _, terminated, truncated, _ = env.step(key)
        if not (obs[6] or obs[7] or next_obs[6] or next_obs[7] or terminated):
            features[key].append(_features(obs))
            changes[key].append(next_obs[list(VELOCITIES)] - obs[list(VELOCITIES)])
            kept += 1
        obs = next_obs
        if terminated or truncated:
            episode += 1
            obs, _ = env.reset(seed=seed + episode)
    return np.stack(
        [np.linalg.lstsq(np.array(x, np.float64), np.array(y, np.float64), rcond=None)[0] for x, y in zip(features, changes, strict=True)]
    )
