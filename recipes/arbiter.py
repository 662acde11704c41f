"""``dcsc arbiter TASK``: the state-dependent arbiter pretrained in simulation, next to a cell's machine.

The machine is the one ``dcsc run`` would fly with (``pretrain.*`` of the task's protocol
yaml: the first of ``pretrain.seeds``, pretrained first when missing, or the shipped one);
the arbiter and its critic learn against the operators of ``state.pool`` (``state.algorithm``) (:func:`~dcsc_torchrl.arbiter_pretraining.pretrain_state_arbiter`), on
development scenarios from ``state.first_seed``. The file it writes, ``arbiter.pt``, records the
pool and the machine: ``dcsc run ... --methods dcsc_state state.arbiters=[...]`` refuses it next
to an operator of the pool or another machine.

    dcsc arbiter TASK [--quick] [--out DIR] [key=value ...]

Outputs in ``--out`` (default ``runs/arbiter_<task>``): ``arbiter.pt``, ``pretraining.csv``
(one row per run: operator, beta or round, frames, success, mean beta) and
``fig_state_beta.png`` (the pretrained arbiter's beta over the state, on the frames it learned
from last).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig

from dcsc_torchrl.arbiter_pretraining import check_algorithm_for, pretrain_state_arbiter
from dcsc_torchrl.config import to_plain, writable_folder
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.recipes.machines import pretrained_machine
from dcsc_torchrl.recipes.settings import cell_settings, check_names, task_config
from dcsc_torchrl.report import plot_state_beta
from dcsc_torchrl.runlog import write_atomic
from dcsc_torchrl.state_arbiter import LEARNER_SETTINGS, save_pretrained_arbiter
from dcsc_torchrl.tasks import Task


def arbiter_config(task: Task, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """The task's protocol config with ``overrides``, checked whole: ``state.pool`` names presets,
    ``state.algorithm`` an algorithm the task can learn with, ``state.betas`` are in [0, 1]."""
    cfg = task_config(task, overrides, quick=quick)
    check_names("state.pool", "operator preset", list(cfg.state.pool), list(PRESETS))
    check_names("state.algorithm", "algorithm", [cfg.state.algorithm], list(LEARNER_SETTINGS))
    check_algorithm_for(task, cfg.state.algorithm)
    return cfg


def pretrain(task: Task, cfg: DictConfig, out: Path, *, quick: bool = False) -> Path:
    """Pretrains the arbiter of ``cfg`` next to its first pretraining seed's machine into ``out``;
    returns ``arbiter.pt``."""
    start = time.perf_counter()
    torch.set_num_threads(1)
    seed = cfg.pretrain.seeds[0]
    machine_net, _ = pretrained_machine(task, cfg, seed, quick=quick)
    settings = cell_settings(cfg)
    state = cfg.state
    learner = {"algorithm": state.algorithm, "gamma": cfg.online.gamma,
               **{key: state[key] for key in LEARNER_SETTINGS[state.algorithm] if key != "gamma"}}
    pretrained, rows, frames = pretrain_state_arbiter(
        task, machine_net, {name: task.make_operator(name) for name in state.pool}, human=settings["human"],
        machine=settings["machine"], arbiter=settings["arbiter"], protocol=settings["protocol"],
        calibration_runs=state.calibration_runs, first_seed=state.first_seed, hidden=list(state.hidden),
        value_hidden=list(state.value_hidden), spread=state.spread, learner=learner, seed=seed,
        progress=lambda line: print(f"  arbiter: {line}", flush=True))
    out.mkdir(parents=True, exist_ok=True)
    table = pd.DataFrame(rows)
    write_atomic(out / "pretraining.csv", lambda file: table.to_csv(file, index=False))
    plot_state_beta(frames, task, out / "fig_state_beta.png",
                    f"{task.title}: the state-dependent arbiter's β after pretraining\n"
                    f"(the frames it learned from last; pool {', '.join(state.pool)})")
    return save_pretrained_arbiter(out / "arbiter.pt", task, pretrained, to_plain(cfg), machine_seed=seed,
                                   frames=int(table["frames"].sum()), seconds=time.perf_counter() - start)


def main(task: Task, overrides: Sequence[str] = (), *, quick: bool = False, out: Path | None = None) -> Path:
    """``dcsc arbiter``'s job: the config checked at the door, then :func:`pretrain`."""
    cfg = arbiter_config(task, overrides, quick=quick)
    folder = writable_folder(out or Path("runs/quick" if quick else "runs") / f"arbiter_{task.name}")
    return pretrain(task, cfg, folder, quick=quick)
