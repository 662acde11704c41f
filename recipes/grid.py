"""The grid driver: a task's cells (operator preset x pretraining seed), each run by the
protocol (:func:`dcsc_torchrl.protocol.run_cell`) and written to its own folder, then
gathered into the task's tables, summary and figures; the local executor, which runs the
cells one after another (``dcsc sweep``'s executor runs them as Ray tasks;
:mod:`dcsc_torchrl.recipes.executors` picks one). docs/architecture.md."""

from __future__ import annotations

import contextlib
import hashlib
import json
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pandas as pd
import torch
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path
from dcsc_torchrl.config import (
    ConfigError,
    distinct,
    to_plain,
    writable_folder,
)
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.methods import task_methods
from dcsc_torchrl.networks import machine_fingerprint, machine_from_checkpoint
from dcsc_torchrl.protocol import (
    run_cell,
)
from dcsc_torchrl.recipes.folder import TABLES, folder_lock, prepare_results, write_csv
from dcsc_torchrl.recipes.machines import (
    copilot_for,
    expert_q,
    load_machine_checkpoint,
    machine_checkpoint,
    pretrained_machine,
    state_arbiter_for,
)
from dcsc_torchrl.recipes.settings import cell_settings, check_names, task_config
from dcsc_torchrl.report import write_task_figures, write_task_summary
from dcsc_torchrl.runlog import Progress, write_atomic
from dcsc_torchrl.tasks import get_task


def cell_grid(presets: Sequence[str], seeds: Sequence[int], main: str) -> tuple[list[tuple[int, str, bool]], str]:
    """The protocol's cells in order, ``(pretraining seed, preset, traced)``, and the main operator.

    The main operator is ``main`` when it is among ``presets`` (else the first preset); its
    cell with the first pretraining seed is the one whose scenario 0 is traced (the paper's
    single-human setting of the tables and figures).
    """
    main_operator = main if main in presets else presets[0]
    cells = [(seed, preset, preset == main_operator and seed == seeds[0]) for seed in seeds for preset in presets]
    return cells, main_operator


@dataclass(frozen=True)
class Cell:
    """One cell of the grid; ``trace`` records scenario 0 (main operator, first pretraining seed)."""

    task: str
    operator: str
    pretrain_seed: int
    trace: bool

    @property
    def name(self) -> str:
        return f"{self.operator}-seed{self.pretrain_seed}"

    def directory(self, out: Path) -> Path:
        """The cell's own files: ``out/<task>/cells/<operator>-seed<s>/``."""
        return out / self.task / "cells" / self.name

    def done(self, out: Path) -> bool:
        return (self.directory(out) / "cell.json").exists()


@dataclass
class TaskGrid:
    """One task's protocol config and cells, in the order of :func:`cell_grid`.

    ``cfg.pretrain.out_dir`` is absolute (the cells may run in other processes or nodes);
    ``pretrain_out_dir`` is as the command gave it, what the run's record keeps.
    """

    task: str
    cfg: DictConfig
    cells: list[Cell]
    main_operator: str
    main_seed: int
    pretrain_out_dir: str
    quick: bool


def make_grid(task: str, cfg: DictConfig, presets: Sequence[str], seeds: Sequence[int], *,
              quick: bool = False) -> TaskGrid:
    """The cells of ``task`` for ``presets`` x ``seeds`` (each once, in order); ``pretrain.out_dir``
    (and ``ida.expert``, ``reddy.copilots``, ``state.arbiters``) made absolute, so that the cells can run in other
    processes or nodes."""
    given = str(cfg.pretrain.out_dir)
    cfg.pretrain.out_dir = str(Path(given).resolve())
    if cfg.ida.expert is not None:  # read by the cells too
        cfg.ida.expert = str(Path(cfg.ida.expert).resolve())
    if cfg.reddy.copilots is not None:
        cfg.reddy.copilots = [str(Path(path).resolve()) for path in cfg.reddy.copilots]
    if "state" in cfg and cfg.state.arbiters is not None:
        cfg.state.arbiters = [str(Path(path).resolve()) for path in cfg.state.arbiters]
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    grid, main_operator = cell_grid(list(dict.fromkeys(presets)), seeds, cfg.operator.main)
    cells = [Cell(task, preset, seed, trace=traced) for seed, preset, traced in grid]
    return TaskGrid(task, cfg, cells, main_operator, seeds[0], given, quick)


def write_cell(cell: Cell, cfg: DictConfig, methods: tuple[str, ...], out: Path, machine: torch.nn.Module,
               critic: torch.nn.Module, info: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Runs one cell (``run_cell``) and writes its rows to its directory, ``cell.json`` last (atomic files).

    Of ``methods`` the cell runs those its task defines (:func:`~dcsc_torchrl.methods.task_methods`:
    the UAV has no ``rule``)."""
    directory = cell.directory(out)
    directory.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    task = get_task(cell.task)
    methods = task_methods(task, methods)
    expert = expert_q(task, cfg) if "ida_expert" in methods else None
    copilot = copilot_for(task, cfg, cell.operator) if "reddy" in methods else None
    state = state_arbiter_for(task, cfg, cell.operator, machine) if "dcsc_state" in methods else None
    result = run_cell(task, task.make_operator(cell.operator), machine, critic, operator_name=cell.operator,
                      pretrain_seed=cell.pretrain_seed, methods=methods, trace=cell.trace, expert_q=expert,
                      copilot=copilot, state_arbiter=state,
                      **cell_settings(cfg),
                      progress=lambda line: print(f"  {cell.name}: {line}", file=sys.stderr, flush=True))
    calibration = [result.calibration] if result.calibration else []
    for name, rows in zip(TABLES, (result.episodes, result.traces, result.theta, calibration), strict=True):
        if rows:
            write_csv(rows, directory / f"{name}.csv")
        else:
            (directory / f"{name}.csv").unlink(missing_ok=True)
    record = {"task": cell.task, "operator": cell.operator, "pretrain_seed": cell.pretrain_seed,
              "machine": machine_fingerprint(machine), "methods": list(methods), "seconds": time.perf_counter() - start,
              "hula_threshold": result.hula_threshold, **(info or {})}
    write_atomic(directory / "cell.json", lambda f: f.write(json.dumps(record, indent=2)))  # last: the cell is done
    return record


def check_one_machine_per_seed(out: Path, grid: TaskGrid, *, against_checkpoints: bool = True) -> None:
    """Refuses a results folder where the done cells of one pretraining seed ran next to two
    machines, or (``against_checkpoints``) next to another machine than the seed's checkpoint
    holds now, pretrained again since: gathered, one table would mix two machines' rows.

    Each cell's ``cell.json`` records its machine (:func:`machine_fingerprint`); cells written
    before it did are not checked.

    Raises:
        ConfigError: naming the cells, the machines and the checkpoint.
    """
    task = get_task(grid.task)
    for seed in dict.fromkeys(cell.pretrain_seed for cell in grid.cells):
        ran: dict[str, list[str]] = {}  # machine -> the done cells that ran next to it
        for cell in grid.cells:
            if cell.pretrain_seed == seed and cell.done(out):
                machine = json.loads((cell.directory(out) / "cell.json").read_text()).get("machine")
                if machine is not None:
                    ran.setdefault(machine, []).append(cell.name)
        path = machine_checkpoint(task, grid.cfg, seed)
        cells = "; ".join(f"{', '.join(names)} next to machine {machine}" for machine, names in ran.items())
        if len(ran) > 1:
            raise ConfigError(f"{out / grid.task}: the cells of pretraining seed {seed} ran next to different "
                              f"machines ({cells}): pass --fresh to run them all next to {path}")
        if ran and against_checkpoints and path.exists():
            now = machine_fingerprint(machine_from_checkpoint(load_machine_checkpoint(task, grid.cfg, path), task)[0])
            if now not in ran:
                raise ConfigError(f"{out / grid.task}: {cells}, but {path} now holds machine {now} (pretrained "
                                  "again since?): pass --fresh to run every cell next to it, or choose another --out")


def failed_section(failed: Sequence[dict[str, Any]]) -> str:
    """The "Failed cells" section appended to a task's ``summary.md``."""
    lines = ["", "## Failed cells", "",
             f"{len(failed)} cell(s) failed after every retry (tracebacks in `cells/<cell>/error.txt`):", "",
             "| cell | attempts | error |", "|---|---|---|"]
    for row in failed:
        error = row["error"].replace("|", "\\|")
        lines.append(f"| {row['cell']} | {row['attempts']} | {error} |")
    return "\n".join(lines) + "\n"


def gather(out: Path, grid: TaskGrid, failed: Sequence[dict[str, Any]] = ()) -> Path:
    """The done cells' rows into ``out/<task>/``'s CSVs, ``summary.md`` and figures; the failures reported.

    Refused (:func:`check_one_machine_per_seed`) when the cells of a pretraining seed ran next to
    two machines: a missing checkpoint pretrained again may be another machine (another host)."""
    check_one_machine_per_seed(out, grid, against_checkpoints=False)
    task_dir = out / grid.task
    task_dir.mkdir(parents=True, exist_ok=True)
    done = [cell for cell in grid.cells if cell.done(out)]
    for name in TABLES:
        paths = [path for cell in done if (path := cell.directory(out) / f"{name}.csv").exists()]
        if paths:
            # read as text: every value passes through exactly as its cell wrote it
            frame = pd.concat([pd.read_csv(path, dtype=str, keep_default_na=False) for path in paths],
                              ignore_index=True)
            write_csv(frame.to_dict("records"), task_dir / f"{name}.csv")
        else:
            (task_dir / f"{name}.csv").unlink(missing_ok=True)
    summary = task_dir / "summary.md"
    if done:
        write_task_summary(task_dir, get_task(grid.task), grid.main_operator, grid.main_seed, quick=grid.quick)
        if (task_dir / "trace.csv").exists():
            write_task_figures(task_dir, get_task(grid.task), grid.main_operator, grid.main_seed)
    else:
        write_atomic(summary, lambda f: f.write(f"# {grid.task}: no cell finished\n"))
    failed_csv = task_dir / "failed_cells.csv"
    if failed:
        write_csv(list(failed), failed_csv)
        text = summary.read_text() + failed_section(failed)
        write_atomic(summary, lambda f: f.write(text))
    else:
        failed_csv.unlink(missing_ok=True)
    return summary


ASSISTANT_FILES = {"ida_expert": ("ida", "expert"), "reddy": ("reddy", "copilots"), "dcsc_state": ("state", "arbiters")}
"""The config key naming the files each method reads beside the machine (an expert's Q, copilots, arbiters)."""


def assistant_files(grid: TaskGrid, methods: Sequence[str]) -> dict[str, str]:
    """A hash of each file the grid's methods read beside the machine (:data:`ASSISTANT_FILES`),
    by path: the files must exist (:func:`run_grid` loads them first)."""
    paths: list[str] = []
    for method in task_methods(get_task(grid.task), methods):
        if method in ASSISTANT_FILES:
            group, key = ASSISTANT_FILES[method]
            named = grid.cfg[group][key]
            paths += [named] if isinstance(named, str) else list(named)
    return {path: hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16] for path in paths}


def run_record(grid: TaskGrid, methods: Sequence[str]) -> dict[str, Any]:
    """What the results of ``grid`` depend on: its config (but ``threads``; ``pretrain.out_dir`` as
    the command gave it), methods and cells, the files its methods read beside the machines
    (:func:`assistant_files`: a copilot trained again is another config); and whether it is a
    ``--quick`` run (for the summary)."""
    config = to_plain(grid.cfg)
    config.pop("threads", None)
    config["pretrain"]["out_dir"] = grid.pretrain_out_dir
    return {"config": config, "methods": list(methods), "cells": [cell.name for cell in grid.cells],
            "files": assistant_files(grid, methods), "quick": grid.quick}


@dataclass
class GridResult:
    """What a run of the grid did: the cells it ran, those done before (skipped), those that failed."""

    out: Path
    ran: list[Cell]
    skipped: list[Cell]
    failed: list[dict[str, Any]]


class Executor(Protocol):
    """Runs the cells of a grid not done yet; returns those it ran and the failures (``{cell, task, ...}`` rows)."""

    def __call__(self, out: Path, grids: Sequence[TaskGrid], cells: Sequence[Cell], methods: tuple[str, ...], *,
                 quick: bool) -> tuple[list[Cell], list[dict[str, Any]]]: ...


def local_executor(out: Path, grids: Sequence[TaskGrid], cells: Sequence[Cell], methods: tuple[str, ...], *,
                   quick: bool) -> tuple[list[Cell], list[dict[str, Any]]]:
    """The cells one after another in this process, the task's outputs gathered after each
    but its last (:func:`run_grid` gathers every task once the executor returns).

    A cell that raises stops the run (its folder has no ``cell.json``: the next run redoes
    it); ``dcsc sweep``'s Ray executor retries and reports instead.
    """
    by_task = {grid.task: grid for grid in grids}
    last = {cell.task: cell for cell in cells}
    ran: list[Cell] = []
    with Progress(len(cells), "cells", "cell", every=0) as progress:
        for cell in cells:
            grid = by_task[cell.task]
            machine, critic = pretrained_machine(get_task(cell.task), grid.cfg, cell.pretrain_seed, quick=quick)
            write_cell(cell, grid.cfg, methods, out, machine, critic)
            if cell is not last[cell.task]:
                gather(out, grid)
            ran.append(cell)
            progress.set_postfix(last=cell.name)
            progress.update()
    return ran, []


def run_grid(out: Path, grids: Sequence[TaskGrid], methods: tuple[str, ...], executor: Executor, *,
             quick: bool = False, fresh: bool = False) -> GridResult:
    """The one driver of the grid: checks each task's folder can be written, locks it
    (:func:`folder_lock`: one run at a time) and claims it (:func:`prepare_results`), runs the
    cells not done yet with ``executor`` (:func:`local_executor`, or ``dcsc sweep``'s Ray
    tasks), then gathers every task's outputs (:func:`gather`, the one writer), the failures
    reported. A grid that runs ``ida_expert`` loads its expert first (:func:`expert_q`), one that
    runs ``reddy`` each cell's copilot (:func:`copilot_for`), one that runs ``dcsc_state`` each
    cell's pretrained arbiter (:func:`state_arbiter_for`; its machine is checked in the cell): a
    missing one is refused before any cell runs, as is a folder whose done cells ran next to
    another machine than their seed's checkpoint holds now (:func:`check_one_machine_per_seed`)."""
    for grid in grids:
        writable_folder(out / grid.task)
        grid_methods = task_methods(get_task(grid.task), methods)
        if "ida_expert" in grid_methods:
            expert_q(get_task(grid.task), grid.cfg)
        if "reddy" in grid_methods:
            for cell in grid.cells:
                copilot_for(get_task(grid.task), grid.cfg, cell.operator)
        if "dcsc_state" in grid_methods:
            for cell in grid.cells:
                state_arbiter_for(get_task(grid.task), grid.cfg, cell.operator)
    with contextlib.ExitStack() as locks:
        for grid in grids:
            locks.enter_context(folder_lock(out / grid.task))
        for grid in grids:
            prepare_results(out / grid.task, run_record(grid, methods), fresh=fresh)
            check_one_machine_per_seed(out, grid)
        cells = [cell for grid in grids for cell in grid.cells]
        todo = [cell for cell in cells if not cell.done(out)]
        ran, failed = executor(out, grids, todo, methods, quick=quick) if todo else ([], [])
        for grid in grids:
            gather(out, grid, [row for row in failed if row["task"] == grid.task])
    return GridResult(out, ran, [cell for cell in cells if cell not in todo], failed)


def checked_grid(task_name: str, *, quick: bool = False, overrides: Sequence[str] = (),
                 operators: Sequence[str] | None = None, seeds: Sequence[int] | None = None,
                 option: str = "--operators") -> TaskGrid:
    """The cells of ``task_name``: every operator preset (or ``operators``, given by ``option``)
    x every pretraining seed (or ``seeds``), each once (a repeat is dropped with a warning).

    The whole config (:func:`task_config`), the presets named and the checkpoints there are
    are checked here, before any cell runs: a typo or a broken checkpoint is answered at once.
    """
    task = get_task(task_name)
    cfg = task_config(task, overrides, quick=quick)
    presets = list(cfg.operator.presets)
    if operators:
        presets = check_names(option, "operator preset", distinct(option, operators), list(PRESETS))
    seeds = list(cfg.pretrain.seeds) if seeds is None else list(seeds)
    if cfg.pretrain.shipped and seeds != [0]:
        raise ConfigError(f"pretrain.shipped=true: only pretraining seed 0 ships, but the seeds are {seeds}: "
                          "add pretrain.seeds=[0]")
    for seed in seeds:
        if not cfg.pretrain.shipped and checkpoint_path(cfg.pretrain.out_dir, seed).exists():
            # a broken or outdated one: refused now
            load_machine_checkpoint(task, cfg, checkpoint_path(cfg.pretrain.out_dir, seed))
    return make_grid(task.name, cfg, presets, seeds, quick=quick)
