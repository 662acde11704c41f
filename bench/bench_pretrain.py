"""Pretraining throughput: this project's recipes vs Stable-Baselines3, same run, as a ratio.

``--task lunarlander`` (default): A2C. Both train with the recipe's number of envs and
rollout length (``env.num_envs`` x ``collector.rollout_length`` of
``recipes/pretrain_a2c_lunarlander.yaml``; ours: the goal-blind machine on TargetLunarLanders
with the pad at the centre in one native batched env, SB3: LunarLander-v3), Table A1's
hyperparameters. SB3 is built as its docs recommend, ``make_vec_env`` (a ``DummyVecEnv`` of
``Monitor``-wrapped envs), but with ``render_mode=None``: ``make_vec_env``'s default
``render_mode="rgb_array"`` keeps a Box2D body per flame particle that only ``render()``
removes and would slow SB3 down unfairly. Ours includes the Q critic's updates, which SB3's A2C does not do.

``--task uav``: DDPG at the same update-to-data ratio, batch, networks and random start
(``recipes/pretrain_ddpg_uav.yaml``: 16 envs x 10 steps per round, 0.25 gradient steps
per frame, batch 128, 256-256 MLPs, 2000 random frames). Ours steps the 16 scenarios as
one batched torch env; SB3 steps 16 copies of the gymnasium id
``dcsc/UAVPathPlanning-v0`` in a ``DummyVecEnv`` (``train_freq`` 10 steps, 40 gradient
steps a round), the way a user of SB3 would run it.

Both sides: one torch thread, frames/s including env stepping and updates, run
alternately ``--repeats`` times (the machine's load drifts), medians compared. SB3 is
installed only for this benchmark (``pip install -e .[bench]``, done by ``make bench``).

    python bench/bench_pretrain.py [--task lunarlander|uav] [--frames N] [--repeats 3] [--envs N] [--rollout T]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig

from dcsc_torchrl.config import load_config
from dcsc_torchrl.networks import view_recipe_settings
from dcsc_torchrl.recipes.configs import RECIPES_DIR

RECIPES = RECIPES_DIR


@dataclass(frozen=True)
class Comparison:
    """One task's benchmark: our recipe and the SB3 algorithm it is compared with."""

    recipe: str  # module in recipes/ (its yaml beside it)
    frames_per_episode: int  # sizes the recipe's episode budget from --frames
    settings: tuple[str, ...]  # the recipe's overrides: its final evaluation off, SB3's task
    sb3: Callable[[DictConfig, int, int, int], float]  # (cfg, frames, envs, rollout) -> frames/s
    ours_label: str
    sb3_label: str


def ours(task: str, frames: int, out: Path, *overrides: str) -> tuple[float, int]:
    """Frames/s of the task's pretraining recipe and the frames it ran, stopped by an episode budget.

    The clock includes building the envs of each checkpointed segment and writing the
    checkpoints (the final evaluation is switched off), as a user's run pays them too.
    """
    bench = TASKS[task]
    main = importlib.import_module(f"dcsc_torchrl.recipes.{bench.recipe}").main
    start = time.perf_counter()
    main(["--out", str(out), f"train.episodes={max(1, frames // bench.frames_per_episode)}", *bench.settings,
          *overrides])
    elapsed = time.perf_counter() - start
    done = int(pd.read_csv(out / "train.csv")["frames"].iloc[-1])
    return done / elapsed, done


def sb3_a2c(cfg: DictConfig, frames: int, num_envs: int, rollout: int) -> float:
    """Frames/s of SB3's A2C with Table A1's hyperparameters where they apply."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("LunarLander-v3", n_envs=num_envs, seed=0, env_kwargs={"render_mode": None})
    model = A2C("MlpPolicy", env, n_steps=rollout, learning_rate=cfg.optim.lr, gamma=cfg.loss.gamma,
                gae_lambda=cfg.loss.gae_lambda, ent_coef=cfg.loss.entropy_coeff, vf_coef=cfg.loss.critic_coeff,
                max_grad_norm=cfg.optim.max_grad_norm, seed=0, device="cpu")
    return _learn(model, env, frames)


def sb3_ddpg(cfg: DictConfig, frames: int, num_envs: int, rollout: int) -> float:
    """Frames/s of SB3's DDPG on the gymnasium id at the recipe's update-to-data ratio, batch and networks."""
    import numpy as np
    from stable_baselines3 import DDPG
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.noise import NormalActionNoise

    import dcsc_torchrl.envs  # noqa: F401  (registers dcsc/UAVPathPlanning-v0)

    env = make_vec_env("dcsc/UAVPathPlanning-v0", n_envs=num_envs, seed=0)
    model = DDPG(
        "MlpPolicy", env, learning_rate=cfg.optim.critic_lr, buffer_size=min(cfg.optim.buffer_size, frames),
        learning_starts=cfg.collector.init_random_frames, batch_size=cfg.optim.batch_size,
        tau=1.0 - cfg.loss.polyak, gamma=cfg.loss.gamma, train_freq=(rollout, "step"),
        gradient_steps=round(cfg.optim.updates_per_frame * num_envs * rollout),
        action_noise=NormalActionNoise(np.zeros(3), np.full(3, cfg.exploration.sigma_init)),
        policy_kwargs={"net_arch": list(cfg.network.hidden)}, seed=0, device="cpu",
    )
    return _learn(model, env, frames)


def _learn(model, env, frames: int) -> float:
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    elapsed = time.perf_counter() - start
    env.close()
    return frames / elapsed


TASKS = {
    "lunarlander": Comparison("pretrain_a2c_lunarlander", 110, ("eval.episodes=0", *view_recipe_settings("blind")), sb3_a2c,
                              "dcsc-torchrl A2C recipe (incl. the Q critic)",
                              "Stable-Baselines3 A2C (`render_mode=None`)"),
    "uav": Comparison("pretrain_ddpg_uav", 120, ("eval.scenarios=0",), sb3_ddpg,
                      "dcsc-torchrl DDPG recipe", "Stable-Baselines3 DDPG"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", choices=sorted(TASKS), default="lunarlander")
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--envs", type=int, default=None, help="envs of both (default: the recipe's env.num_envs)")
    parser.add_argument("--rollout", type=int, default=None,
                        help="frames per env per update, both (default: the recipe's collector.rollout_length)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    bench = TASKS[args.task]
    cfg = load_config(RECIPES / f"{bench.recipe}.yaml")
    num_envs = int(cfg.env.num_envs) if args.envs is None else args.envs
    rollout = int(cfg.collector.rollout_length) if args.rollout is None else args.rollout
    envs = (f"env.num_envs={num_envs}", f"collector.rollout_length={rollout}")
    ours_fps, sb3_fps = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            fps, done = ours(args.task, args.frames, Path(tmp), *envs)
        ours_fps.append(fps)
        sb3_fps.append(bench.sb3(cfg, done, num_envs, rollout))
    ours_m, sb3_m = statistics.median(ours_fps), statistics.median(sb3_fps)
    print(f"| {args.task} pretraining, {num_envs} envs x {rollout} steps, median of {args.repeats} | frames/s |")
    print("|---|---:|")
    print(f"| {bench.ours_label} | {ours_m:,.0f} |")
    print(f"| {bench.sb3_label} | {sb3_m:,.0f} |")
    print(f"| ratio ours / SB3 | {ours_m / sb3_m:.2f} |")


if __name__ == "__main__":
    main()
