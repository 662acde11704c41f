"""What ``FirstEpisodeOnly`` saves: a run that learns nothing, with and without it, as a ratio.

    python bench/bench_first_episode.py [--scenarios 50] [--repeats 3] [--beta 0.6] [--tasks lunarlander uav]

For each task: the shipped seed-0 machine and the ``expert`` operator play a constant β
on ``--scenarios`` development scenarios (seeds 30000..; one env each, as a cell's
validation run does), through :func:`dcsc_torchrl.episodes.run_scenarios`, once with the
env holding each scenario after its recorded episode (``FirstEpisodeOnly``, what the
protocol gives its runs that learn nothing) and once without, alternately ``--repeats``
times in one process. Checks that both record the same rows and frames, and prints a
markdown table: the median seconds of each, their ratio, and the frames the batch
records against those it would step without the transform.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time

import torch

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.episodes import EpisodeBatch, run_scenarios
from dcsc_torchrl.methods import build_policy, make_arbiter
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.shipped import shipped_path
from dcsc_torchrl.tasks import TASK_NAMES, get_task
from dcsc_torchrl.transforms import (
    FirstEpisodeOnly,
    HumanConfidenceTransform,
    HumanOperatorTransform,
)


def play(task_name: str, seeds: list[int], beta: float, first_episode_only: bool) -> tuple[EpisodeBatch, float]:
    """One constant-β run of ``seeds``; its episodes and its seconds."""
    task = get_task(task_name)
    cfg = task_config(task)
    settings = cell_settings(cfg)
    checkpoint = load_checkpoint(shipped_path(task, cfg.pretrain.get("observes")), task=task.name)
    machine, _ = machine_from_checkpoint(checkpoint, task)
    transforms = [HumanOperatorTransform(task.make_operator("expert"), seed=0),
                  HumanConfidenceTransform(**settings["human"])]
    env = task.make_envs(seeds, None, [FirstEpisodeOnly(), *transforms] if first_episode_only else transforms)
    policy = build_policy(machine, make_arbiter("constant", task.action_dims, constant_beta=beta),
                          env.full_action_spec["action"], discrete=task.discrete,
                          num_samples=settings["machine"].num_samples, lam=settings["machine"].lam,
                          delta2=settings["machine"].delta2)
    torch.manual_seed(0)
    start = time.perf_counter()
    result = run_scenarios(env, policy, task, rollout_length=settings["protocol"].rollout_length,
                           exploration_type=settings["protocol"].exploration_type)
    seconds = time.perf_counter() - start
    env.close()
    return result, seconds


def bench(task_name: str, scenarios: int, repeats: int, beta: float) -> dict[str, float]:
    seeds = list(range(30_000, 30_000 + scenarios))
    times: dict[bool, list[float]] = {True: [], False: []}
    results: dict[bool, EpisodeBatch] = {}
    for _ in range(repeats):
        for held in (True, False):
            results[held], seconds = play(task_name, seeds, beta, held)
            times[held].append(seconds)
    held, played = results[True], results[False]
    if held.rows != played.rows or not all(held.frames[key].equal(played.frames[key])
                                           for key in held.frames.keys(True, True)):
        raise SystemExit(f"{task_name}: FirstEpisodeOnly changed the recorded episodes")
    steps = [row["steps"] for row in held.rows]
    rollout = 5 * -(-max(steps) // 5)  # the batch runs in rollouts of 5 frames to its longest episode
    return {"held": statistics.median(times[True]), "played": statistics.median(times[False]),
            "recorded": sum(steps), "stepped": rollout * len(steps)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--beta", type=float, default=0.6)
    parser.add_argument("--tasks", nargs="+", default=list(TASK_NAMES), choices=TASK_NAMES)
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    print(f"constant beta {args.beta}, operator expert, shipped machine, {args.scenarios} scenarios, "
          f"median of {args.repeats}, torch threads: 1\n")
    print("| task | with FirstEpisodeOnly (s) | without (s) | ratio without / with | frames recorded / stepped without |")
    print("|---|---:|---:|---:|---:|")
    for task in args.tasks:
        r = bench(task, args.scenarios, args.repeats, args.beta)
        print(f"| {task} | {r['held']:.1f} | {r['played']:.1f} | {r['played'] / r['held']:.2f} "
              f"| {r['recorded']:,} / {r['stepped']:,} |")


if __name__ == "__main__":
    main()
