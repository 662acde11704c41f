"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest

from dcsc_torchrl.envs.target_lunar_lander import TargetLunarLander


@pytest.fixture
def lunar_physics_steps(monkeypatch) -> list[int]:
    """Counts the physics steps of every TargetLunarLander (one entry per ``step``)."""
    steps: list[int] = []
    step = TargetLunarLander.step
    monkeypatch.setattr(TargetLunarLander, "step", lambda self, action: steps.append(1) or step(self, action))
    return steps
