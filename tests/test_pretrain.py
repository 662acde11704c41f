"""The pretraining recipes' tiny settings, end to end: outputs, resume, atomic checkpoints."""

from __future__ import annotations

import importlib
import math
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
import torch

from dcsc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from dcsc_torchrl.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[1]
RECIPES = {
    "lunarlander": "dcsc_torchrl.recipes.pretrain_a2c_lunarlander",
    "uav": "dcsc_torchrl.recipes.pretrain_ddpg_uav",
}
COLUMNS = {
    "lunarlander": ["episode", "frames", "return", "steps", "success", "loss_objective", "loss_critic",
                    "loss_entropy", "loss_qvalue"],
    "uav": ["episode", "frames", "return", "steps", "success", "loss_actor", "loss_value"],
}


def run_recipe(task: str, out: Path, *extra: str) -> None:
    importlib.import_module(RECIPES[task]).main(["--quick", "--out", str(out), *extra])


@pytest.mark.parametrize("task", sorted(RECIPES))
def test_tiny_recipe_writes_checkpoint_csv_and_png(task, tmp_path):
    run_recipe(task, tmp_path)
    log = pd.read_csv(tmp_path / "train.csv")
    assert list(log.columns) == COLUMNS[task]
    assert len(log) >= 1 and log["episode"].tolist() == list(range(1, len(log) + 1))
    assert log["return"].map(math.isfinite).all()
    assert (log["frames"].diff().dropna() >= 0).all()
    assert (tmp_path / "learning_curve.png").stat().st_size > 1000
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt", task=task)
    assert ckpt["episodes"] == len(log) and ckpt["config"]["train"]["episodes"] == len(log)
    assert "actor" in ckpt["state"]
    evaluation = pd.read_csv(tmp_path / "eval.csv")
    assert evaluation["return"].map(math.isfinite).all()


@pytest.mark.parametrize("task", sorted(RECIPES))
def test_resume_from_a_halfway_checkpoint_gives_the_same_rows(task, tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    run_recipe(task, straight)
    total = len(pd.read_csv(straight / "train.csv"))
    half = int(load_checkpoint(straight / "checkpoint.pt", task=task)["config"]["train"]["checkpoint_every"])
    assert half < total
    run_recipe(task, resumed, f"train.episodes={half}")
    assert len(pd.read_csv(resumed / "train.csv")) == half
    run_recipe(task, resumed, "--resume")
    pd.testing.assert_frame_equal(pd.read_csv(resumed / "train.csv"), pd.read_csv(straight / "train.csv"))


def test_loading_a_uav_checkpoint_into_the_lunarlander_recipe_fails_clearly(tmp_path):
    save_checkpoint(tmp_path / "checkpoint.pt", task="uav", payload={"state": {}})
    with pytest.raises(ValueError, match="written for task 'uav'.*task 'lunarlander'"):
        run_recipe("lunarlander", tmp_path, "--resume")


def test_a_checkpoint_of_the_wrong_shape_is_refused(tmp_path):
    run_recipe("lunarlander", tmp_path, "train.episodes=3")
    with pytest.raises(ValueError, match="network.hidden"):
        run_recipe("lunarlander", tmp_path, "--resume", "network.hidden=[32,32]")


def test_sigkill_while_checkpointing_leaves_the_previous_checkpoint_loadable(tmp_path):
    target = tmp_path / "checkpoint.pt"
    save_checkpoint(target, task="uav", payload={"state": {"w": torch.zeros(3)}, "step": -1})
    writer = textwrap.dedent(
        f"""
        import torch
        from dcsc_torchrl.checkpoint import save_checkpoint
        big = torch.randn(4_000_000)
        step = 0
        while True:
            save_checkpoint({str(target)!r}, task="uav", payload={{"state": {{"w": big}}, "step": step}})
            print(step, flush=True)
            step += 1
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", writer], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    proc.stdout.readline()  # one full checkpoint is on disk; the next one is being written
    time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    data = load_checkpoint(target, task="uav")
    assert data["step"] >= 0 and data["state"]["w"].shape == (4_000_000,)


@pytest.mark.parametrize("capacity", [2000, 20])  # partly filled, and wrapped around
def test_replay_buffer_checkpoint_keeps_only_filled_rows_and_restores_exactly(capacity):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    from dcsc_torchrl.checkpoint import load_replay_buffer_state, replay_buffer_state

    buffer = ReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=4)
    for _ in range(3):
        buffer.extend(TensorDict({"observation": torch.randn(16, 9),
                                  "next": {"reward": torch.randn(16, 1)}}, [16]))
    state = replay_buffer_state(buffer)
    assert all(v.shape[0] == len(buffer) for v in state["_storage"]["_storage"].values())
    restored = ReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=4)
    load_replay_buffer_state(restored, state)
    assert len(restored) == len(buffer)
    assert restored.state_dict()["_writer"] == buffer.state_dict()["_writer"]
    n = len(buffer)
    assert (restored.storage[:n] == buffer.storage[:n]).all()
    assert ("next", "reward") in restored.storage[:n].keys(True)


@pytest.mark.parametrize("algorithm", ["a2c", "ppo"])
def test_a_tiny_actor_critic_run_improves_its_return_on_a_fixed_seed(algorithm):
    """The recipe's A2C (``make_actor_critic`` + ``actor_critic_step``, its yaml's settings), and its PPO
    (``loss.algorithm=ppo``), on 8 CartPoles: LunarLander needs minutes to show progress,
    CartPole shows it in ~150 updates."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode
    from torchrl.collectors import Collector
    from torchrl.envs import GymWrapper, RewardSum, StepCounter

    from dcsc_torchrl.config import load_config
    from dcsc_torchrl.networks import lunar_actor, lunar_critic
    from dcsc_torchrl.recipes.pretrain_a2c_lunarlander import (
        CONFIG,
        actor_critic_step,
        make_actor_critic,
    )
    from dcsc_torchrl.training import finished_episodes

    torch.manual_seed(0)
    cfg = load_config(CONFIG, [f"loss.algorithm={algorithm}"])
    env = GymWrapper(gym.make_vec("CartPole-v1", num_envs=8, vectorization_mode="sync",
                                  vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}))
    env.append_transform(RewardSum())
    env.append_transform(StepCounter())
    env.set_seed(0)
    hidden = list(cfg.network.hidden)
    actor, loss, optim = make_actor_critic(cfg, lunar_actor(hidden, 0.0, obs_dims=4, n_actions=2, in_dims=4),
                                  lunar_critic(hidden, 1, obs_dims=4), env.full_action_spec["action"])
    collector = Collector(env, actor, frames_per_batch=40, total_frames=40 * 150,
                          auto_register_policy_transforms=False)
    returns = []
    for batch in collector:
        returns += [row["return"] for row in finished_episodes(batch)]
        metrics = actor_critic_step(cfg, loss, optim, batch)
        assert all(math.isfinite(value) for value in metrics.values())
    collector.shutdown()
    first, last = sum(returns[:20]) / 20, sum(returns[-20:]) / 20
    assert last > 1.4 * first, (first, last)


def test_the_landing_check_runs_after_each_segment_but_the_last(tmp_path):
    # a random machine never lands: the check runs (and is logged) but never stops training
    run_recipe("lunarlander", tmp_path, "train.stop_success=0.5", "train.stop_eval_episodes=2")
    checks = pd.read_csv(tmp_path / "stop_checks.csv")
    log = pd.read_csv(tmp_path / "train.csv")
    assert len(log) == 6 and checks["episode"].tolist() == [3, 6]
    assert checks["success"].between(0, 1).all()


def test_the_linear_learning_rate_falls_to_zero_over_the_episode_budget(tmp_path):
    run_recipe("lunarlander", tmp_path, "optim.lr_schedule=linear")
    log = pd.read_csv(tmp_path / "train.csv")
    before_last_update = (log["frames"] < log["frames"].max()).sum()  # episodes done when it ran
    lr = load_checkpoint(tmp_path / "checkpoint.pt", task="lunarlander")["state"]["optim"]["param_groups"][0]["lr"]
    assert 0 < before_last_update < 6 and lr == pytest.approx(5e-4 * (1 - before_last_update / 6))


def test_a_frame_budget_ends_training_mid_segment_and_drives_the_linear_learning_rate(tmp_path):
    # the quick recipe: 2 envs x 5 frames a batch, 6 episodes; 300 frames end it first
    run_recipe("lunarlander", tmp_path, "train.frames=300", "train.episodes=1000", "optim.lr_schedule=linear")
    log = pd.read_csv(tmp_path / "train.csv")
    data = load_checkpoint(tmp_path / "checkpoint.pt", task="lunarlander")
    assert data["frames"] == 300 and data["episodes"] == len(log) < 1000
    # the last update ran with 290 of 300 frames spent: lr = 5e-4 * (1 - 290 / 300)
    assert data["state"]["optim"]["param_groups"][0]["lr"] == pytest.approx(5e-4 * 10 / 300)


def test_a_frame_budget_counts_its_progress_in_frames(tmp_path, capsys):
    run_recipe("lunarlander", tmp_path, "train.frames=300", "train.episodes=1000")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("lunarlander frames")]
    assert lines and lines[-1].startswith("lunarlander frames: 300/300 frame")


def test_the_rmsprop_optimiser_is_the_one_trained_with(tmp_path):
    run_recipe("lunarlander", tmp_path, "optim.name=rmsprop", "optim.eps=1.0e-5")
    group = load_checkpoint(tmp_path / "checkpoint.pt", task="lunarlander")["state"]["optim"]["param_groups"][0]
    assert group["alpha"] == 0.99 and group["eps"] == 1e-5
    with pytest.raises(ConfigError, match="optim.name: expected one of adam, rmsprop, got 'sgd'"):
        run_recipe("lunarlander", tmp_path, "optim.name=sgd")


def test_an_unknown_lr_schedule_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="optim.lr_schedule"):
        run_recipe("lunarlander", tmp_path, "optim.lr_schedule=cosine")


def test_an_unknown_algorithm_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="loss.algorithm: expected one of a2c, ppo, got 'sac'"):
        run_recipe("lunarlander", tmp_path, "loss.algorithm=sac")


def test_an_unknown_network_init_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="network.init: expected one of default, orthogonal, got 'xavier'"):
        run_recipe("lunarlander", tmp_path, "network.init=xavier")


def test_orthogonal_init_gives_orthogonal_layers_a_small_policy_head_and_zero_biases():
    from dcsc_torchrl.networks import lunar_actor, orthogonal_init_

    torch.manual_seed(0)
    linears = [m for m in orthogonal_init_(lunar_actor([64, 64], 0.01), out_gain=0.01).modules()
               if isinstance(m, torch.nn.Linear)]
    for layer, gain in zip(linears, (math.sqrt(2), math.sqrt(2), 0.01), strict=True):
        w = layer.weight / gain  # rows (out < in) or columns orthonormal
        gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
        torch.testing.assert_close(gram, torch.eye(len(gram)), atol=1e-5, rtol=0)
        assert not layer.bias.any()
    with pytest.raises(ValueError, match="no nn.Linear"):
        orthogonal_init_(torch.nn.Tanh(), out_gain=1.0)


def test_the_ppo_recipe_trains_checkpoints_and_evaluates(tmp_path):
    run_recipe("lunarlander", tmp_path, "loss.algorithm=ppo", "ppo.minibatch_size=8")
    assert len(pd.read_csv(tmp_path / "train.csv")) == 6
    assert (tmp_path / "eval.csv").exists()
    data = load_checkpoint(tmp_path / "checkpoint.pt", task="lunarlander")
    assert data["config"]["loss"]["algorithm"] == "ppo"
    # a batch of 2 envs x 5 frames in minibatches of 8 (8 + 2 frames) over 4 epochs: 8 Adam steps
    adam_steps = data["state"]["optim"]["state"][0]["step"]
    assert adam_steps == 8 * data["frames"] / 10


def test_keep_best_makes_the_best_checks_machine_the_result(tmp_path):
    run_recipe("lunarlander", tmp_path, "train.keep_best=true", "train.stop_eval_episodes=2")
    checks = pd.read_csv(tmp_path / "stop_checks.csv")
    assert checks["episode"].tolist() == [3, 6] and len(pd.read_csv(tmp_path / "train.csv")) == 6
    best = checks.loc[checks["success"].idxmax(), "episode"]  # the first of equal checks
    for name in ("checkpoint.pt", "best.pt"):
        assert load_checkpoint(tmp_path / name, task="lunarlander")["episodes"] == best
    assert (tmp_path / "eval.csv").exists()


def test_restore_best_brings_back_the_kept_checkpoint(tmp_path):
    from dcsc_torchrl.training import TrainingRun

    net = torch.nn.Linear(1, 1)
    run = TrainingRun("lunarlander", out_dir=tmp_path, episodes=10, checkpoint_every=5, seed=0,
                      config={"seed": 0}, columns=["episode", "frames"], stateful={"net": net})
    run.start(resume=False)
    torch.nn.init.constant_(net.weight, 1.0)
    run.episodes = 5
    run.end_segment()
    run.keep_best()  # the check after segment 1 was the best
    torch.nn.init.constant_(net.weight, 2.0)
    run.episodes = 10
    run.end_segment()
    run.restore_best()
    assert net.weight.item() == 1.0 and run.episodes == 5 and run.segment == 1
    assert load_checkpoint(tmp_path / "checkpoint.pt", task="lunarlander")["state"]["net"]["weight"].item() == 1.0


@pytest.mark.parametrize(("task", "no_eval"), [("lunarlander", "eval.episodes=0"), ("uav", "eval.scenarios=0")])
def test_no_evaluation_episodes_skip_the_evaluation(task, no_eval, tmp_path):
    run_recipe(task, tmp_path, no_eval)  # the benchmarks run the recipes this way
    assert (tmp_path / "checkpoint.pt").exists() and not (tmp_path / "eval.csv").exists()


def protocol_machine(pretrain_dir: Path, seed: int, *overrides: str) -> None:
    """The LunarLander protocol's ``pretrained_machine`` for ``seed`` of ``pretrain_dir`` (quick config)."""
    from dcsc_torchrl.recipes.configs import CONFIGS
    from dcsc_torchrl.recipes.machines import pretrained_machine
    from dcsc_torchrl.tasks import get_task

    cfg = load_config(CONFIGS["lunarlander"].protocol,
                      [f"pretrain.out_dir={pretrain_dir}", *overrides], quick=True)
    pretrained_machine(get_task("lunarlander"), cfg, seed, quick=True)


def test_a_machine_kept_before_the_budget_is_loaded_by_the_protocol_not_resumed(tmp_path, capsys):
    # a random machine never lands: both checks (episodes 3, 6) give 0%, so keep_best keeps episode 3's
    run_recipe("lunarlander", tmp_path / "seed0", "train.keep_best=true")
    data = load_checkpoint(tmp_path / "seed0" / "checkpoint.pt", task="lunarlander")
    assert (data["episodes"], data["config"]["train"]["episodes"], data["finished"]) == (3, 6, True)
    protocol_machine(tmp_path, 0)
    assert "resuming" not in capsys.readouterr().err
    assert load_checkpoint(tmp_path / "seed0" / "checkpoint.pt", task="lunarlander")["episodes"] == 3
    assert len(pd.read_csv(tmp_path / "seed0" / "train.csv")) == 6


def test_the_protocol_pretrains_a_missing_machine_with_its_recipe_settings(tmp_path):
    protocol_machine(tmp_path, 1, "pretrain.recipe=[loss.algorithm=ppo,ppo.epochs=2]")
    config = load_checkpoint(tmp_path / "seed1" / "checkpoint.pt", task="lunarlander")["config"]
    assert (config["seed"], config["loss"]["algorithm"], config["ppo"]["epochs"]) == (1, "ppo", 2)


def test_greedy_episodes_stop_with_the_last_first_episode_and_match_a_full_rollout(lunar_physics_steps):
    """The greedy evaluation ends once every env's first episode is over (envs done are not
    stepped again) and finds the episodes a rollout to the frame limit finds."""
    from tensordict.nn import TensorDictModule

    from dcsc_torchrl.batched_envs import make_lunar_env
    from dcsc_torchrl.training import first_episodes, greedy_episodes

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(9, 16), torch.nn.Tanh(), torch.nn.Linear(16, 4))
    policy = TensorDictModule(lambda obs: torch.nn.functional.one_hot(net(obs).argmax(-1), 4),
                              ["observation"], ["action"])

    def env():
        lander = make_lunar_env(6, random_pad=False)
        lander.set_seed(5)
        return lander

    rows = greedy_episodes(env(), policy, 1000, ["success", "crashed"])
    resets = 2 * 6  # gymnasium's LunarLander steps once in a reset: set_seed's, then the rollout's
    assert len(lunar_physics_steps) == resets + sum(row["steps"] for row in rows)  # each env to its episode's end
    with torch.no_grad():
        full = env().rollout(1000, policy, break_when_any_done=False)
    assert rows == first_episodes(full, ["success", "crashed"])
    assert len(rows) == 6 and max(row["steps"] for row in rows) < 1000
