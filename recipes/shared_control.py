"""Shared control end to end: Algorithm 1, the baselines and the paper's protocol (§6; docs/architecture.md).

For every pretraining seed (the machine is pretrained when its checkpoint is missing) and
every operator preset, one *cell* of the protocol runs (``dcsc_torchrl.protocol.run_cell``):

1. calibrate: the operator alone, then the machine alone, on 20 scenarios — HULA's
   threshold, the unit of the machine's uncertainty, the critic's warm-up;
2. collaborate: each learned arbiter (Eq. 15, centred) on 20 scenarios — theta and the
   critic learn online (Algorithm 1);
3. validate: the 50 validation scenarios (5 groups of 10) for machine / operator / HULA /
   both DC-SC forms / DC-SC with frozen confidences / a sweep of constant betas, the
   learned arbiters still learning online.

    dcsc run {lunarlander,uav} [--quick] [--out DIR] [--methods M ...] [--operators P ...]
        [--fresh] [--workers N] [key=value ...]

Outputs in ``DIR/<task>/`` (default ``results/<task>/``): ``episodes.csv`` (every episode of
every phase), ``trace.csv`` (every step of scenario 0 for each method, main operator and
first pretraining seed), ``theta.csv`` (every online update of theta), ``calibration.csv`` (one row per cell), ``summary.md`` and
the figures ``fig_*.png``. Each cell writes its rows to ``cells/<operator>-seed<s>/``, its
``cell.json`` last; after every cell the task's tables, summary and figures are gathered
again from the finished cells (:func:`gather`, the one writer of these files, which
``dcsc sweep`` uses too), so the folder never describes two different sets of cells.

The door (:func:`checked_grid`, shared by ``dcsc run``, ``dcsc sweep`` and ``dcsc
reproduce``): the whole config, the presets, methods and checkpoints named, and the
results folder are checked before any frame is stepped or any folder is written; a
repeated preset, seed or method is dropped with a warning, so each cell is run once.

Resume: running the same command again (from any folder) skips the cells with a
``cell.json``. The config the cells ran with is kept in ``run_config.yaml``; a run into a
folder whose record differs (or into an older folder with no record) is refused with the
keys that differ, unless ``--fresh`` deletes the old results first or no cell of the
earlier config finished. One run writes a folder at a time (:func:`folder_lock`).
Temporary files of a killed run are removed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from dcsc_torchrl.config import (
    ConfigError,
    distinct,
)
from dcsc_torchrl.methods import DEFAULT_METHODS, METHOD_NAMES, check_task_methods
from dcsc_torchrl.recipes.executors import executor
from dcsc_torchrl.recipes.grid import checked_grid, run_grid
from dcsc_torchrl.recipes.options import Parser, add_run_options
from dcsc_torchrl.recipes.settings import check_names
from dcsc_torchrl.tasks import TASK_NAMES, get_task


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line of ``dcsc run`` (the same options, :func:`dcsc_torchrl.cli.add_run_options`)."""
    parser = Parser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task", choices=TASK_NAMES, help="the task")
    return add_run_options(parser).parse_args(argv)


def run_task(task_name: str, *, out: Path = Path("results"), quick: bool = False, overrides: Sequence[str] = (),
             methods: Sequence[str] | None = None, operators: Sequence[str] | None = None,
             fresh: bool = False, workers: int = 1) -> Path:
    """Every cell of ``task_name`` not done yet, ``workers`` at a time (:func:`run_grid` with the
    :func:`~dcsc_torchrl.recipes.executors.executor`: one after another in this process, or Ray tasks on a local
    instance); returns ``out/<task>``.

    Everything named (config keys, methods, operator presets, the results folder's
    earlier config, the checkpoints there are) is checked before a machine is loaded or pretrained.
    """
    if methods:  # named ones must be the task's (the default, every method, runs those the task defines)
        methods = check_names("--methods", "method", distinct("--methods", methods), METHOD_NAMES)
        try:
            check_task_methods(get_task(task_name), methods)
        except ValueError as err:
            raise ConfigError(str(err)) from None
    methods = tuple(methods or DEFAULT_METHODS)
    grid = checked_grid(task_name, quick=quick, overrides=overrides, operators=operators)
    torch.set_num_threads(grid.cfg.threads)
    run_grid(Path(out), [grid], methods, executor(workers), quick=quick, fresh=fresh)
    task_dir = Path(out) / grid.task
    print(f"results in {task_dir}", file=sys.stderr, flush=True)
    return task_dir


def run(args: argparse.Namespace) -> Path:
    """``dcsc run``: :func:`run_task` with the command line's options."""
    return run_task(args.task, out=args.out, quick=args.quick, overrides=args.overrides, methods=args.methods,
                    operators=args.operators, fresh=args.fresh, workers=args.workers)


def main(argv: Sequence[str] | None = None) -> Path:
    return run(parse_args(argv))


if __name__ == "__main__":
    main()
