"""Where a cell's time goes, run by run: one full cell of each task, the seconds of every run.

    python bench/bench_cell_runs.py [--tasks lunarlander uav] [--operator expert]

For each task, one cell of the protocol (:func:`dcsc_torchrl.protocol.run_cell`) with the
shipped seed-0 machine, the ``--operator`` preset, every default method and the task's full
settings, one torch thread, as ``dcsc run TASK "pretrain.shipped=true" "pretrain.seeds=[0]"
--operators expert`` runs it. The seconds between one run's start and the next (the cell's
``progress`` lines; the last run ends with the cell) are summed into the runs that learn
nothing (the fixed methods, the constant sweep, the calibration runs), of them the validation
runs, and the runs that learn online (DC-SC in collaboration and validation); the warm-up of the
critic falls to the run before it. Printed: a line per run, then a markdown row per task
(docs/scaling.md, "How far the targets are").
"""

from __future__ import annotations

import argparse
import logging
import time

import torch

from dcsc_torchrl.methods import METHODS, task_methods
from dcsc_torchrl.protocol import run_cell
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.shipped import shipped_machine
from dcsc_torchrl.tasks import TASK_NAMES, get_task


def learns(phase: str, method: str) -> bool:
    """Whether the run of ``method`` in ``phase`` learns online (DC-SC's arbiters)."""
    name = method.split("/")[0]
    return phase == "collaboration" or (phase == "validation" and METHODS[name].kind in ("learned", "frozen",
                                                                                          "pretrained"))


def cell_runs(task_name: str, operator: str) -> tuple[float, list[tuple[str, str, float]]]:
    """One cell's seconds and, per run, ``(phase, method, seconds)``."""
    task = get_task(task_name)
    cfg = task_config(task, ["pretrain.shipped=true", "pretrain.seeds=[0]"])
    machine, critic = shipped_machine(task, cfg.pretrain.get("observes"))
    marks: list[tuple[str, float]] = []
    start = time.perf_counter()
    run_cell(task, task.make_operator(operator), machine, critic, operator_name=operator, pretrain_seed=0,
             methods=task_methods(task), **cell_settings(cfg),
             progress=lambda line: marks.append((line, time.perf_counter())))
    end = time.perf_counter()
    runs = []
    for (line, at), (_, until) in zip(marks, [*marks[1:], ("", end)], strict=True):
        phase, method = line.split(": ", 1)
        runs.append((phase, method.split(" ")[0], until - at))
    return end - start, runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASK_NAMES), choices=TASK_NAMES)
    parser.add_argument("--operator", default="expert")
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    rows = []
    for task in args.tasks:
        seconds, runs = cell_runs(task, args.operator)
        for phase, method, run_seconds in runs:
            print(f"{task:12s} {phase:18s} {method:18s} {'learns' if learns(phase, method) else '':7s} "
                  f"{run_seconds:6.1f} s", flush=True)
        fixed = sum(s for p, m, s in runs if not learns(p, m))
        validation = sum(s for p, m, s in runs if not learns(p, m) and p == "validation")
        learning = sum(s for p, m, s in runs if learns(p, m))
        rows.append(f"| {task} | {seconds:.0f} s | {fixed:.1f} s ({validation:.1f} s) | {learning:.1f} s |")
    print(f"\noperator {args.operator}, the shipped seed-0 machines, one torch thread\n")
    print("| task | cell | runs that learn nothing (of it: validation) | runs that learn online |")
    print("|---|---:|---:|---:|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
