"""The task and method registries: every task and method is one entry that the rest reads."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import pytest
import torch

from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.envs.uav import HORIZON
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.methods import (
    DEFAULT_METHODS,
    METHOD_NAMES,
    METHODS,
    learned_method,
    make_arbiter,
    task_methods,
)
from dcsc_torchrl.networks import ConcatInputs
from dcsc_torchrl.tasks import TASKS, get_task
from dcsc_torchrl.transforms import HumanOperator, HumanOperatorTransform


def test_each_task_limit_is_its_envs_own():
    assert get_task("lunarlander").max_steps == gym.spec(LUNAR_ID).max_episode_steps
    assert get_task("uav").max_steps == HORIZON


@pytest.mark.parametrize("name", list(TASKS))
def test_a_task_entry_builds_its_env_operator_and_networks(name):
    task = get_task(name)
    operator = task.make_operator("expert")
    assert isinstance(operator, HumanOperator)
    env = task.make_envs([3, 4], 5, [HumanOperatorTransform(operator, seed=0)])
    td = env.rollout(3, break_when_any_done=False)
    assert td.batch_size[0] == 2 and set(task.info_keys) <= set(td["next"].keys())
    actor, critic = task.make_networks({"hidden": [8], "actor_dropout": 0.1})
    obs = td["observation"][:, 0]
    assert actor(obs).shape[-1] == (4 if task.discrete else task.action_dims)
    value = critic(obs) if task.discrete else critic(obs, td["action"][:, 0].float())
    assert value.isfinite().all()
    assert len(task.action_names) == (0 if task.discrete else task.action_dims)
    assert task.make_pretraining_envs(2).batch_size[0] == 2


def test_lunar_scenarios_must_be_consecutive_seeds():
    with pytest.raises(ValueError, match=r"consecutive seeds.*\[0, 2\]"):
        get_task("lunarlander").make_envs([0, 2], None, [])


def test_unknown_task_is_named():
    with pytest.raises(ValueError, match="unknown task 'lunar': expected one of lunarlander, uav"):
        get_task("lunar")


def test_the_registry_module_loads_no_torch():
    code = "import sys, dcsc_torchrl.tasks, dcsc_torchrl.methods; print('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"


@pytest.mark.parametrize("method", [m for m in METHOD_NAMES
                                    if METHODS[m].kind not in ("frozen", "pretrained") and m != "reddy"])
def test_every_method_the_registry_builds_has_an_arbiter_of_the_task_dims(method):
    arbiter = make_arbiter(method, 3, theta_init=0.5, hula_threshold=0.1, constant_beta=0.2,
                           rule=lambda obs: obs[..., 0] > 0, q_value=ConcatInputs(torch.nn.Linear(12, 1)),
                           expert_q=ConcatInputs(torch.nn.Linear(12, 1)), discrete=False)
    td = arbiter(_confidences(4).update({"observation": torch.randn(4, 9), "machine_action": torch.rand(4, 3),
                                         "human_action": torch.rand(4, 3)}))
    assert td["beta"].shape == (4, 3)


def test_learned_forms_map_to_their_methods():
    assert [learned_method(m.form) for m in METHODS.values() if m.kind == "learned"] == ["dcsc", "dcsc_centred"]
    with pytest.raises(ValueError, match="arbiter form must be one of paper, centred, got 'other'"):
        learned_method("other")


def test_presets_are_known_to_every_task():
    for task in TASKS.values():
        for preset in PRESETS:
            assert isinstance(task.make_operator(preset), HumanOperator)


def _confidences(n: int):
    from tensordict import TensorDict

    return TensorDict({"machine_confidence": torch.rand(n, 1), "human_confidence": torch.rand(n, 1),
                       "machine_uncertainty": torch.rand(n, 1)}, [n])


def test_the_rule_method_runs_for_a_task_with_an_authority_rule_only():
    assert tuple(m for m in METHOD_NAMES if m not in ("ida_expert", "reddy", "dcsc_state")) == DEFAULT_METHODS
    assert task_methods(get_task("lunarlander")) == DEFAULT_METHODS
    assert task_methods(get_task("uav")) == tuple(m for m in DEFAULT_METHODS if m != "rule")
    assert "reddy" in task_methods(get_task("lunarlander"), METHOD_NAMES)
    assert "reddy" in task_methods(get_task("uav"), METHOD_NAMES)  # on a sampled action set
    with pytest.raises(ValueError, match="the rule arbiter needs a rule"):
        make_arbiter("rule", 1)
    with pytest.raises(ValueError, match="method reddy brings its own machine"):
        make_arbiter("reddy", 1)
    with pytest.raises(ValueError, match="method dcsc_state brings its own arbiter"):
        make_arbiter("dcsc_state", 1)
    assert "dcsc_state" in task_methods(get_task("lunarlander"), METHOD_NAMES)
    assert "dcsc_state" in task_methods(get_task("uav"), METHOD_NAMES)  # beta per action dimension (authority)


def test_the_lunar_rule_hands_the_machine_the_controls_over_the_middle_of_the_pad():
    rule = get_task("lunarlander").authority_rule
    obs = torch.zeros(4, 9)
    obs[:, 8] = 0.6  # the pad's centre
    obs[:, 0] = torch.tensor([0.6, 0.65, 0.75, -0.6])  # over its centre, inside half its half-width, beyond, far
    assert rule(obs).tolist() == [True, True, False, False]
