"""Scaling: sweep cells/minute with 1 vs 2 Ray workers, collection frames/s with 1 vs 2 collector workers.

Run: ``python bench/bench_sweep.py`` (a few minutes; everything in a temporary directory).

- Sweep: the quick grid of both tasks, presets expert and noisy, pretraining seed 0
  (4 cells, every method), run by ``recipes.sweep.run_sweep`` on a fresh local Ray instance
  of 1, then 2 CPUs; the quick machines are pretrained first, outside the timing. Ray's
  start is timed apart; the workers' start (importing torch) counts in the sweep.
- Per-cell seconds (``cell.json``) and env-frames (every batch of scenarios runs until
  its last scenario ends: scenarios x longest episode) give seconds per env-frame, which
  prices a full-scale cell at the protocol's frame bound (every batch to the horizon) and
  the full grid on N nodes (longest-cell-first list scheduling of its cells).
- Collection: the pretraining recipes' envs (full config: 8 LunarLanders, 16 UAVs),
  untrained actor, ``dcsc_torchrl.training.make_collector`` with 1 vs 2 workers; frames/s
  after the first batch (the workers' start is reported apart).

One measurement per row (no repeats: a sweep is minutes); the machine's other load shows.
"""

from __future__ import annotations

import heapq
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import pandas as pd
import ray
import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule
from torchrl.modules import OneHotCategorical, ProbabilisticActor

from dcsc_torchrl.config import load_config
from dcsc_torchrl.methods import METHOD_NAMES as METHODS
from dcsc_torchrl.methods import task_methods
from dcsc_torchrl.recipes.configs import CONFIGS, SWEEP_CONFIG
from dcsc_torchrl.recipes.machines import pretrained_machine
from dcsc_torchrl.recipes.sweep import connect, run_sweep, task_grid
from dcsc_torchrl.tasks import TASK_NAMES as TASKS
from dcsc_torchrl.tasks import get_task
from dcsc_torchrl.training import make_collector

RAY_WORKERS = (1, 2)
COLLECTOR_WORKERS = (1, 2)
COLLECT_FRAMES = {"lunarlander": 6_000, "uav": 8_000}
NODES = (1, 4, 16)
WORKERS_PER_NODE = (2, 16)  # this machine's CPUs, a common cluster node's


def cell_frames(episodes: pd.DataFrame) -> int:
    """Env-frames a cell stepped: each (phase, method) batch runs until its longest episode ends."""
    batches = episodes.groupby(["phase", "method"])["steps"]
    return int((batches.size() * batches.max()).sum())


def full_cell_frames(cfg: DictConfig, task: str) -> int:
    """The frame bound of one full-scale cell: every batch of scenarios runs to the horizon."""
    counts = cfg.scenarios
    methods = task_methods(get_task(task), METHODS)
    scenarios = counts.operator_runs + counts.collaboration_runs + counts.validation_scenarios * len(methods)
    return scenarios * (cfg.protocol.max_steps or get_task(task).max_steps)


def makespan(seconds: list[float], slots: int) -> float:
    """Wall time of ``seconds``-long jobs on ``slots`` workers, longest first to the least loaded."""
    loads = [0.0] * slots
    for job in sorted(seconds, reverse=True):
        heapq.heapreplace(loads, loads[0] + job)
    return max(loads)


def bench_sweep(root: Path) -> tuple[int, list[tuple[int, float, float]], dict[str, tuple[float, float]]]:
    """Cells; (Ray workers, Ray start s, sweep s) per setting; per task, seconds per cell and per
    env-frame (1 worker)."""
    sweep_cfg = load_config(SWEEP_CONFIG, ["operators=[expert,noisy]", "pretrain_seeds=[0]"], quick=True)
    grids = [task_grid(task, sweep_cfg, [f"pretrain.out_dir={root / f'pretrain_{task}'}"], quick=True)
             for task in TASKS]
    for grid in grids:
        pretrained_machine(get_task(grid.task), grid.cfg, 0, quick=True)
    rows, per_cell = [], {}
    for workers in RAY_WORKERS:
        out = root / f"sweep_{workers}"
        start = time.perf_counter()
        connect(None, workers)
        started = time.perf_counter()
        result = run_sweep(out, grids, METHODS, quick=True, retries=0, workers=workers)
        rows.append((workers, started - start, time.perf_counter() - started))
        ray.shutdown()
        if result.failed:
            raise RuntimeError(f"cells failed: {result.failed}")
        if workers == 1:
            for grid in grids:
                cells = [cell.directory(out) for cell in grid.cells]
                seconds = sum(json.loads((d / "cell.json").read_text())["seconds"] for d in cells)
                frames = sum(cell_frames(pd.read_csv(d / "episodes.csv")) for d in cells)
                per_cell[grid.task] = (seconds / len(cells), seconds / frames)
    return sum(len(grid.cells) for grid in grids), rows, per_cell


def collection_rate(task: str, workers: int) -> tuple[float, float]:
    """(start s, frames/s) of the pretraining recipe's collection with ``workers`` processes."""
    spec = get_task(task)
    cfg = load_config(CONFIGS[spec.name].pretrain)
    actor = spec.make_networks(cfg.network)[0]
    make_env = spec.make_pretraining_envs
    if spec.discrete:
        policy = ProbabilisticActor(TensorDictModule(actor, ["observation"], ["logits"]), ["logits"],
                                    spec=make_env(1).full_action_spec["action"], distribution_class=OneHotCategorical)
    else:
        policy = TensorDictModule(actor, ["observation"], ["action"])
    start = time.perf_counter()
    collector = make_collector(make_env, cfg.env.num_envs, policy, workers=workers, seed=0,
                               frames_per_batch=cfg.env.num_envs * cfg.collector.rollout_length)
    batches = iter(collector)
    next(batches)
    started = time.perf_counter()
    frames = 0
    while frames < COLLECT_FRAMES[task]:
        frames += next(batches).numel()
    rate = frames / (time.perf_counter() - started)
    collector.shutdown()
    torch.set_num_threads(1)
    return started - start, rate


def main() -> None:
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # the same in the collectors' spawned workers
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        cells, sweep_rows, per_cell = bench_sweep(Path(tmp))
    base = sweep_rows[0][2]
    print(f"torch {torch.__version__}, ray {ray.__version__}, {os.cpu_count()} CPUs, load average {load:.1f} "
          "at the start; one measurement per row\n")
    print(f"## Sweep: quick grid, {cells} cells (tasks x presets expert, noisy x seed 0), every method\n")
    print("| Ray workers | Ray start (s) | sweep (s) | cells / minute | speed-up |")
    print("|---:|---:|---:|---:|---:|")
    for workers, ray_start, seconds in sweep_rows:
        print(f"| {workers} | {ray_start:.1f} | {seconds:.1f} | {cells / seconds * 60:.1f} | {base / seconds:.2f} x |")

    print("\n## Full grid, priced from the measured seconds per env-frame (1 worker)\n")
    print("| task | quick cell (s) | s / env-frame | frame bound of a full cell | full cell (min) | cells |")
    print("|---|---:|---:|---:|---:|---:|")
    full_cells: list[float] = []
    for task in TASKS:
        cfg = load_config(CONFIGS[task].protocol)
        frames = full_cell_frames(cfg, task)
        n_cells = len(cfg.operator.presets) * len(cfg.pretrain.seeds)
        quick_cell, per_frame = per_cell[task]
        full_cells += [per_frame * frames] * n_cells
        print(f"| {task} | {quick_cell:.1f} | {per_frame * 1e3:.2f} ms | {frames:,} | {per_frame * frames / 60:.1f} "
              f"| {n_cells} |")
    print(f"\nAll {len(full_cells)} cells: {sum(full_cells) / 3600:.1f} CPU-hours.\n")
    print("| nodes | " + " | ".join(f"wall time (h), {w} workers / node" for w in WORKERS_PER_NODE) + " |")
    print("|---:|" + "---:|" * len(WORKERS_PER_NODE))
    for nodes in NODES:
        walls = [makespan(full_cells, nodes * workers) / 3600 for workers in WORKERS_PER_NODE]
        print(f"| {nodes} | " + " | ".join(f"{wall:.2f}" for wall in walls) + " |")

    print("\n## Pretraining collection: recipe envs, untrained actor\n")
    print("| task | collector workers | start (s) | frames / s | vs 1 worker |")
    print("|---|---:|---:|---:|---:|")
    for task in TASKS:
        rates = {workers: collection_rate(task, workers) for workers in COLLECTOR_WORKERS}
        for workers, (start, rate) in rates.items():
            print(f"| {task} | {workers} | {start:.1f} | {rate:,.0f} | {rate / rates[1][1]:.2f} x |")


if __name__ == "__main__":
    main()
