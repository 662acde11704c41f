"""``dcsc map``: where shared control pays, over operators x machines (docs/cli.md).

    dcsc map [--quick] [--out DIR] [--fresh] [--workers N] [key=value ...]

For every machine of ``recipes/map.yaml`` (what it observes x how long it trained), the
task's protocol (``dcsc run``'s, the same cells and CSVs) runs every operator preset of the
map into ``DIR/<machine>/<task>/``, each machine pretrained first when its checkpoint is
missing. Then ``DIR/map.csv`` (:func:`~dcsc_torchrl.sharing_map.sharing_map`), ``DIR/map.md``
and ``DIR/fig_map.png`` set each method's validation success against the better partner
alone, per scenario, with 95% CIs. A machine whose cells are done is not run again, so a
stopped map resumes; ``--fresh`` starts every machine's folder over.

The field's assistants need inputs of their own, made before any cell runs: ``ida_expert``
reads the critic of machine ``expert`` (pretrained first when missing), ``reddy`` the
copilots of ``copilots`` (``dcsc copilot``, trained into ``{pretrain_dir}/copilot-<name>/``
when missing; each cell takes the first not trained with its operator), ``dcsc_state`` the
arbiters of ``arbiters`` (``dcsc arbiter``, pretrained next to every selected machine into
``{pretrain_dir}/<machine>/arbiter-<name>/``, the machines pretrained first; each cell takes
the one of its machine whose pool lacks its operator; ``arbiters_leave_one_out``: one per
operator, pretrained with all the others).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from multiprocessing import get_context
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path
from dcsc_torchrl.config import ConfigError, distinct, load_config, writable_folder
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.methods import METHOD_NAMES, METHODS
from dcsc_torchrl.recipes.configs import MAP_CONFIG
from dcsc_torchrl.recipes.executors import executor
from dcsc_torchrl.recipes.grid import TaskGrid, checked_grid, run_grid
from dcsc_torchrl.recipes.options import Parser, add_map_options
from dcsc_torchrl.recipes.settings import check_names
from dcsc_torchrl.report import QUICK_NOTE, read_table
from dcsc_torchrl.runlog import write_atomic
from dcsc_torchrl.sharing_map import (
    claims_markdown,
    map_markdown,
    map_tally,
    paper_claims,
    plot_map,
    sharing_map,
    tally_markdown,
)
from dcsc_torchrl.tasks import get_task


def map_config(overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """``recipes/map.yaml`` with ``overrides``, checked: the machines selected exist, the
    operators and methods are known, and each machine's protocol config passes the door."""
    cfg = load_config(MAP_CONFIG, overrides, quick=quick)
    cfg.selected = check_names("selected", "machine", distinct("selected", cfg.selected), list(cfg.machines))
    cfg.methods = check_names("methods", "method", distinct("methods", cfg.methods), list(METHOD_NAMES))
    cfg.operators = distinct("operators", cfg.operators)
    check_names("expert", "machine", [cfg.expert], list(cfg.machines))
    for group in ("copilots", "arbiters"):
        for name, pool in cfg[group].items():
            if not pool:
                raise ConfigError(f"{group}.{name}: expected at least one operator preset, got {list(pool)}")
            check_names(f"{group}.{name}", "operator preset", list(pool), list(PRESETS))
    if "dcsc_state" in cfg.methods and cfg.arbiters_leave_one_out and len(cfg.operators) < 2:
        raise ConfigError(f"arbiters_leave_one_out: an arbiter pretrained without the cell's operator needs another "
                          f"operator in the map, got operators={list(cfg.operators)}")
    return cfg


def _pretrain_machine(task: str, overrides: list[str], operators: list[str], quick: bool) -> None:
    from dcsc_torchrl.recipes.machines import pretrained_machine

    cfg = checked_grid(task, quick=quick, overrides=overrides, operators=operators, option="operators").cfg
    pretrained_machine(get_task(task), cfg, 0, quick=quick)


def _train_copilot(task: str, pool: list[str], folder: Path, quick: bool) -> None:
    from dcsc_torchrl.recipes.copilot import copilot_config, train

    print(f"map: training copilot {folder.name} ({', '.join(pool)})", flush=True)
    train(copilot_config(get_task(task), [f"pool=[{','.join(pool)}]"], quick=quick, out=folder),
          resume=(folder / "checkpoint.pt").is_file())


def _pretrain_arbiter(task: str, overrides: list[str], pool: list[str], folder: Path, quick: bool) -> None:
    from dcsc_torchrl.recipes.arbiter import main

    print(f"map: pretraining arbiter {folder.parent.name}/{folder.name} ({', '.join(pool)})", flush=True)
    main(get_task(task), [*overrides, f"state.pool=[{','.join(pool)}]"], quick=quick, out=folder)


def arbiter_pools(cfg: DictConfig) -> dict[str, list[str]]:
    """``dcsc_state``'s pretraining pools by name: ``arbiters``, or with ``arbiters_leave_one_out``
    one per operator of the map, every other operator of the map (``without-<operator>``)."""
    if cfg.arbiters_leave_one_out:
        return {f"without-{left}": [op for op in cfg.operators if op != left] for left in cfg.operators}
    return {name: list(pool) for name, pool in cfg.arbiters.items()}


def _run_jobs(jobs: Sequence[partial], workers: int) -> None:
    """``jobs`` ``workers`` at a time, each in its own process when more than one."""
    if workers == 1 or len(jobs) < 2:
        for job in jobs:
            job()
        return
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=get_context("spawn")) as pool:
        for future in [pool.submit(job) for job in jobs]:
            future.result()


def ready_assistants(cfg: DictConfig, *, quick: bool, workers: int = 1) -> list[str]:
    """The protocol settings of the assistants the map's methods read, made when missing
    (``workers`` at a time, each in its own process when more than one): ``ida.expert``
    (machine ``expert``'s seed-0 checkpoint, pretrained), ``reddy.copilots`` (trained) and
    the arbiters of :func:`machine_arbiters` (pretrained next to every selected machine, after the
    machines; each machine's grid names its own, :func:`machine_grids`)."""
    jobs, settings, machines = [], [], {}
    if "ida_expert" in cfg.methods:
        machines[cfg.expert] = checkpoint_path(Path(cfg.pretrain_dir).resolve() / cfg.expert, 0)
        settings.append(f"ida.expert={machines[cfg.expert]}")
    if "dcsc_state" in cfg.methods:
        machines.update({name: checkpoint_path(Path(cfg.pretrain_dir).resolve() / name, cfg.machines[name].seeds[0])
                         for name in cfg.selected})
    jobs += [partial(_pretrain_machine, cfg.task, machine_overrides(cfg, name), list(cfg.operators), quick)
             for name, path in machines.items() if not path.is_file()]
    if "reddy" in cfg.methods:
        paths = []
        for name, pool in cfg.copilots.items():
            folder = (Path(cfg.pretrain_dir) / f"copilot-{name}").resolve()
            if not (folder / "copilot.pt").is_file():
                jobs.append(partial(_train_copilot, cfg.task, list(pool), folder, quick))
            paths.append(str(folder / "copilot.pt"))
        settings.append(f"reddy.copilots=[{','.join(paths)}]")
    _run_jobs(jobs, workers)
    if "dcsc_state" in cfg.methods:  # next to the machines, which exist now
        _run_jobs([partial(_pretrain_arbiter, cfg.task, machine_overrides(cfg, machine), pool, path.parent, quick)
                   for machine in cfg.selected for path, pool in machine_arbiters(cfg, machine).items()
                   if not path.is_file()], workers)
    return settings


def machine_arbiters(cfg: DictConfig, machine: str) -> dict[Path, list[str]]:
    """``dcsc_state``'s arbiters next to ``machine``: each file (``{pretrain_dir}/<machine>/arbiter-<pool
    name>/arbiter.pt``) and the pool it is pretrained with (:func:`arbiter_pools`)."""
    return {(Path(cfg.pretrain_dir) / machine / f"arbiter-{name}").resolve() / "arbiter.pt": pool
            for name, pool in arbiter_pools(cfg).items()}


def machine_overrides(cfg: DictConfig, name: str) -> list[str]:
    """The protocol settings of machine ``name``: its folder, what it observes, its seeds and
    the recipe of its strength, then the map's own ``protocol`` settings."""
    machine = cfg.machines[name]
    check_names(f"machines.{name}.strength", "strength", [machine.strength], list(cfg.strengths))
    recipe = ",".join(cfg.strengths[machine.strength])
    seeds = ",".join(str(seed) for seed in machine.seeds)
    return [f"pretrain.out_dir={Path(cfg.pretrain_dir) / name}", f"pretrain.observes={machine.observes}",
            f"pretrain.seeds=[{seeds}]", f"pretrain.recipe=[{recipe}]", *cfg.protocol]


def machine_grids(cfg: DictConfig, *, quick: bool) -> dict[str, TaskGrid]:
    """Every selected machine's grid (the task's protocol config, checked whole, before any cell runs),
    with ``dcsc_state``'s arbiters of that machine alone (so a map of fewer machines resumes)."""
    grids = {}
    for name in cfg.selected:
        arbiters = ([f"state.arbiters=[{','.join(map(str, machine_arbiters(cfg, name)))}]"]
                    if "dcsc_state" in cfg.methods else [])
        try:
            grids[name] = checked_grid(cfg.task, quick=quick, overrides=[*machine_overrides(cfg, name), *arbiters],
                                       operators=cfg.operators, option="operators")
        except ConfigError as err:
            raise ConfigError(f"machines.{name}: {err}") from None
    return grids


def write_map(out: Path, task: str, machines: Sequence[str], *, quick: bool = False) -> Path:
    """``map.csv``, ``map.md`` and ``fig_map.png`` from every machine's ``<machine>/<task>/episodes.csv``
    (``quick``: ``map.md`` says its numbers test the code, not the method)."""
    frames = [read_table(out / name / task / "episodes.csv").assign(machine=name) for name in machines
              if (out / name / task / "episodes.csv").is_file()]
    if not frames:
        raise ConfigError(f"--out {out}: no machine's {task}/episodes.csv there yet")
    episodes = pd.concat(frames, ignore_index=True)
    table = sharing_map(episodes)
    write_atomic(out / "map.csv", lambda f: table.to_csv(f, index=False))
    plot_map(table, out / "fig_map.png", f"{task}: success − the better partner alone (validation, 95% CI)")
    text = (f"# Where shared control pays: {task}\n\nEach method's validation success minus the better "
            "partner's alone, in points, paired per scenario (± 95% CI); **bold**: above both partners. "
            "Machines: `recipes/map.yaml`.\n\n" + (QUICK_NOTE + "\n" if quick else "") + map_markdown(table)
            + "\n## Each method over the cells\n\nAbove both partners: the whole 95% CI above 0; below the "
            "better partner: the whole CI below 0.\n\n" + tally_markdown(map_tally(table)))
    for method in ("dcsc_centred", "dcsc"):
        claims = paper_claims(episodes, method)
        if len(claims):
            text += (f"\n## The paper's claims for {METHODS[method].label}, cell by cell\n\n"
                     "Paired per scenario: *yes* where the 95% CI of the difference lies on the claimed side, "
                     "*within CI* where only its mean does.\n\n" + claims_markdown(claims))
    path = out / "map.md"
    write_atomic(path, lambda f: f.write(text))
    return path


def run_map(out: Path | None = None, *, quick: bool = False, overrides: Sequence[str] = (), fresh: bool = False,
            workers: int = 2) -> Path:
    """Every selected machine's grid (resumable), then the map; returns ``map.md``."""
    out = writable_folder((out or Path("results/quick/map" if quick else "results/map")).resolve())
    cfg = map_config(overrides, quick=quick)
    machine_grids(cfg, quick=quick)  # every machine's config checked before any assistant is made
    cfg.protocol = [*cfg.protocol, *ready_assistants(cfg, quick=quick, workers=workers)]
    grids = machine_grids(cfg, quick=quick)
    run = executor(workers)
    torch.set_num_threads(next(iter(grids.values())).cfg.threads)
    methods = tuple(cfg.methods)
    for name, grid in grids.items():
        start = time.perf_counter()
        result = run_grid(out / name, [grid], methods, run, quick=quick, fresh=fresh)
        print(f"map: {name}: {len(result.ran)} cell(s) run, {len(result.skipped)} done before, "
              f"{len(result.failed)} failed ({time.perf_counter() - start:.0f} s)", flush=True)
    return write_map(out, cfg.task, list(grids), quick=quick)


def main(argv: Sequence[str] | None = None) -> Path:
    args = add_map_options(Parser(description=__doc__.split("\n\n")[0])).parse_args(argv)
    return run_map(args.out, quick=args.quick, overrides=args.overrides, fresh=args.fresh, workers=args.workers)


if __name__ == "__main__":
    main()
