"""The pipeline's cost as a ratio to the physics: a validation run of each method against the
same frames stepped with no policy, in one process, one torch thread.

    python bench/bench_physics_ratio.py [--tasks lunarlander uav] [--scenarios 50] [--repeats 3]

For each task and method (``machine``, ``operator``, ``hula``, ``dcsc_centred`` learning
online as in validation), the shipped seed-0 machine and the ``expert`` operator play
``--scenarios`` development scenarios (seeds 30000..; one env each) through
:func:`dcsc_torchrl.episodes.run_scenarios`, the protocol's own path; its rate is the
recorded frames (each scenario's episode) per second. The physics baseline replays the
recorded actions with no policy, no operator and no TorchRL: LunarLander, one gymnasium
``TargetLunarLander`` per scenario stepped in a plain Python loop for as many frames as the
scenario recorded; the UAV, the task's batched env (its physics is written in torch) stepped
with the recorded actions until its longest episode, its rate the frames recorded per
second. Printed: a markdown table of both rates and their ratio (the median of
``--repeats``; docs/scaling.md records it).
"""

from __future__ import annotations

import argparse
import copy
import logging
import statistics
import time

import torch

from dcsc_torchrl.episodes import EpisodeBatch, run_scenarios
from dcsc_torchrl.methods import build_policy, make_arbiter
from dcsc_torchrl.online import make_online_learner
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.shipped import shipped_machine
from dcsc_torchrl.task import Task
from dcsc_torchrl.tasks import TASK_NAMES, get_task
from dcsc_torchrl.transforms import (
    FirstEpisodeOnly,
    HumanConfidenceTransform,
    HumanOperatorTransform,
)

METHODS = ("machine", "operator", "hula", "dcsc_centred")


def validation_run(task: Task, seeds: list[int], method: str, hula_threshold: float) -> tuple[EpisodeBatch, float]:
    """One validation run of ``method`` as the protocol plays it; its episodes and seconds."""
    cfg = task_config(task)
    settings = cell_settings(cfg)
    machine, critic = shipped_machine(task, cfg.pretrain.get("observes"))
    learns = method == "dcsc_centred"
    transforms = [HumanOperatorTransform(task.make_operator("expert"), seed=0),
                  HumanConfidenceTransform(**settings["human"])]
    env = task.make_envs(seeds, None, transforms if learns else [FirstEpisodeOnly(), *transforms])
    arbiter = make_arbiter(method, task.action_dims, hula_threshold=hula_threshold,
                           **(settings["arbiter"].start(method) if learns else {}))
    machine_settings = settings["machine"]
    spec_env = task.make_envs(seeds[:1], None, [])  # one env's action spec, as the protocol builds its policies
    action_spec = spec_env.full_action_spec["action"]
    spec_env.close()
    policy = build_policy(machine, arbiter, action_spec, discrete=task.discrete,
                          num_samples=machine_settings.num_samples, lam=machine_settings.lam,
                          delta2=machine_settings.delta2, observation_size=env.observation_spec["observation"].shape[-1])
    learner = make_online_learner(policy, copy.deepcopy(critic), **settings["online"]) if learns else None
    torch.manual_seed(0)
    start = time.perf_counter()
    result = run_scenarios(env, policy if learner is None else learner.policy, task,
                           rollout_length=settings["protocol"].rollout_length, update=learner,
                           exploration_type=settings["protocol"].exploration_type)
    seconds = time.perf_counter() - start
    env.close()
    return result, seconds


def recorded_actions(result: EpisodeBatch, n_envs: int) -> list[torch.Tensor]:
    """Each scenario's recorded actions, in frame order."""
    frames = result.frames
    return [frames["action"][frames["env_index"] == i][frames["frame_index"][frames["env_index"] == i].argsort()]
            for i in range(n_envs)]


def lunar_physics(seeds: list[int], actions: list[torch.Tensor]) -> float:
    """Seconds for the raw gymnasium TargetLunarLanders to step the recorded actions, one env per scenario."""
    from dcsc_torchrl.envs.target_lunar_lander import TargetLunarLander

    keys = [a.argmax(-1).tolist() for a in actions]
    envs = [TargetLunarLander(random_pad=True) for _ in seeds]
    start = time.perf_counter()
    for env, seed, scenario_keys in zip(envs, seeds, keys, strict=True):
        env.reset(seed=seed)
        for key in scenario_keys:
            _, _, terminated, truncated, _ = env.step(key)
            if terminated or truncated:  # a replay that ends sooner starts over: the frame count is what is timed
                env.reset()
    seconds = time.perf_counter() - start
    for env in envs:
        env.close()
    return seconds


def uav_physics(task: Task, seeds: list[int], actions: list[torch.Tensor]) -> float:
    """Seconds for the batched UAV env alone to step the recorded actions (each env its own,
    its last one held once its episode is over) until the longest episode ends."""
    env = task.make_envs(seeds, None, [])
    longest = max(len(a) for a in actions)
    padded = torch.stack([torch.cat([a, a[-1:].expand(longest - len(a), -1)]) for a in actions], dim=1)
    td = env.reset()
    start = time.perf_counter()
    for step in range(longest):
        td["action"] = padded[step]
        _, td = env.step_and_maybe_reset(td)
    seconds = time.perf_counter() - start
    env.close()
    return seconds


def bench(task_name: str, scenarios: int, repeats: int) -> list[dict[str, float | str]]:
    task = get_task(task_name)
    seeds = list(range(30_000, 30_000 + scenarios))
    operator, _ = validation_run(task, seeds, "operator", 0.0)
    threshold = float(torch.quantile(operator.uncertainty.double(), 0.9))  # HULA's, as the protocol calibrates it
    rows = []
    for method in METHODS:
        pipeline, physics = [], []
        for _ in range(repeats):
            result, seconds = validation_run(task, seeds, method, threshold)
            actions = recorded_actions(result, len(seeds))
            frames = sum(len(a) for a in actions)
            pipeline.append(frames / seconds)
            replay = lunar_physics(seeds, actions) if task.discrete else uav_physics(task, seeds, actions)
            physics.append(frames / replay)
        rows.append({"task": task_name, "method": method, "frames": frames,
                     "pipeline": statistics.median(pipeline), "physics": statistics.median(physics)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASK_NAMES), choices=TASK_NAMES)
    parser.add_argument("--scenarios", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    print(f"shipped seed-0 machines, operator expert, {args.scenarios} development scenarios, median of "
          f"{args.repeats}, torch threads: 1\n")
    print("| task | method | frames recorded | pipeline (frames/s) | physics alone (frames/s) | ratio |")
    print("|---|---|---:|---:|---:|---:|")
    for task in args.tasks:
        for r in bench(task, args.scenarios, args.repeats):
            print(f"| {r['task']} | {r['method']} | {r['frames']:,} | {r['pipeline']:,.0f} | {r['physics']:,.0f} "
                  f"| {r['pipeline'] / r['physics']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
