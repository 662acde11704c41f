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
        [--fresh] [key=value ...]

Outputs in ``DIR/<task>/`` (default ``results/<task>/``): ``episodes.csv`` (every episode of
every phase), ``trace.csv`` (every step of scenario 0 for each method, main operator and
first pretraining seed), ``theta.csv`` (every online update of theta), ``calibration.csv`` (one row per cell), ``summary.md`` and
the figures ``fig_*.png``. Each cell writes its rows to ``cells/<operator>-seed<s>/``, its
``cell.json`` last; after every cell the task's tables, summary and figures are gathered
again from the finished cells (:func:`gather`, the one writer of these files, which
``dcsc sweep`` uses too), so the folder never describes two different sets of cells.

Resume: running the same command again skips the cells with a ``cell.json``. The config
the cells ran with is kept in ``run_config.yaml``; a run into a folder whose record differs
(or into an older folder with no record) is refused with the keys that differ, unless
``--fresh`` deletes the old results first. Temporary files of a killed run are removed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pandas as pd
import torch
import yaml
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path, load_checkpoint
from dcsc_torchrl.cli import Parser, add_run_options
from dcsc_torchrl.config import ConfigError, config_diff, load_config, to_plain
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.methods import METHOD_NAMES, check_task_methods, task_methods
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.online import check_online_settings
from dcsc_torchrl.protocol import (
    ArbiterSettings,
    MachineSettings,
    ProtocolSettings,
    Scenarios,
    WarmupSettings,
    run_cell,
)
from dcsc_torchrl.report import write_task_figures, write_task_summary
from dcsc_torchrl.runlog import Progress
from dcsc_torchrl.tasks import TASK_NAMES, Task, get_task
from dcsc_torchrl.transforms import HumanConfidenceTransform

RECIPES = Path(__file__).parent
TABLES = ("episodes", "trace", "theta", "calibration")
RUN_RECORD = "run_config.yaml"
OUTPUTS = (*(f"{name}.csv" for name in TABLES), "summary.md", "failed_cells.csv", "cells", "fig_*.png")
"""What a run writes in ``<out>/<task>/`` (removed by ``--fresh``, with :data:`RUN_RECORD`)."""


def task_config(task: Task, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """The shared-control config of ``task`` (its yaml over ``shared_control.yaml``), checked:
    the yaml's keys and types (:func:`~dcsc_torchrl.config.load_config`), then every group's
    values by the object that will use them (:func:`cell_settings`)."""
    cfg = load_config(RECIPES / task.config, overrides, quick=quick)
    cell_settings(cfg)
    return cfg


def _human_settings(**group: Any) -> dict[str, Any]:
    """:class:`HumanConfidenceTransform`'s keywords, its ranges checked (Eqs. 6-9: ``K > 0``, ...)."""
    HumanConfidenceTransform(**group)
    return group


def _online_settings(**group: Any) -> dict[str, Any]:
    """:class:`~dcsc_torchrl.online.OnlineLearner`'s keywords, the names it would refuse refused now."""
    check_online_settings(**group)
    return group


SETTINGS: dict[str, Callable[..., Any]] = {
    "human": _human_settings,
    "machine": MachineSettings,
    "arbiter": ArbiterSettings,
    "online": _online_settings,
    "warmup": WarmupSettings,
    "protocol": ProtocolSettings,
    "scenarios": Scenarios.standard,
}
"""The object each config group's keys are the keywords of (``protocol`` also gets the config's seed)."""


def _settings_of(group: str, build: Callable[..., Any], values: Mapping[str, Any], **extra: Any) -> Any:
    """``build(**values)``; a ``ValueError`` in it is a :class:`ConfigError` naming the key (``human.K ...``)."""
    try:
        return build(**values, **extra)
    except ValueError as err:
        text = str(err)
        named = text.split(" ", 1)[0] in values  # the message starts with the parameter's name
        raise ConfigError(f"{group}.{text}" if named else text) from None


def cell_settings(cfg: DictConfig) -> dict[str, Any]:
    """:func:`run_cell`'s settings from the config's groups, every value checked by the object
    that uses it: a bad one is a :class:`ConfigError` naming its key."""
    return {group: _settings_of(group, build, cfg[group], **({"seed": cfg.seed} if group == "protocol" else {}))
            for group, build in SETTINGS.items()}


def machine_checkpoint(task: Task, cfg: DictConfig, seed: int) -> Path:
    """Where pretraining seed ``seed``'s machine is read: ``{pretrain.out_dir}/seed{seed}/checkpoint.pt``,
    or with ``pretrain.shipped`` the file shipped with the package (seed 0's)."""
    if cfg.pretrain.shipped:
        from dcsc_torchrl.shipped import shipped_path

        return shipped_path(task)
    return checkpoint_path(cfg.pretrain.out_dir, seed)


def pretrained_machine(task: Task, cfg: DictConfig, seed: int, *, quick: bool) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The machine actor and critic of pretraining seed ``seed``; pretrained first when missing
    (by the task's recipe with the ``pretrain.recipe`` settings: e.g. a converged machine).

    With ``pretrain.shipped`` the machine shipped with the package (seed 0) instead.

    A checkpoint short of its episodes that its run did not finish (a pretraining killed
    halfway) is resumed to the end first; one the run finished early (its landing check
    stopped it, or ``train.keep_best`` kept an earlier machine) is loaded as it is.
    """
    import importlib

    path = machine_checkpoint(task, cfg, seed)
    if cfg.pretrain.shipped:
        return machine_from_checkpoint(load_checkpoint(path, task=task.name), task)
    recipe = importlib.import_module(task.pretrain_recipe)
    settings = [*cfg.pretrain.recipe, f"seed={seed}", f"logger.out_dir={path.parent}"]
    if not path.exists():
        print(f"{task.name}: no checkpoint at {path}, pretraining seed {seed} first", file=sys.stderr, flush=True)
        recipe.train(load_config(recipe.CONFIG, settings, quick=quick))
    data = load_checkpoint(path, task=task.name)
    budget = data["config"].get("train", {}).get("episodes")  # a weights-only file has none
    if budget is not None and not data.get("finished", False) and data.get("episodes", budget) < budget:
        print(f"{task.name}: {path} stopped at episode {data['episodes']}, resuming", file=sys.stderr, flush=True)
        recipe.train(load_config(recipe.CONFIG, settings, quick=quick), resume=True)
        data = load_checkpoint(path, task=task.name)
    return machine_from_checkpoint(data, task)


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
    """One task's protocol config and cells, in the order of :func:`cell_grid`."""

    task: str
    cfg: DictConfig
    cells: list[Cell]
    main_operator: str
    main_seed: int


def make_grid(task: str, cfg: DictConfig, presets: Sequence[str], seeds: Sequence[int]) -> TaskGrid:
    """The cells of ``task`` for ``presets`` x ``seeds``; ``pretrain.out_dir`` made absolute.

    An absolute ``pretrain.out_dir`` lets the cells run in other processes or nodes, and
    makes the run's record the same from wherever it was started.
    """
    cfg.pretrain.out_dir = str(Path(cfg.pretrain.out_dir).resolve())
    grid, main_operator = cell_grid(list(presets), [int(s) for s in seeds], cfg.operator.main)
    cells = [Cell(task, preset, seed, trace=traced) for seed, preset, traced in grid]
    return TaskGrid(task, cfg, cells, main_operator, int(seeds[0]))


def check_names(kind: str, names: Sequence[str], known: Sequence[str]) -> list[str]:
    """``names`` when every one is in ``known``; else a :class:`ConfigError` listing the known ones."""
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ConfigError(f"unknown {kind} {', '.join(map(repr, unknown))}: expected one of {', '.join(known)}")
    return list(names)


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
    result = run_cell(task, task.make_operator(cell.operator), machine, critic, operator_name=cell.operator,
                      pretrain_seed=cell.pretrain_seed, methods=methods, trace=cell.trace, **cell_settings(cfg),
                      progress=lambda line: print(f"  {cell.name}: {line}", file=sys.stderr, flush=True))
    calibration = [result.calibration] if result.calibration else []
    for name, rows in zip(TABLES, (result.episodes, result.traces, result.theta, calibration), strict=True):
        if rows:
            write_csv(rows, directory / f"{name}.csv")
        else:
            (directory / f"{name}.csv").unlink(missing_ok=True)
    record = {"task": cell.task, "operator": cell.operator, "pretrain_seed": cell.pretrain_seed,
              "methods": list(methods), "seconds": time.perf_counter() - start,
              "hula_threshold": result.hula_threshold, **(info or {})}
    tmp = directory / "cell.json.tmp"
    tmp.write_text(json.dumps(record, indent=2))
    os.replace(tmp, directory / "cell.json")  # last: the cell counts as done once this exists
    return record


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
    """The done cells' rows into ``out/<task>/``'s CSVs, ``summary.md`` and figures; the failures reported."""
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
        write_task_summary(task_dir, grid.task, grid.main_operator, grid.main_seed)
        if (task_dir / "trace.csv").exists():
            write_task_figures(task_dir, grid.task, grid.main_operator, grid.main_seed)
    else:
        summary.write_text(f"# {grid.task}: no cell finished\n")
    failed_csv = task_dir / "failed_cells.csv"
    if failed:
        write_csv(list(failed), failed_csv)
        summary.write_text(summary.read_text() + failed_section(failed))
    else:
        failed_csv.unlink(missing_ok=True)
    return summary


def run_record(grid: TaskGrid, methods: Sequence[str]) -> dict[str, Any]:
    """What the results of ``grid`` depend on: its config (but ``threads``), methods and cells."""
    config = to_plain(grid.cfg)
    config.pop("threads", None)
    return {"config": config, "methods": list(methods), "cells": [cell.name for cell in grid.cells]}


def prepare_results(task_dir: Path, record: Mapping[str, Any], *, fresh: bool) -> None:
    """Claims ``task_dir`` for a run of ``record``: refuses another config's results unless ``fresh``.

    A grid that keeps the config and methods and adds cells (more pretraining seeds or
    operators) extends the folder: its finished cells stay, the new ones run. ``fresh``
    removes the earlier run's outputs (:data:`OUTPUTS`). The temporary files of a killed run
    are removed in any case; the record is written to :data:`RUN_RECORD`.

    Raises:
        ConfigError: ``task_dir`` holds results of another config, or of a run that kept no record.
    """
    record_path = task_dir / RUN_RECORD
    old_outputs = [path for pattern in OUTPUTS for path in task_dir.glob(pattern)]
    if fresh:
        for path in old_outputs:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        record_path.unlink(missing_ok=True)
    elif record_path.exists():
        old = yaml.safe_load(record_path.read_text()) or {}
        new = json.loads(json.dumps(record))
        if set(old.get("cells", [])) <= set(new["cells"]):
            old["cells"] = new["cells"]  # a grown grid: the cells done stay valid
        changed = config_diff(old, new)
        if changed:
            more = f"; and {len(changed) - 5} more" if len(changed) > 5 else ""
            raise ConfigError(f"{task_dir} holds results of another config ({'; '.join(changed[:5])}{more}): "
                              "pass --fresh to replace them, or choose another --out")
    elif old_outputs:
        raise ConfigError(f"{task_dir} holds results of an earlier run with no {RUN_RECORD}: pass --fresh to "
                          "replace them, or choose another --out")
    for tmp in [*task_dir.glob("*.tmp"), *task_dir.glob("cells/*/*.tmp")]:
        tmp.unlink(missing_ok=True)
    task_dir.mkdir(parents=True, exist_ok=True)
    tmp = record_path.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump(json.loads(json.dumps(record)), sort_keys=False))
    os.replace(tmp, record_path)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line of ``dcsc run`` (the same options, :func:`dcsc_torchrl.cli.add_run_options`)."""
    parser = Parser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task", choices=TASK_NAMES, help="the task")
    return add_run_options(parser).parse_args(argv)


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
    """The one driver of the grid: claims each task's folder, runs the cells not done yet with
    ``executor`` (:func:`local_executor`, or ``dcsc sweep``'s Ray tasks), then gathers every
    task's outputs (:func:`gather`, the one writer), the failures reported."""
    for grid in grids:
        prepare_results(out / grid.task, run_record(grid, methods), fresh=fresh)
    cells = [cell for grid in grids for cell in grid.cells]
    todo = [cell for cell in cells if not cell.done(out)]
    ran, failed = executor(out, grids, todo, methods, quick=quick) if todo else ([], [])
    for grid in grids:
        gather(out, grid, [row for row in failed if row["task"] == grid.task])
    return GridResult(out, ran, [cell for cell in cells if cell not in todo], failed)


def checked_grid(task_name: str, *, quick: bool = False, overrides: Sequence[str] = (),
                 operators: Sequence[str] | None = None) -> TaskGrid:
    """The cells of ``task_name`` (every operator preset, or ``operators``, x every pretraining seed).

    Everything named (config keys, operator presets, the checkpoints there are) is checked
    here, before any cell runs: a typo or a broken checkpoint is answered at once.
    """
    task = get_task(task_name)
    cfg = task_config(task, overrides, quick=quick)
    presets = check_names("operator preset", list(operators or cfg.operator.presets), list(PRESETS))
    if cfg.pretrain.shipped and list(cfg.pretrain.seeds) != [0]:
        raise ConfigError(f"pretrain.shipped=true: only pretraining seed 0 ships, but pretrain.seeds is "
                          f"{list(cfg.pretrain.seeds)}: add pretrain.seeds=[0]")
    for seed in cfg.pretrain.seeds:
        if not cfg.pretrain.shipped and checkpoint_path(cfg.pretrain.out_dir, seed).exists():
            load_checkpoint(checkpoint_path(cfg.pretrain.out_dir, seed), task=task.name)  # a broken one: refused now
    return make_grid(task.name, cfg, presets, list(cfg.pretrain.seeds))


def run_task(task_name: str, *, out: Path = Path("results"), quick: bool = False, overrides: Sequence[str] = (),
             methods: Sequence[str] | None = None, operators: Sequence[str] | None = None,
             fresh: bool = False) -> Path:
    """Every cell of ``task_name`` not done yet, one after another (:func:`run_grid` with the
    :func:`local_executor`); returns ``out/<task>``.

    Everything named (config keys, methods, operator presets, the results folder's
    earlier config, the checkpoints there are) is checked before a machine is loaded or pretrained.
    """
    if methods:  # named ones must be the task's (the default, every method, runs those the task defines)
        try:
            check_task_methods(get_task(task_name), check_names("method", methods, METHOD_NAMES))
        except ValueError as err:
            raise ConfigError(str(err)) from None
    methods = tuple(methods or METHOD_NAMES)
    grid = checked_grid(task_name, quick=quick, overrides=overrides, operators=operators)
    torch.set_num_threads(grid.cfg.threads)
    run_grid(Path(out), [grid], methods, local_executor, quick=quick, fresh=fresh)
    task_dir = Path(out) / grid.task
    print(f"results in {task_dir}", file=sys.stderr, flush=True)
    return task_dir


def run(args: argparse.Namespace) -> Path:
    """``dcsc run``: :func:`run_task` with the command line's options."""
    return run_task(args.task, out=args.out, quick=args.quick, overrides=args.overrides, methods=args.methods,
                    operators=args.operators, fresh=args.fresh)


def main(argv: Sequence[str] | None = None) -> Path:
    return run(parse_args(argv))


if __name__ == "__main__":
    main()
