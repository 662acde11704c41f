"""A2C pretraining throughput: this project's recipe vs Stable-Baselines3's A2C, same run.

Both train on LunarLander-class envs with the same number of envs and rollout length
(this recipe: 8 TargetLunarLanders with the pad at the centre, SB3: 8 LunarLander-v3),
one torch thread each, and report frames/s including environment stepping and updates.
SB3 is installed only for this benchmark (``pip install -e .[bench]``, done by
``make bench``).

    python bench/bench_pretrain.py [--frames 20000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import pandas as pd
import torch


def ours(frames: int, out: Path) -> float:
    """Frames/s of recipes/pretrain_a2c_lunarlander.py, stopped by an episode budget.

    The clock includes building the envs of each checkpointed segment and writing the
    checkpoints (the final evaluation is switched off), as a user's run pays them too.
    """
    from recipes.pretrain_a2c_lunarlander import main

    start = time.perf_counter()
    main(["--out", str(out), f"train.episodes={max(1, frames // 110)}", "eval.episodes=0"])
    elapsed = time.perf_counter() - start
    done = pd.read_csv(out / "train.csv")["frames"].iloc[-1]
    return done / elapsed


def sb3(frames: int, num_envs: int, rollout: int) -> float:
    """Frames/s of SB3's A2C with Table A1's hyperparameters where they apply."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("LunarLander-v3", n_envs=num_envs, seed=0)
    model = A2C("MlpPolicy", env, n_steps=rollout, learning_rate=5e-4, gamma=0.99, gae_lambda=0.95,
                ent_coef=0.01, vf_coef=0.5, max_grad_norm=0.5, seed=0, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    return frames / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        ours_fps = ours(args.frames, Path(tmp))
    sb3_fps = sb3(args.frames, num_envs=8, rollout=5)
    print("| A2C pretraining, 8 envs x 5 steps | frames/s |")
    print("|---|---:|")
    print(f"| dcsc-torchrl recipe (incl. Q critic) | {ours_fps:,.0f} |")
    print(f"| Stable-Baselines3 A2C | {sb3_fps:,.0f} |")
    print(f"| ratio ours / SB3 | {ours_fps / sb3_fps:.2f} |")


if __name__ == "__main__":
    main()
