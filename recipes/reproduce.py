"""``make reproduce``: both experiments end to end, then one report (docs/architecture.md).

    dcsc reproduce [--quick] [--out DIR] [--fresh] [--workers N] [key=value ...]

Pretrains every machine that has no checkpoint yet (A2C and DDPG, every pretraining
seed), runs the shared-control protocol of both tasks for every operator preset, and
writes ``DIR/<task>/`` (CSVs, summary, figures) and ``DIR/summary.md`` gathering both tasks
with the wall time. ``--quick`` runs the same code paths at a tiny scale into
``results/quick``. ``--workers N`` (default 2, this project's machine) runs N
pretrainings or cells at a time as Ray tasks on a local instance (``dcsc sweep``'s
executor); ``--workers 1`` runs them one after another in this process, without Ray. The
rows are the same either way (each cell seeds its own streams).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import torch
import yaml

from dcsc_torchrl.config import UsageError, writable_folder
from dcsc_torchrl.methods import DEFAULT_METHODS
from dcsc_torchrl.recipes.executors import executor
from dcsc_torchrl.recipes.folder import RUN_RECORD
from dcsc_torchrl.recipes.grid import checked_grid, run_grid
from dcsc_torchrl.recipes.options import Parser, add_reproduce_options
from dcsc_torchrl.report import CELL_COLUMNS, read_table, write_task_figures, write_task_summary
from dcsc_torchrl.runlog import write_atomic
from dcsc_torchrl.tasks import TASK_NAMES, get_task


def _traced_cell(task_dir: Path) -> tuple[str, int]:
    """The operator and pretraining seed whose scenario 0 was traced (the paper's setting)."""
    trace = read_table(task_dir / "trace.csv", CELL_COLUMNS)
    if trace.empty:
        raise UsageError(f"{task_dir / 'trace.csv'} has no rows: the traced cell did not finish")
    return str(trace["operator"].iloc[0]), int(trace["pretrain_seed"].iloc[0])


def _quick(task_dir: Path) -> bool:
    """Whether the run's record says it was a ``--quick`` run (an older record does not say: no)."""
    record = task_dir / RUN_RECORD
    return bool(record.exists() and (yaml.safe_load(record.read_text()) or {}).get("quick", False))


def report(results: Path, wall_seconds: float | None = None) -> Path:
    """Redraws every task's summary and figures from its CSVs, and the joint ``summary.md``.

    Raises:
        UsageError: ``results`` holds no task's ``episodes.csv``, or a table is not whole
            (:func:`~dcsc_torchrl.report.read_table`).
    """
    tasks = [task for task in TASK_NAMES if (results / task / "episodes.csv").is_file()]
    if not tasks:
        where = " or ".join(f"{task}/episodes.csv" for task in TASK_NAMES)
        raise UsageError(f"--out {results}: no results there (no {where}); run dcsc run or dcsc reproduce first")
    writable_folder(results)
    parts = ["# DC-SC reproduction: results\n"]
    if wall_seconds is not None:
        parts.append(f"Wall time of the whole run: {wall_seconds / 60:.1f} min.\n")
    for task in tasks:
        task_dir = results / task
        operator, seed = _traced_cell(task_dir)
        summary = write_task_summary(task_dir, get_task(task), operator, seed, quick=_quick(task_dir))
        write_task_figures(task_dir, get_task(task), operator, seed)
        body = summary.read_text().replace("# ", "## ", 1).replace("\n## ", "\n### ")
        parts.append(body)
    path = (results / "summary.md").resolve()
    text = "\n".join(parts)
    write_atomic(path, lambda f: f.write(text))
    return path


def reproduce(results: Path | None = None, *, quick: bool = False, overrides: Sequence[str] = (),
              fresh: bool = False, workers: int = 1) -> Path:
    """Pretraining (when missing), both protocols, the report; returns ``summary.md``.

    Cells finished by an earlier run of the same config are kept (``dcsc run``'s resume);
    ``fresh`` deletes an earlier run's results first. ``overrides`` go to both tasks'
    protocol configs; ``workers``: pretrainings and cells at a time (:func:`executor`).
    """
    results = (results or Path("results/quick" if quick else "results")).resolve()  # Ray tasks' cwd may differ
    run = executor(workers)
    grids = [checked_grid(task, quick=quick, overrides=overrides) for task in TASK_NAMES]
    start = time.perf_counter()
    torch.set_num_threads(grids[0].cfg.threads)
    run_grid(results, grids, DEFAULT_METHODS, run, quick=quick, fresh=fresh)
    return report(results, time.perf_counter() - start)


def main(argv: Sequence[str] | None = None) -> Path:
    args = add_reproduce_options(Parser(description=__doc__.split("\n\n")[0])).parse_args(argv)
    return reproduce(args.out, quick=args.quick, overrides=args.overrides, fresh=args.fresh, workers=args.workers)


if __name__ == "__main__":
    main()
