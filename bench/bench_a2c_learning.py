"""Does our A2C learn as Stable-Baselines3's does? Both at RL-Zoo's LunarLander settings, same frames, same task.

    python bench/bench_a2c_learning.py [--frames 200000] [--seeds 0 1 2]

A check of the training path, not a speed benchmark. RL-Zoo's A2C hyperparameters for
LunarLander (``a2c.yml``): 8 envs, ``n_steps`` 5, gamma 0.995, GAE lambda 1 (SB3's A2C
default), learning rate linear from 8.3e-4 to 0, entropy 1e-5, value 0.5, gradient norm 0.5,
RMSprop (alpha 0.99, eps 1e-5: SB3's A2C optimiser), 64-64 tanh networks with orthogonal
initialisation. Ours: ``dcsc pretrain lunarlander``'s recipe with those values
(``network.actor_dropout=0``: no dropout, as SB3's policy), its budget ``train.frames``.
Both play the same task: TargetLunarLander with the pad at the centre
(``dcsc/TargetLunarLander-v0``, ``random_pad=False``), the first 8 observation values (the
9th, the pad's x, is 0 there); SB3 through ``make_vec_env`` (``Monitor``-wrapped
envs), ``render_mode=None``. One torch thread each.

Printed per seed and method: the mean return of the last 100 training episodes when the
budget is spent (SB3's ``ep_info_buffer``; ours the last 100 rows of ``train.csv``), and the
frames/s; then each side's mean and spread over the seeds. Ours trains its Q critic beside
(what DC-SC needs), which SB3 does not: it costs time, not learning (separate network).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import torch

from dcsc_torchrl.batched_envs import LUNAR_ID
from dcsc_torchrl.networks import view_recipe_settings
from dcsc_torchrl.recipes.pretrain_a2c_lunarlander import main as pretrain_lunarlander

RL_ZOO = {"envs": 8, "n_steps": 5, "gamma": 0.995, "lr": 8.3e-4, "ent_coef": 1e-5, "vf_coef": 0.5,
          "max_grad_norm": 0.5, "rms_prop_eps": 1e-5}
"""RL-Zoo's A2C LunarLander entry, with SB3's A2C defaults it relies on."""
LAST_EPISODES = 100


def ours(seed: int, frames: int, out: Path) -> tuple[float, float]:
    """Mean return of our recipe's last 100 training episodes at the frame budget, and its frames/s."""
    z = RL_ZOO
    start = time.perf_counter()
    pretrain_lunarlander([
        "--out", str(out), f"seed={seed}", "threads=1", f"env.num_envs={z['envs']}",
        f"collector.rollout_length={z['n_steps']}", f"loss.gamma={z['gamma']}", "loss.gae_lambda=1.0",
        f"loss.entropy_coeff={z['ent_coef']}", f"loss.critic_coeff={z['vf_coef']}", "loss.critic_loss=l2",
        "loss.normalize_advantage=false", "optim.name=rmsprop", f"optim.lr={z['lr']}", "optim.lr_schedule=linear",
        f"optim.eps={z['rms_prop_eps']}", f"optim.max_grad_norm={z['max_grad_norm']}", "network.actor_dropout=0.0",
        "network.init=orthogonal", "network.hidden=[64,64]", f"train.frames={frames}", "train.episodes=1000000",
        "train.checkpoint_every=1000000", "eval.episodes=0", *view_recipe_settings("blind"),
    ])
    elapsed = time.perf_counter() - start
    log = pd.read_csv(out / "train.csv")
    return float(log["return"].tail(LAST_EPISODES).mean()), int(log["frames"].iloc[-1]) / elapsed


def sb3(seed: int, frames: int) -> tuple[float, float]:
    """Mean return of SB3's A2C's last 100 training episodes at the frame budget, and its frames/s."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    def make() -> gym.Env:
        env = gym.make(LUNAR_ID, random_pad=False, render_mode=None)
        low, high = env.observation_space.low[:8], env.observation_space.high[:8]
        return gym.wrappers.TransformObservation(env, lambda obs: obs[:8], gym.spaces.Box(low, high, dtype=np.float32))

    z = RL_ZOO
    env = make_vec_env(make, n_envs=z["envs"], seed=seed)
    model = A2C("MlpPolicy", env, n_steps=z["n_steps"], gamma=z["gamma"], learning_rate=lambda left: left * z["lr"],
                ent_coef=z["ent_coef"], vf_coef=z["vf_coef"], max_grad_norm=z["max_grad_norm"],
                rms_prop_eps=z["rms_prop_eps"], seed=seed, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    elapsed = time.perf_counter() - start
    env.close()
    returns = [info["r"] for info in model.ep_info_buffer]  # SB3 keeps the last 100 episodes
    return float(np.mean(returns[-LAST_EPISODES:])), frames / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    torch.set_num_threads(1)
    results: dict[str, list[float]] = {"dcsc-torchrl": [], "Stable-Baselines3": []}
    print(f"A2C at RL-Zoo's LunarLander settings, {args.frames:,} frames, TargetLunarLander (pad at the centre)\n")
    print(f"| seed | method | mean return, last {LAST_EPISODES} episodes | frames/s |")
    print("|---:|---|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for name, run in (("dcsc-torchrl", lambda s=seed: ours(s, args.frames, Path(tmp) / f"seed{s}")),
                              ("Stable-Baselines3", lambda s=seed: sb3(s, args.frames))):
                value, fps = run()
                results[name].append(value)
                print(f"| {seed} | {name} | {value:.1f} | {fps:,.0f} |", flush=True)
    print()
    for name, values in results.items():
        spread = f"{min(values):.1f} .. {max(values):.1f}"
        print(f"{name}: mean {statistics.mean(values):.1f} over seeds {args.seeds}, range {spread}")


if __name__ == "__main__":
    main()
