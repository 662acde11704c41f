"""The human transforms and the whole DC-SC pipeline inside TorchRL envs and collectors."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, SerialEnv, TransformedEnv
from torchrl.envs.transforms import Compose
from torchrl.envs.utils import check_env_specs

from dcsc_torchrl.arbiters import ConfidenceArbiter
from dcsc_torchrl.confidence import human_confidence, knowledge_update
from dcsc_torchrl.humans import RandomOperator
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

CONTRACT_KEYS = [
    "observation", "human_action", "human_rt", "human_decided", "knowledge", "human_confidence",
    "machine_probs", "machine_uncertainty", "machine_confidence", "confidence_ratio", "beta",
    "probs", "action",
]


class EveryThirdFrame:
    """A scripted operator: key 2 always, a decision every third frame, RT cycling."""

    def __init__(self, rts: tuple[float, ...] = (0.4, 1.6, 0.7)) -> None:
        self.rts = torch.tensor(rts)
        self.frames = None

    def reset(self, seed: int | None) -> None:
        self.frames = None

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        batch = td.batch_size
        if self.frames is None:
            self.frames = torch.zeros(*batch, 1, dtype=torch.long)
        self.frames = torch.where(td["is_init"], torch.zeros_like(self.frames), self.frames + 1)
        decided = self.frames % 3 == 0
        rt = self.rts[(self.frames // 3) % len(self.rts)]
        action = torch.nn.functional.one_hot(torch.full(batch, 2), 4)
        return TensorDict({"human_action": action, "human_rt": rt, "human_decided": decided}, batch)


def human_env(operator, **confidence_kwargs) -> TransformedEnv:
    return TransformedEnv(
        GymEnv("LunarLander-v3"),
        Compose(HumanOperatorTransform(operator, seed=0), HumanConfidenceTransform(**confidence_kwargs)),
    )


def test_human_transforms_pass_check_env_specs():
    env = human_env(RandomOperator(n_actions=4))
    check_env_specs(env)
    assert env.observation_spec["human_action"].shape == (4,)
    assert "knowledge" in env.full_state_spec.keys()


def test_human_transforms_pass_check_env_specs_inside_serial_env():
    env = SerialEnv(2, lambda: human_env(RandomOperator(n_actions=4)))
    check_env_specs(env)
    env.close()


def test_knowledge_updates_only_on_decision_frames_and_restarts_each_episode():
    kwargs = {"p": 0.1, "eta": 0.6, "delta1": 2.0, "K": 20.0, "t_d": 1.0, "k0": 0.05}
    env = human_env(EveryThirdFrame(), **kwargs)
    env.set_seed(0)
    rollout = env.rollout(12, break_when_any_done=False)
    k_now, k_next = rollout["knowledge"], rollout["next", "knowledge"]
    decided, rt = rollout["next", "human_decided"], rollout["next", "human_rt"]
    expected = torch.where(decided, knowledge_update(k_now, rt, 20.0, 1.0), k_now)
    torch.testing.assert_close(k_next, expected)
    assert (k_next[~decided] == k_now[~decided]).all()
    assert decided.sum() == 4 and rollout[0]["knowledge"].item() == pytest.approx(0.05)
    torch.testing.assert_close(rollout["next", "human_confidence"], human_confidence(k_next, 0.1, 0.6, 2.0))
    # a long RT (1.6 s > t_d) lowered k on its decision frame
    long_rt = decided & (rt > 1.0)
    assert (k_next[long_rt] < k_now[long_rt]).all()
    # a new episode starts again at k0
    assert env.reset()["knowledge"].item() == pytest.approx(0.05)


def test_knowledge_persists_across_episodes_when_asked():
    env = human_env(EveryThirdFrame(rts=(0.3,)), K=20.0, k0=0.05, persist=True)
    td = env.rollout(10, break_when_any_done=False)
    last = td[-1]["next", "knowledge"]
    assert last.item() > 0.05
    reset = env.reset(td[-1]["next"].select("knowledge"))
    torch.testing.assert_close(reset["knowledge"], last)


@pytest.mark.parametrize(
    "kwargs, name",
    [({"p": 1.0}, "p"), ({"eta": 0.0}, "eta"), ({"delta1": 0.0}, "delta1"), ({"K": -1.0}, "K"),
     ({"t_d": 0.0}, "t_d"), ({"k0": 30.0}, "k0"), ({"mode": "fast"}, "mode")],
)
def test_human_confidence_transform_rejects_bad_parameters(kwargs, name):
    with pytest.raises(ValueError, match=name):
        HumanConfidenceTransform(**kwargs)


def test_operator_transform_rejects_a_non_operator_and_bad_answers():
    with pytest.raises(TypeError, match="reset"):
        HumanOperatorTransform(object())

    class NegativeRT(EveryThirdFrame):
        def __call__(self, td):
            out = super().__call__(td)
            out["human_rt"] = -out["human_rt"]
            return out

    with pytest.raises(ValueError, match="human_rt"):
        human_env(NegativeRT()).reset()


def make_pipeline(num_envs: int = 1):
    def make_env():
        return human_env(RandomOperator(n_actions=4))

    env = make_env() if num_envs == 1 else SerialEnv(num_envs, make_env)
    net = nn.Sequential(nn.Linear(8, 32), nn.Tanh(), nn.Dropout(0.1), nn.Linear(32, 4))
    policy = SharedPolicyModule(MCDropoutPolicy(net, num_samples=10), ConfidenceArbiter(1.0), env.full_action_spec["action"])
    return env, policy


def test_pipeline_rollout_has_every_design_key_finite():
    env, policy = make_pipeline()
    check_env_specs(env)
    rollout = env.rollout(50, policy, break_when_any_done=False)
    for key in CONTRACT_KEYS:
        assert key in rollout.keys(), key
        assert torch.isfinite(rollout[key].float()).all(), key
    assert ((rollout["beta"] >= 0.5) & (rollout["beta"] <= 1)).all()


def test_pipeline_runs_in_a_collector_with_batched_envs():
    env, policy = make_pipeline(num_envs=2)
    collector = Collector(env, policy, frames_per_batch=100, total_frames=300, auto_register_policy_transforms=False)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 3
    for batch in batches:
        assert batch.batch_size == (2, 50)
        for key in CONTRACT_KEYS:
            assert key in batch.keys(), key
            assert torch.isfinite(batch[key].float()).all(), key
        assert (batch["action"].sum(-1) == 1).all()
        assert (batch["next", "human_confidence"] >= 0).all()


# --- FirstEpisodeOnly: TorchRL's partial steps -------------------------------------


@pytest.mark.parametrize("task_name", ["lunarlander", "uav"])
def test_batched_envs_step_only_the_envs_of_a_partial_step(task_name):
    """``"_step"`` False: the env keeps its state (time included), earns 0 and is not done."""
    from dcsc_torchrl.tasks import get_task

    env = get_task(task_name).make_envs([0, 1], None, [])
    before = env.reset()
    td = before.clone().set("action", env.full_action_spec["action"].rand()).set("_step", torch.tensor([True, False]))
    after = env.step(td)["next"]
    assert not after["observation"][0].equal(before["observation"][0])
    assert after["observation"][1].equal(before["observation"][1])
    assert after["reward"][1].item() == 0.0 and not after["done"][1].item()
    if task_name == "uav":
        assert after["time"][1].item() == 0.0 and after["time"][0].item() > 0.0


def test_first_episode_only_holds_the_envs_done_and_changes_no_recorded_frame(lunar_physics_steps):
    """A fixed method's run with FirstEpisodeOnly records the same rows, trace and frames as
    without it, stepping the physics only until each env's first episode ends."""
    from dcsc_torchrl.episodes import run_scenarios
    from dcsc_torchrl.methods import build_policy, make_arbiter
    from dcsc_torchrl.networks import lunar_actor
    from dcsc_torchrl.tasks import get_task
    from dcsc_torchrl.transforms import FirstEpisodeOnly

    task = get_task("lunarlander")
    torch.manual_seed(0)
    machine = lunar_actor([16], 0.1)

    def run(first_episode_only: bool):
        transforms = [HumanOperatorTransform(task.make_operator("noisy"), seed=0), HumanConfidenceTransform()]
        env = task.make_envs([0, 1, 2, 3], 300, [FirstEpisodeOnly(), *transforms] if first_episode_only else transforms)
        policy = build_policy(machine, make_arbiter("constant", 1, constant_beta=0.7), env.full_action_spec["action"],
                              discrete=True, num_samples=4, lam=0.6, delta2=1.05)
        lunar_physics_steps.clear()
        torch.manual_seed(1)
        return run_scenarios(env, policy, task, rollout_length=5, trace=True), len(lunar_physics_steps)

    (held, held_steps), (played, played_steps) = run(True), run(False)
    assert len({row["steps"] for row in held.rows}) > 1  # the episodes end on different frames
    assert held.rows == played.rows and held.trace == played.trace
    assert all(held.frames[key].equal(played.frames[key]) for key in held.frames.keys(True, True))
    recorded = sum(row["steps"] for row in held.rows)
    assert recorded <= held_steps < played_steps  # at most a rollout's worth past each episode's end
    assert held_steps <= recorded + 4 * len(held.rows)
