"""Environment throughput: TargetLunarLander vs stock LunarLander, batched UAV vs a loop.

Run: ``python bench/bench_envs.py``. One torch thread. Prints a markdown table; every
ratio compares two rows measured in this same run, interleaved, best of ``REPEATS``.

- LunarLander rows: random actions on the raw gymnasium env (``render_mode=None``),
  resetting on termination.
- UAV rows: ``UAVPathPlanningEnv`` stepped through TorchRL's public
  ``step_and_maybe_reset`` (as a collector does, auto-resetting finished scenarios) with
  random actions; env-steps/s = batch x steps/s. The baseline is a Python loop over 50
  batch-1 envs, one scenario each, stepped the same way.
- ``dcsc/UAVPathPlanning-v0`` row: the gymnasium id as Stable-Baselines3 drives it
  (``gym.make``, one scenario, numpy action in, numpy observation out, ``reset`` on
  termination), against the batched env at batch 1.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial

import gymnasium as gym
import numpy as np
import torch

import dcsc_torchrl.envs  # noqa: F401  (registers the ids)
from dcsc_torchrl.envs.uav import UAVPathPlanningEnv

LUNAR_STEPS = 20_000
UAV_STEPS = {1: 400, 50: 200, 1024: 60, 4096: 30}
LOOP_SCENARIOS = 50
LOOP_STEPS = 40
REPEATS = 5


def gym_steps_per_second(env_id: str, actions: list, seed: int) -> float:
    """Steps/s of the given actions on a gymnasium id (seeded reset, reset when done): how
    an outside client such as SB3 drives it."""
    env = gym.make(env_id)
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return len(actions) / (time.perf_counter() - start)


def lunar_steps_per_second(env_id: str, seed: int) -> float:
    """Steps/s of ``LUNAR_STEPS`` random steps."""
    return gym_steps_per_second(env_id, np.random.default_rng(seed).integers(0, 4, LUNAR_STEPS).tolist(), seed)


def uav_env_steps_per_second(env: UAVPathPlanningEnv, steps: int, seed: int) -> float:
    """Env-steps/s of ``steps`` random-action ``step_and_maybe_reset`` calls."""
    generator = torch.Generator().manual_seed(seed)
    actions = 3 * torch.rand(steps, *env.batch_size, 3, generator=generator)
    td = env.reset()
    start = time.perf_counter()
    for action in actions:
        _, td = env.step_and_maybe_reset(td.set("action", action))
    return env.batch_size.numel() * steps / (time.perf_counter() - start)


def uav_gym_steps_per_second(steps: int, seed: int) -> float:
    """Steps/s of ``steps`` random numpy actions on the gymnasium id, resetting when done."""
    actions = np.random.default_rng(seed).uniform(0.0, 3.0, (steps, 3)).astype(np.float32)
    return gym_steps_per_second("dcsc/UAVPathPlanning-v0", list(actions), seed)


def uav_loop_steps_per_second(singles: list[UAVPathPlanningEnv], seed: int) -> float:
    """Env-steps/s of a Python loop stepping single-scenario envs one after the other."""
    generator = torch.Generator().manual_seed(seed)
    actions = 3 * torch.rand(LOOP_STEPS, len(singles), 1, 3, generator=generator)
    tds = [env.reset() for env in singles]
    start = time.perf_counter()
    for step_actions in actions:
        for i, env in enumerate(singles):
            _, tds[i] = env.step_and_maybe_reset(tds[i].set("action", step_actions[i]))
    return len(singles) * LOOP_STEPS / (time.perf_counter() - start)


def best_of(measures: dict[str, Callable[[int], float]]) -> dict[str, float]:
    """Best rate of each measure over ``REPEATS`` rounds, the measures interleaved.

    Interleaving keeps a ratio fair when the machine's load drifts during the run.
    """
    best = dict.fromkeys(measures, 0.0)
    for repeat in range(REPEATS):
        for name, measure in measures.items():
            best[name] = max(best[name], measure(repeat))
    return best


def main() -> None:
    torch.set_num_threads(1)
    lunar = best_of(
        {
            "stock": partial(lunar_steps_per_second, "LunarLander-v3"),
            "target": partial(lunar_steps_per_second, "dcsc/TargetLunarLander-v0"),
        }
    )
    singles = [UAVPathPlanningEnv(scenario_seeds=[seed]) for seed in range(LOOP_SCENARIOS)]
    batched = {batch: UAVPathPlanningEnv(batch, seed=0) for batch in UAV_STEPS}
    uav = best_of(
        {
            "loop": partial(uav_loop_steps_per_second, singles),
            "gym": partial(uav_gym_steps_per_second, UAV_STEPS[1]),
            **{
                batch: partial(uav_env_steps_per_second, env, UAV_STEPS[batch])
                for batch, env in batched.items()
            },
        }
    )

    rows = [
        ("LunarLander-v3 (stock), 1 env", lunar["stock"], ""),
        (
            "dcsc/TargetLunarLander-v0, 1 env",
            lunar["target"],
            f"{lunar['target'] / lunar['stock']:.2f} x stock",
        ),
        (f"UAV, Python loop over {LOOP_SCENARIOS} batch-1 envs", uav["loop"], ""),
    ]
    for batch in UAV_STEPS:
        note = f"{uav[batch] / uav['loop']:.1f} x loop" if batch == LOOP_SCENARIOS else ""
        rows.append((f"UAVPathPlanningEnv, batch {batch}", uav[batch], note))
    rows.append((
        "dcsc/UAVPathPlanning-v0 (gymnasium, numpy in/out), 1 env",
        uav["gym"],
        f"{uav['gym'] / uav[1]:.2f} x batch 1",
    ))

    print(f"torch {torch.__version__}, 1 thread; best of {REPEATS} interleaved runs\n")
    print("| environment | env-steps/s | ratio |")
    print("|---|---:|---|")
    for name, rate, note in rows:
        print(f"| {name} | {rate:,.0f} | {note} |")


if __name__ == "__main__":
    main()
