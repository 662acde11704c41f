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
import contextlib
import fcntl
import json
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pandas as pd
import torch
import yaml
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path, load_checkpoint
from dcsc_torchrl.cli import Parser, add_run_options
from dcsc_torchrl.config import (
    ConfigError,
    UsageError,
    config_diff,
    distinct,
    load_config,
    to_plain,
    warn,
    writable_folder,
)
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
from dcsc_torchrl.runlog import Progress, write_atomic
from dcsc_torchrl.tasks import TASK_NAMES, Task, get_task
from dcsc_torchrl.transforms import HumanConfidenceTransform

RECIPES = Path(__file__).parent
TABLES = ("episodes", "trace", "theta", "calibration")
RUN_RECORD = "run_config.yaml"
OUTPUTS = (*(f"{name}.csv" for name in TABLES), "summary.md", "failed_cells.csv", "cells", "fig_*.png")
"""What a run writes in ``<out>/<task>/`` (removed by ``--fresh``, with :data:`RUN_RECORD`)."""


def task_config(task: Task, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """The shared-control config of ``task`` (its yaml over ``shared_control.yaml``), checked whole:
    the yaml's keys, types and ranges (:func:`~dcsc_torchrl.config.load_config`), every group's
    values by the object that will use them (:func:`cell_settings`), the validation groups, the
    operator presets named and the pretraining recipe's settings (:func:`pretrain_config`)."""
    cfg = load_config(RECIPES / task.config, overrides, quick=quick)
    cell_settings(cfg)
    check_groups(cfg)
    check_names("operator.presets", "operator preset", cfg.operator.presets, list(PRESETS))
    check_names("operator.main", "operator preset", [cfg.operator.main], list(PRESETS))
    if not cfg.pretrain.shipped:
        pretrain_config(task, cfg, cfg.pretrain.seeds[0], quick=quick)
    return cfg


def check_groups(cfg: DictConfig) -> None:
    """Refuses a ``protocol.group_size`` that does not split the validation scenarios into equal groups."""
    size, count = cfg.protocol.group_size, cfg.scenarios.validation_scenarios
    if count % size:
        raise ConfigError(f"protocol.group_size: expected a divisor of scenarios.validation_scenarios ({count}), "
                          f"got {size} (the groups would differ in size)")


def pretrain_config(task: Task, cfg: DictConfig, seed: int, *, quick: bool) -> DictConfig:
    """The config that pretrains seed ``seed``'s machine of ``cfg``: the task's pretraining yaml with
    ``pretrain.recipe``'s settings, written to ``{pretrain.out_dir}/seed{seed}/``.

    Raises:
        ConfigError: a setting of ``pretrain.recipe`` is refused by the pretraining yaml (named).
    """
    yaml_path = RECIPES / f"{task.pretrain_recipe.rsplit('.', 1)[1]}.yaml"
    out_dir = checkpoint_path(cfg.pretrain.out_dir, seed).parent
    settings = [*cfg.pretrain.recipe, f"seed={seed}", f"logger.out_dir={out_dir}"]
    try:
        return load_config(yaml_path, settings, quick=quick)
    except ConfigError as err:
        raise ConfigError(f"pretrain.recipe: {err}") from None


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
        return machine_from_checkpoint(load_checkpoint(path, task=task.name, machine=True), task)
    recipe = importlib.import_module(task.pretrain_recipe)
    if not path.exists():
        print(f"{task.name}: no checkpoint at {path}, pretraining seed {seed} first", file=sys.stderr, flush=True)
        recipe.train(pretrain_config(task, cfg, seed, quick=quick))
    data = load_checkpoint(path, task=task.name, machine=True)
    budget = data["config"].get("train", {}).get("episodes")  # a weights-only file has none
    if budget is not None and not data.get("finished", False) and data.get("episodes", budget) < budget:
        print(f"{task.name}: {path} stopped at episode {data['episodes']}, resuming", file=sys.stderr, flush=True)
        recipe.train(pretrain_config(task, cfg, seed, quick=quick), resume=True)
        data = load_checkpoint(path, task=task.name, machine=True)
    return machine_from_checkpoint(data, task)


def write_csv(rows: list[dict], path: Path) -> None:
    """All rows so far, written atomically (:func:`~dcsc_torchrl.runlog.write_atomic`: a full disk
    leaves the file as it was, and an error naming it)."""
    write_atomic(path, lambda f: pd.DataFrame(rows).to_csv(f, index=False))


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
    made absolute, so that the cells can run in other processes or nodes."""
    given = str(cfg.pretrain.out_dir)
    cfg.pretrain.out_dir = str(Path(given).resolve())
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    grid, main_operator = cell_grid(list(dict.fromkeys(presets)), seeds, cfg.operator.main)
    cells = [Cell(task, preset, seed, trace=traced) for seed, preset, traced in grid]
    return TaskGrid(task, cfg, cells, main_operator, seeds[0], given, quick)


def check_names(key: str, kind: str, names: Sequence[str], known: Sequence[str]) -> list[str]:
    """``names`` when every one is in ``known``; else a :class:`ConfigError` naming ``key`` and listing the known ones."""
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ConfigError(f"{key}: unknown {kind} {', '.join(map(repr, unknown))}: expected one of "
                          f"{', '.join(known)}")
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
    write_atomic(directory / "cell.json", lambda f: f.write(json.dumps(record, indent=2)))  # last: the cell is done
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
        write_task_summary(task_dir, grid.task, grid.main_operator, grid.main_seed, quick=grid.quick)
        if (task_dir / "trace.csv").exists():
            write_task_figures(task_dir, grid.task, grid.main_operator, grid.main_seed)
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


def run_record(grid: TaskGrid, methods: Sequence[str]) -> dict[str, Any]:
    """What the results of ``grid`` depend on: its config (but ``threads``; ``pretrain.out_dir`` as
    the command gave it), methods and cells; and whether it is a ``--quick`` run (for the summary)."""
    config = to_plain(grid.cfg)
    config.pop("threads", None)
    config["pretrain"]["out_dir"] = grid.pretrain_out_dir
    return {"config": config, "methods": list(methods), "cells": [cell.name for cell in grid.cells],
            "quick": grid.quick}


def _comparable(record: Mapping[str, Any]) -> dict[str, Any]:
    """``record`` as :func:`prepare_results` compares it: ``pretrain.out_dir`` resolved from the
    current folder (the same command from another folder, or an older record's absolute path,
    is the same run), without the ``quick`` flag (it only words the summary)."""
    record = json.loads(json.dumps(record))
    record.pop("quick", None)
    pretrain = record.get("config", {}).get("pretrain", {})
    if "out_dir" in pretrain:
        pretrain["out_dir"] = str(Path(pretrain["out_dir"]).resolve())
    return record


@contextlib.contextmanager
def folder_lock(task_dir: Path) -> Iterator[Path]:
    """Holds ``task_dir/.lock`` (``flock``) while a run writes ``task_dir``; released on exit.

    The kernel releases the lock of a process that dies, so a killed run never blocks the
    next one; the file stays (removing it would race with a run taking it).

    Raises:
        UsageError: another run holds the folder (its pid named).
    """
    task_dir.mkdir(parents=True, exist_ok=True)
    path = task_dir / ".lock"
    with open(path, "a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "unknown"
            raise UsageError(f"{task_dir} is in use by another dcsc run (pid {holder}): wait for it to end, "
                             "or choose another --out") from None
        lock.seek(0)
        lock.truncate()
        lock.write(f"{os.getpid()}\n")
        lock.flush()
        try:
            yield path
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def prepare_results(task_dir: Path, record: Mapping[str, Any], *, fresh: bool) -> None:
    """Claims ``task_dir`` for a run of ``record``: refuses another config's results unless ``fresh``.

    A grid that keeps the config and methods and adds cells (more pretraining seeds or
    operators) extends the folder: its finished cells stay, the new ones run. ``fresh``
    removes the earlier run's outputs (:data:`OUTPUTS`), and so does another config when no
    cell of the earlier one finished (nothing is lost: a run that stopped in its first cell
    does not hold the folder). The temporary files of a killed run are removed in any case;
    the record is written to :data:`RUN_RECORD`.

    Raises:
        ConfigError: ``task_dir`` holds results of another config, or of a run that kept no record.
    """
    record_path = task_dir / RUN_RECORD
    old_outputs = [path for pattern in OUTPUTS for path in task_dir.glob(pattern)]
    if not fresh and record_path.exists():
        old = _comparable(yaml.safe_load(record_path.read_text()) or {})
        new = _comparable(record)
        if set(old.get("cells", [])) <= set(new["cells"]):
            old["cells"] = new["cells"]  # a grown grid: the cells done stay valid
        changed = config_diff(old, new)
        if changed and not list(task_dir.glob("cells/*/cell.json")):
            warn(f"{task_dir}: no cell of its earlier config ({changed[0]}) finished; starting over with this one")
            fresh = True
        elif changed:
            more = f"; and {len(changed) - 5} more" if len(changed) > 5 else ""
            raise ConfigError(f"{task_dir} holds results of another config ({'; '.join(changed[:5])}{more}): "
                              "pass --fresh to replace them, or choose another --out")
    elif old_outputs and not fresh:
        raise ConfigError(f"{task_dir} holds results of an earlier run with no {RUN_RECORD}: pass --fresh to "
                          "replace them, or choose another --out")
    if fresh:
        for path in old_outputs:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        record_path.unlink(missing_ok=True)
    for tmp in [*task_dir.glob("*.tmp"), *task_dir.glob("cells/*/*.tmp")]:
        tmp.unlink(missing_ok=True)
    task_dir.mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(json.loads(json.dumps(record)), sort_keys=False)
    write_atomic(record_path, lambda f: f.write(text))


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
    """The one driver of the grid: checks each task's folder can be written, locks it
    (:func:`folder_lock`: one run at a time) and claims it (:func:`prepare_results`), runs the
    cells not done yet with ``executor`` (:func:`local_executor`, or ``dcsc sweep``'s Ray
    tasks), then gathers every task's outputs (:func:`gather`, the one writer), the failures
    reported."""
    for grid in grids:
        writable_folder(out / grid.task)
    with contextlib.ExitStack() as locks:
        for grid in grids:
            locks.enter_context(folder_lock(out / grid.task))
        for grid in grids:
            prepare_results(out / grid.task, run_record(grid, methods), fresh=fresh)
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
            load_checkpoint(checkpoint_path(cfg.pretrain.out_dir, seed), task=task.name, machine=True)
    return make_grid(task.name, cfg, presets, seeds, quick=quick)


def run_task(task_name: str, *, out: Path = Path("results"), quick: bool = False, overrides: Sequence[str] = (),
             methods: Sequence[str] | None = None, operators: Sequence[str] | None = None,
             fresh: bool = False) -> Path:
    """Every cell of ``task_name`` not done yet, one after another (:func:`run_grid` with the
    :func:`local_executor`); returns ``out/<task>``.

    Everything named (config keys, methods, operator presets, the results folder's
    earlier config, the checkpoints there are) is checked before a machine is loaded or pretrained.
    """
    if methods:  # named ones must be the task's (the default, every method, runs those the task defines)
        methods = check_names("--methods", "method", distinct("--methods", methods), METHOD_NAMES)
        try:
            check_task_methods(get_task(task_name), methods)
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
