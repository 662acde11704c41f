"""A2C pretraining throughput: this project's recipe vs Stable-Baselines3's A2C, same run.

Both train with the recipe's number of envs and rollout length (``env.num_envs`` x
``collector.rollout_length`` of ``recipes/pretrain_a2c_lunarlander.yaml``; ours:
TargetLunarLanders with the pad at the centre, SB3: LunarLander-v3), one torch thread
each, and report frames/s including environment stepping and updates. SB3 is built as
its docs recommend, ``make_vec_env`` (a ``DummyVecEnv`` of ``Monitor``-wrapped envs), but
with ``render_mode=None``: ``make_vec_env``'s default ``render_mode="rgb_array"`` keeps a
Box2D body per flame particle that only ``render()`` removes and would slow SB3 down
unfairly. The two are run alternately ``--repeats`` times (the machine's load drifts) and
the medians are compared. SB3 is installed only for this benchmark (``pip install -e
.[bench]``, done by ``make bench``).

    python bench/bench_pretrain.py [--frames 20000] [--repeats 3] [--envs N] [--rollout T]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import pandas as pd
import torch

from dcsc_torchrl.config import load_config

RECIPE_CONFIG = Path(__file__).resolve().parents[1] / "recipes" / "pretrain_a2c_lunarlander.yaml"


def ours(frames: int, out: Path, *overrides: str) -> tuple[float, int]:
    """Frames/s of recipes/pretrain_a2c_lunarlander.py and the frames it ran, stopped by an episode budget.

    The clock includes building the envs of each checkpointed segment, the Q critic's
    updates and writing the checkpoints (the final evaluation is switched off), as a
    user's run pays them too.
    """
    from recipes.pretrain_a2c_lunarlander import main

    start = time.perf_counter()
    main(["--out", str(out), f"train.episodes={max(1, frames // 110)}", "eval.episodes=0", *overrides])
    elapsed = time.perf_counter() - start
    done = int(pd.read_csv(out / "train.csv")["frames"].iloc[-1])
    return done / elapsed, done


def sb3(frames: int, num_envs: int, rollout: int) -> float:
    """Frames/s of SB3's A2C with Table A1's hyperparameters where they apply."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("LunarLander-v3", n_envs=num_envs, seed=0, env_kwargs={"render_mode": None})
    model = A2C("MlpPolicy", env, n_steps=rollout, learning_rate=5e-4, gamma=0.99, gae_lambda=0.95,
                ent_coef=0.01, vf_coef=0.5, max_grad_norm=0.5, seed=0, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    elapsed = time.perf_counter() - start
    env.close()
    return frames / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--envs", type=int, default=None, help="envs of both (default: the recipe's env.num_envs)")
    parser.add_argument("--rollout", type=int, default=None,
                        help="frames per env per update, both (default: the recipe's collector.rollout_length)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(RECIPE_CONFIG)
    num_envs = int(cfg.env.num_envs) if args.envs is None else args.envs
    rollout = int(cfg.collector.rollout_length) if args.rollout is None else args.rollout
    envs = (f"env.num_envs={num_envs}", f"collector.rollout_length={rollout}")
    ours_fps, sb3_fps = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            fps, done = ours(args.frames, Path(tmp), *envs)
        ours_fps.append(fps)
        sb3_fps.append(sb3(done, num_envs, rollout))
    ours_m, sb3_m = statistics.median(ours_fps), statistics.median(sb3_fps)
    print(f"| A2C pretraining, {num_envs} envs x {rollout} steps, median of {args.repeats} | frames/s |")
    print("|---|---:|")
    print(f"| dcsc-torchrl recipe (incl. the Q critic) | {ours_m:,.0f} |")
    print(f"| Stable-Baselines3 A2C (`render_mode=None`) | {sb3_m:,.0f} |")
    print(f"| ratio ours / SB3 | {ours_m / sb3_m:.2f} |")


if __name__ == "__main__":
    main()
