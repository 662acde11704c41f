"""Shared control end to end: Algorithm 1, the baselines and the paper's protocol (§6, DESIGN §5).

For every pretraining seed (the machine is pretrained when its checkpoint is missing) and
every operator preset, one *cell* of the protocol runs (``dcsc_torchrl.experiment.run_cell``):

1. the operator alone on 20 scenarios — calibrates HULA's threshold;
2. DC-SC collaborating on 20 scenarios — theta and the critic learn online (Algorithm 1);
3. the 50 validation scenarios (5 groups of 10) for machine / operator / HULA / DC-SC,
   DC-SC still learning online.

    python recipes/shared_control.py {lunarlander,uav} [--quick] [--out DIR]
        [--methods M ...] [--operators P ...] [key=value ...]

Outputs in ``DIR/<task>/`` (default ``results/<task>/``): ``episodes.csv`` (every episode of
every phase), ``trace.csv`` (every step of scenario 0 for each method, main operator and
first pretraining seed), ``theta.csv`` (every online update of theta), ``summary.md`` and
the figures ``fig_*.png``. The CSVs are rewritten (atomically) after every cell, so a run
that stops halfway keeps the cells it finished.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.config import load_config
from dcsc_torchrl.experiment import METHODS, run_cell
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.report import write_task_figures, write_task_summary

RECIPES = Path(__file__).parent
PRETRAIN = {"lunarlander": "pretrain_a2c_lunarlander", "uav": "pretrain_ddpg_uav"}


def pretrained_machine(task: str, cfg: DictConfig, seed: int, *, quick: bool) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The machine actor and critic of pretraining seed ``seed``; pretrains it when missing."""
    out = Path(cfg.pretrain.out_dir) / f"seed{seed}"
    if not (out / "checkpoint.pt").exists():
        import importlib

        recipe = importlib.import_module(f"recipes.{PRETRAIN[task]}")
        recipe.main([*(["--quick"] if quick else []), "--out", str(out), f"seed={seed}"])
    return machine_from_checkpoint(load_checkpoint(out / "checkpoint.pt", task=task), task)


def write_csv(rows: list[dict], path: Path) -> None:
    """All rows so far, written atomically (temp file + rename)."""
    tmp = path.with_suffix(".csv.tmp")
    pd.DataFrame(rows).to_csv(tmp, index=False)
    os.replace(tmp, path)


def cell_grid(presets: Sequence[str], seeds: Sequence[int], main: str) -> tuple[list[tuple[int, str, bool]], str]:
    """The protocol's cells in order, ``(pretraining seed, preset, traced)``, and the main operator.

    The main operator is ``main`` when it is among ``presets`` (else the first preset); its
    cell with the first pretraining seed is the one whose scenario 0 is traced (the paper's
    single-human setting of the tables and figures).
    """
    main_operator = main if main in presets else presets[0]
    cells = [(seed, preset, preset == main_operator and seed == seeds[0]) for seed in seeds for preset in presets]
    return cells, main_operator


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task", choices=sorted(PRETRAIN))
    parser.add_argument("--quick", action="store_true", help="the tiny setting (tests, QUICK=1)")
    parser.add_argument("--out", type=Path, default=Path("results"), help="results root (default results/)")
    parser.add_argument("--methods", "--method", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--operators", "--operator", nargs="+", default=None, help="operator presets (default: the config's)")
    parser.add_argument("overrides", nargs="*", help="config overrides, hydra style: online.theta_lr=0.1")
    return parser.parse_intermixed_args(argv)


def main(argv: Sequence[str] | None = None) -> Path:
    args = parse_args(argv)
    cfg = load_config(RECIPES / f"shared_control_{args.task}.yaml", args.overrides, quick=args.quick)
    torch.set_num_threads(cfg.threads)
    seeds = list(cfg.pretrain.seeds)
    cells, main_operator = cell_grid(args.operators or list(cfg.operator.presets), seeds, cfg.operator.main)
    out = args.out / args.task
    out.mkdir(parents=True, exist_ok=True)

    episodes, traces, thetas = [], [], []
    for seed, preset, traced in tqdm(cells, desc=f"{args.task} cells", unit="cell", disable=None):
        machine, critic = pretrained_machine(args.task, cfg, seed, quick=args.quick)
        result = run_cell(args.task, cfg, preset, seed, machine, critic, methods=tuple(args.methods), trace=traced)
        episodes += result.episodes
        traces += result.traces
        thetas += result.theta
        write_csv(episodes, out / "episodes.csv")
        write_csv(traces, out / "trace.csv")
        write_csv(thetas, out / "theta.csv")

    write_task_summary(out, args.task, main_operator, seeds[0])
    write_task_figures(out, args.task, main_operator, seeds[0])
    return out


if __name__ == "__main__":
    main()
