"""Operator-only success per preset on both tasks, and how fast the operators decide.

    python bench/bench_operators.py [--seeds 50] [--tasks lunarlander uav] [--presets P ...]

For every preset of :data:`dcsc_torchrl.humans.PRESETS`, the simulated operator flies
alone (``action = human_action``) one episode per env: TargetLunarLander with a random
pad over ``--seeds`` seeds (one batched env, up to 1000 frames) and the UAV over the
validation scenarios 0..seeds-1 (up to 500 steps). Prints a markdown table: success
rate, mean return and steps of those episodes, the rollout's env frames/s, the
operator's decisions/s (decisions over the seconds spent inside the operator) and the
operator's share of the rollout time.
"""

from __future__ import annotations

import argparse
import logging
import time

import torch
from tensordict import TensorDictBase

from dcsc_torchrl.humans import (
    PRESETS,
    SimulatedHuman,
    operator_only_episodes,
)
from dcsc_torchrl.tasks import TASK_NAMES, get_task
from dcsc_torchrl.transforms import HumanOperatorTransform


class TimedOperator:
    """Wraps an operator; adds up the seconds spent in it and the decisions it made."""

    def __init__(self, operator: SimulatedHuman) -> None:
        self.operator = operator
        self.seconds = 0.0
        self.decisions = 0

    def reset(self, seed: int | None) -> None:
        self.operator.reset(seed)

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        answer = self.operator(tensordict)
        self.seconds += time.perf_counter() - start
        self.decisions += int(answer.get("human_decided").sum())
        return answer


def bench(task: str, preset: str, seeds: int) -> dict[str, float]:
    """One preset alone on ``task`` over ``seeds`` episodes (one per env)."""
    spec = get_task(task)
    timed = TimedOperator(spec.make_operator(preset))
    env = spec.make_envs(list(range(seeds)), None, [HumanOperatorTransform(timed, seed=0)])
    env.set_seed(0)
    start = time.perf_counter()
    result = operator_only_episodes(env, spec.max_steps)
    wall = time.perf_counter() - start
    frames = seeds * int(result["steps"].max())
    return {
        "success": result["success"].float().mean().item(),
        "return": result["return"].mean().item(),
        "steps": result["steps"].float().mean().item(),
        "frames_per_s": frames / wall,
        "decisions_per_s": timed.decisions / timed.seconds,
        "operator_share": timed.seconds / wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument(
        "--tasks", nargs="+", default=list(TASK_NAMES), choices=TASK_NAMES
    )
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    print(f"operator alone, {args.seeds} seeds per task, torch threads: 1\n")
    print(
        "| task | preset | success | mean return | mean steps | env frames/s | operator decisions/s | operator share of time |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for task in args.tasks:
        for preset in args.presets:
            r = bench(task, preset, args.seeds)
            print(
                f"| {task} | {preset} | {r['success']:.0%} | {r['return']:.1f} | {r['steps']:.0f} "
                f"| {r['frames_per_s']:.0f} | {r['decisions_per_s']:.0f} | {r['operator_share']:.0%} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
