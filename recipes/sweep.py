"""``dcsc sweep``: the protocol's cells as Ray tasks, on this machine or a Ray cluster.

A *cell* is one (task, operator preset, pretraining seed) of the protocol: every method
on every scenario seed of the task's config (``dcsc_torchrl.protocol.run_cell``). The
sweep runs the grid of cells as Ray tasks, one CPU each (docs/scaling.md):

1. one Ray task per pretraining checkpoint the cells need, which pretrains it when it is
   missing (or finishes one that stopped halfway); a cell starts once its checkpoint is
   there, so no two cells ever pretrain the same seed;
2. the cells, each writing its rows to ``DIR/<task>/cells/<operator>-seed<s>/``:
   ``episodes.csv``, ``trace.csv``, ``theta.csv`` (those with rows), then ``cell.json``
   (time, attempts, worker), every file atomic;
3. per task, the cells' rows gathered into ``DIR/<task>/episodes.csv``, ``trace.csv``,
   ``theta.csv``, ``summary.md`` and the figures: the files ``make reproduce`` writes, rows
   in the same order.

These are the files ``dcsc run`` writes: both are ``dcsc_torchrl.recipes.grid.run_grid``, the
one driver of the grid, ``dcsc run`` with its local executor (one cell after another) and
the sweep with Ray's (this module), so a sweep and a serial run can finish each other's
folders; a folder of another config is refused unless ``--fresh``.

A cell that raises is re-run by Ray (``ray.retries`` times); one that keeps failing is
listed with its error in ``DIR/<task>/failed_cells.csv`` and in a "Failed cells" section
of ``summary.md`` (traceback in its ``error.txt``), and the other cells' rows are kept. A
cell with a ``cell.json`` is done: running the sweep again runs only the others.

    dcsc sweep [--quick] [--out DIR] [--address ADDR] [--fresh] [key=value ...]

``key=value`` sets the sweep config (``recipes/sweep.yaml``: ``ray.workers=4``,
``tasks=[uav]``), or, prefixed with a task, that task's protocol config
(``lunarlander.protocol.max_steps=200``).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import ray
import torch
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.config import load_config
from dcsc_torchrl.methods import DEFAULT_METHODS, METHOD_NAMES
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.recipes.configs import SWEEP_CONFIG
from dcsc_torchrl.recipes.grid import (
    Cell,
    Executor,
    GridResult,
    TaskGrid,
    checked_grid,
    run_grid,
    write_cell,
)
from dcsc_torchrl.recipes.machines import machine_checkpoint, pretrained_machine
from dcsc_torchrl.recipes.options import Parser, add_sweep_options
from dcsc_torchrl.recipes.settings import check_names
from dcsc_torchrl.runlog import Progress
from dcsc_torchrl.tasks import TASK_NAMES, get_task


def task_grid(task: str, sweep: DictConfig, overrides: Sequence[str] = (), *, quick: bool) -> TaskGrid:
    """The cells of ``task``: the sweep's presets and seeds, else the protocol config's, each once.

    Checked whole before any cell runs, as ``dcsc run`` checks it
    (:func:`~dcsc_torchrl.recipes.grid.checked_grid`); ``pretrain.out_dir`` is made absolute: the
    cells may run in other processes or nodes.
    """
    return checked_grid(task, quick=quick, overrides=overrides, operators=sweep.operators,
                        seeds=sweep.pretrain_seeds, option="operators")


def _worker_setup() -> None:
    torch.set_num_threads(1)  # one CPU per Ray task; the rows do not depend on it (run_cell seeds torch)
    logging.getLogger("torchrl").setLevel(logging.WARNING)


@ray.remote(num_cpus=1)
def ensure_pretrained(task: str, cfg: DictConfig, seed: int, quick: bool) -> str:
    """Ray task: the path of pretraining seed ``seed``'s checkpoint, pretrained (or resumed
    to the end, after an earlier attempt stopped halfway) when short (:func:`pretrained_machine`)."""
    _worker_setup()
    pretrained_machine(get_task(task), cfg, seed, quick=quick)
    return str(machine_checkpoint(get_task(task), cfg, seed))


def _count_attempt(directory: Path) -> int:
    path = directory / "attempts"
    attempts = int(path.read_text()) + 1 if path.exists() else 1
    path.write_text(str(attempts))
    return attempts


@ray.remote(num_cpus=1)
def run_sweep_cell(cell: Cell, cfg: DictConfig, methods: tuple[str, ...], out: str, checkpoint: str) -> dict[str, Any]:
    """Ray task: one cell of the protocol, its rows written (atomically) to its directory."""
    _worker_setup()
    directory = cell.directory(Path(out))
    directory.mkdir(parents=True, exist_ok=True)
    attempts = _count_attempt(directory)
    machine, critic = machine_from_checkpoint(load_checkpoint(checkpoint, task=cell.task, modules=get_task(cell.task).checkpoint_modules),
                                              get_task(cell.task))
    return write_cell(cell, cfg, methods, Path(out), machine, critic,
                      {"attempts": attempts, "host": socket.gethostname(), "pid": os.getpid()})


def _failure(out: Path, cell: Cell, err: Exception) -> dict[str, Any]:
    """The row of ``failed_cells.csv`` for a cell whose retries are spent; the traceback to ``error.txt``."""
    directory = cell.directory(out)
    (directory / "error.txt").write_text(re.sub(r"\x1b\[[0-9;]*m", "", str(err)))  # no terminal colours
    cause = getattr(err, "cause", None) or err  # a RayTaskError carries the task's own exception
    attempts = directory / "attempts"
    return {"task": cell.task, "operator": cell.operator, "pretrain_seed": cell.pretrain_seed, "cell": cell.name,
            "attempts": int(attempts.read_text()) if attempts.exists() else 0,
            "error": f"{type(cause).__name__}: {cause}".splitlines()[0]}


def connect(address: str | None, workers: int) -> bool:
    """Joins the Ray cluster at ``address``, or starts a local instance of ``workers`` CPUs.

    Does nothing when this process is already connected (a notebook, the tests).

    Returns:
        Whether this call connected (and the caller should ``ray.shutdown()``).
    """
    if ray.is_initialized():
        return False
    if address:
        ray.init(address=address)
    else:
        ray.init(num_cpus=workers, include_dashboard=False)
    return True


def ray_executor(*, retries: int, address: str | None, workers: int) -> Executor:
    """An :class:`~dcsc_torchrl.recipes.grid.Executor` running cells as Ray tasks.

    One Ray task per pretraining checkpoint the cells need (:func:`ensure_pretrained`), then
    one per cell, started once its checkpoint is there; Ray re-runs a failing one
    ``retries`` times, and one that keeps failing is reported (``failed_cells.csv``) while
    the others' rows are kept. ``address``: a Ray cluster to join, ``None``: a local instance
    of ``workers`` CPUs (shut down afterwards).
    """

    def execute(out: Path, grids: Sequence[TaskGrid], cells: Sequence[Cell], methods: tuple[str, ...], *,
                quick: bool) -> tuple[list[Cell], list[dict[str, Any]]]:
        started = connect(address, workers)
        try:
            return _run_cells(out, grids, cells, methods, quick=quick, retries=retries)
        finally:
            if started:
                ray.shutdown()

    return execute


def _run_cells(out: Path, grids: Sequence[TaskGrid], cells: Sequence[Cell], methods: tuple[str, ...], *,
               quick: bool, retries: int) -> tuple[list[Cell], list[dict[str, Any]]]:
    cfgs = {grid.task: grid.cfg for grid in grids}
    retry = {"max_retries": retries, "retry_exceptions": True}
    checkpoints = {
        (task, seed): ensure_pretrained.options(**retry).remote(task, cfgs[task], seed, quick)
        for task, seed in dict.fromkeys((cell.task, cell.pretrain_seed) for cell in cells)
    }
    pending: dict[ray.ObjectRef, Cell] = {}
    for cell in cells:
        directory = cell.directory(out)
        directory.mkdir(parents=True, exist_ok=True)
        for stale in ("attempts", "error.txt"):
            (directory / stale).unlink(missing_ok=True)
        ref = run_sweep_cell.options(**retry).remote(cell, cfgs[cell.task], methods, str(out),
                                                     checkpoints[cell.task, cell.pretrain_seed])
        pending[ref] = cell
    ran, failed = [], []
    with Progress(len(pending), "cells", "cell", every=0) as progress:
        while pending:
            [ref], _ = ray.wait(list(pending))
            cell = pending.pop(ref)
            try:
                ray.get(ref)
                ran.append(cell)
            except Exception as err:  # Ray's retries are spent: report it, keep the others
                failed.append(_failure(out, cell, err))
            progress.update()
    return ran, failed


def run_sweep(out: Path, grids: Sequence[TaskGrid], methods: tuple[str, ...] = DEFAULT_METHODS, *, quick: bool = False,
              retries: int = 2, address: str | None = None, workers: int = 2, fresh: bool = False) -> GridResult:
    """Every cell of ``grids`` not done yet, as Ray tasks: :func:`run_grid` with :func:`ray_executor`.

    Args:
        out: the results root (``out/<task>/...``).
        grids: the tasks' cells (:func:`task_grid`).
        methods: the methods every cell runs.
        quick: the tiny setting for pretraining a missing checkpoint.
        retries: Ray re-runs of a failing cell or pretraining.
        address: a Ray cluster to join; ``None`` starts a local instance.
        workers: CPUs of the local instance.
        fresh: delete each task's earlier results first (else a folder of another config is refused).
    """
    return run_grid(out.resolve(), grids, methods, ray_executor(retries=retries, address=address, workers=workers),
                    quick=quick, fresh=fresh)


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], dict[str, list[str]]]:
    """``<task>.key=value`` to that task's protocol config, the rest to the sweep config."""
    sweep: list[str] = []
    tasks: dict[str, list[str]] = {task: [] for task in TASK_NAMES}
    for item in overrides:
        head, _, rest = item.partition(".")
        if head in tasks:
            tasks[head].append(rest)
        else:
            sweep.append(item)
    return sweep, tasks


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line of ``dcsc sweep`` (:func:`dcsc_torchrl.cli.add_sweep_options`)."""
    return add_sweep_options(Parser(description=__doc__.split("\n\n")[0])).parse_args(argv)


def sweep(args: argparse.Namespace) -> GridResult:
    """``dcsc sweep``: the configs checked, every cell not done yet run, every task gathered."""
    sweep_overrides, task_overrides = split_overrides(args.overrides)
    cfg = load_config(SWEEP_CONFIG, sweep_overrides, quick=args.quick)
    check_names("tasks", "task", cfg.tasks, TASK_NAMES)
    methods = tuple(check_names("methods", "method", cfg.methods or DEFAULT_METHODS, METHOD_NAMES))
    grids = [task_grid(task, cfg, task_overrides[task], quick=args.quick) for task in cfg.tasks]
    out = args.out or Path("results/quick" if args.quick else "results")
    result = run_sweep(out, grids, methods, quick=args.quick, retries=cfg.ray.retries,
                       address=args.address or cfg.ray.address, workers=cfg.ray.workers, fresh=args.fresh)
    print(f"{len(result.ran)} cells ran, {len(result.skipped)} were done already, {len(result.failed)} failed; "
          f"results in {result.out}", file=sys.stderr, flush=True)
    return result


def main(argv: Sequence[str] | None = None) -> GridResult:
    return sweep(parse_args(argv))


if __name__ == "__main__":
    main()
