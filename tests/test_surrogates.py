"""The peers' surrogate pilots (``surrogate_*`` presets): corrupted exactly as defined.

Each is the undelayed controller queried every frame; ``surrogate_noisy`` replaces its
choice by a uniformly random one with probability 0.3, ``surrogate_laggy`` repeats its
previous choice with probability 0.85 (docs/operators.md). Measured over many frames,
each rate must equal its definition within sampling error (4 standard errors).
"""

from __future__ import annotations

import math

import pytest
import torch
from test_operators import query

from dcsc_torchrl.humans import PRESETS, SimulatedOperator, SimulatedPilot

ENVS, FRAMES = 200, 100


def keys_of(preset: str, plan, **overrides) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keys ``[ENVS, FRAMES]`` a LunarLander surrogate presses when its controller plans ``plan(t, n)``,
    with its decisions and RTs."""
    pilot = SimulatedPilot.from_preset(preset, **overrides)
    frame = iter(range(FRAMES))
    pilot.plan = lambda perceived: plan(next(frame), perceived.batch_size[0])
    pilot.reset(0)
    obs = torch.zeros(ENVS, 9)
    outs = [pilot(query(obs, t == 0)) for t in range(FRAMES)]
    keys = torch.stack([out["human_action"].argmax(-1) for out in outs], 1)
    decided = torch.stack([out["human_decided"].squeeze(-1) for out in outs], 1)
    rts = torch.stack([out["human_rt"].squeeze(-1) for out in outs], 1)
    return keys, decided, rts


def within_sampling_error(rate: float, expected: float, n: int) -> bool:
    return abs(rate - expected) <= 4 * math.sqrt(expected * (1 - expected) / n)


def test_the_surrogates_are_the_undelayed_controller_queried_every_frame_with_the_defined_rates():
    base = PRESETS["surrogate_expert"]
    assert not base.perceive_delayed and not base.lapses and base.eps == 0 and base.lag == 0
    assert PRESETS["surrogate_noisy"].eps == 0.3 and PRESETS["surrogate_laggy"].lag == 0.85
    assert SimulatedPilot.from_preset("surrogate_noisy").decision_period == 1
    assert SimulatedOperator.from_preset("surrogate_laggy").decision_period == 1


def test_surrogate_noisy_replaces_30_percent_of_frames_by_a_uniform_key():
    keys, decided, _ = keys_of("surrogate_noisy", lambda t, n: torch.zeros(n, dtype=torch.long))
    assert decided.all()
    n = keys.numel()
    # a random key is any of the 4 with probability 1/4: key 0 stays 0.7 + 0.3/4, every other key 0.3/4
    for key in range(1, 4):
        assert within_sampling_error((keys == key).float().mean().item(), 0.3 / 4, n)
    assert within_sampling_error((keys != 0).float().mean().item(), 0.3 * 3 / 4, n)


def test_surrogate_laggy_repeats_its_previous_key_85_percent_of_frames():
    generator = torch.Generator().manual_seed(1)
    keys, decided, _ = keys_of("surrogate_laggy", lambda t, n: torch.randint(4, (n,), generator=generator))
    assert decided.all()
    repeated = keys[:, 1:] == keys[:, :-1]
    # lagged (0.85), or a fresh uniform plan that happens to equal the held key (0.15 / 4)
    assert within_sampling_error(repeated.float().mean().item(), 0.85 + 0.15 / 4, repeated.numel())


def test_surrogate_expert_presses_its_controller_s_key_on_every_frame():
    keys, _, _ = keys_of("surrogate_expert", lambda t, n: torch.full((n,), t % 4))
    assert keys.equal(torch.arange(FRAMES).remainder(4).expand(ENVS, -1))


@pytest.mark.parametrize("preset", ["surrogate_expert", "surrogate_noisy", "surrogate_laggy"])
def test_a_surrogate_reports_an_rt_stream_but_never_lapses(preset):
    """RTs past t_d leave its decisions every frame (a person's lapse would hold the key)."""
    keys, decided, rts = keys_of(preset, lambda t, n: torch.full((n,), t % 4), rt_mu=1.5)
    assert decided.all()
    assert (rts > PRESETS[preset].lapse_threshold).float().mean() > 0.9
    assert rts.std() > 0
