"""``dcsc sweep`` on a local Ray instance: same rows as the cells run in turn, failures, resume."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import ray
import torch

from dcsc_torchrl.cli import _sweep, build_parser
from dcsc_torchrl.config import load_config
from dcsc_torchrl.protocol import run_cell
from dcsc_torchrl.recipes.configs import RECIPES_DIR as RECIPES
from dcsc_torchrl.recipes.folder import TABLES, write_csv
from dcsc_torchrl.recipes.grid import make_grid
from dcsc_torchrl.recipes.machines import pretrained_machine
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.recipes.sweep import main, run_sweep, split_overrides
from dcsc_torchrl.tasks import get_task

PROTOCOL = ["scenarios.operator_runs=1", "scenarios.collaboration_runs=1", "scenarios.validation_scenarios=2",
            "protocol.group_size=1", "protocol.max_steps=60"]
METHODS = ["machine", "dcsc"]


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray instance (2 CPUs) for the module; every sweep here joins it."""
    ray.init(num_cpus=2, include_dashboard=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def pretrain_dir(tmp_path_factory):
    """``pretrain.out_dir`` of the quick machines: the first sweep pretrains seeds 0 and 1 there."""
    return tmp_path_factory.mktemp("pretrain")


def sweep_args(out, pretrain_dir, operators: str, seeds: str, *extra: str) -> list[str]:
    """The command line of a tiny lunarlander sweep (quick config, two methods, a few short episodes)."""
    return ["--quick", "--out", str(out), "tasks=[lunarlander]", f"operators={operators}",
            f"pretrain_seeds={seeds}", f"methods=[{','.join(METHODS)}]", "ray.retries=1",
            f"lunarlander.pretrain.out_dir={pretrain_dir}", *(f"lunarlander.{item}" for item in PROTOCOL), *extra]


@pytest.fixture(scope="module")
def grid_sweep(local_ray, pretrain_dir, tmp_path_factory):
    """A 2 x 2 sweep (presets expert, noisy x pretraining seeds 0, 1), pretraining included."""
    out = tmp_path_factory.mktemp("sweep")
    args = sweep_args(out, pretrain_dir, "[expert,noisy]", "[0,1]")
    return out, args, main(args)


def test_sweep_gives_the_rows_of_the_cells_run_one_after_another(grid_sweep, pretrain_dir, tmp_path):
    out, _, result = grid_sweep
    assert len(result.ran) == 4 and not result.failed
    cfg = load_config(RECIPES / "shared_control_lunarlander.yaml", [*PROTOCOL, f"pretrain.out_dir={pretrain_dir}"],
                      quick=True)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        tables: dict[str, list[dict]] = {name: [] for name in TABLES}
        for seed in (0, 1):
            for preset in ("expert", "noisy"):
                task = get_task("lunarlander")
                machine, critic = pretrained_machine(task, cfg, seed, quick=True)
                cell = run_cell(task, task.make_operator(preset), machine, critic, operator_name=preset,
                                pretrain_seed=seed, methods=tuple(METHODS), trace=(preset, seed) == ("expert", 0),
                                **cell_settings(cfg))
                tables["episodes"] += cell.episodes
                tables["trace"] += cell.traces
                tables["theta"] += cell.theta
                tables["calibration"].append(cell.calibration)
    finally:
        torch.set_num_threads(threads)
    for name, rows in tables.items():
        write_csv(rows, tmp_path / f"{name}.csv")
        pd.testing.assert_frame_equal(pd.read_csv(out / "lunarlander" / f"{name}.csv"),
                                      pd.read_csv(tmp_path / f"{name}.csv"))
    task_dir = out / "lunarlander"
    assert "DC-SC" in (task_dir / "summary.md").read_text()
    assert (task_dir / "fig_performance.png").exists() and not (task_dir / "failed_cells.csv").exists()
    assert sorted(p.name for p in (task_dir / "cells").iterdir()) == ["expert-seed0", "expert-seed1", "noisy-seed0",
                                                                       "noisy-seed1"]


def test_rerunning_a_finished_sweep_runs_no_cell(grid_sweep):
    out, args, _ = grid_sweep
    marks = sorted((out / "lunarlander" / "cells").glob("*/cell.json"))
    before = [(path.stat().st_mtime_ns, path.read_text()) for path in marks]
    episodes = (out / "lunarlander" / "episodes.csv").read_text()
    again = main(args)
    assert again.ran == [] and len(again.skipped) == 4 and not again.failed
    assert [(path.stat().st_mtime_ns, path.read_text()) for path in marks] == before
    assert (out / "lunarlander" / "episodes.csv").read_text() == episodes


def test_a_failing_cell_is_retried_then_reported_and_the_other_cells_kept(local_ray, pretrain_dir, grid_sweep,
                                                                          tmp_path):
    """A cell that raises in its Ray task: here one of an unknown preset, in a grid built past the
    door (``dcsc sweep`` refuses the name before any cell runs: tests/test_door.py)."""
    cfg = task_config(get_task("lunarlander"), [*PROTOCOL, f"pretrain.out_dir={pretrain_dir}"], quick=True)
    grid = make_grid("lunarlander", cfg, ["expert", "nobody"], [0], quick=True)
    result = run_sweep(tmp_path, [grid], tuple(METHODS), quick=True, retries=1)
    assert [cell.name for cell in result.ran] == ["expert-seed0"]
    task_dir = tmp_path / "lunarlander"
    failed = pd.read_csv(task_dir / "failed_cells.csv")
    assert failed[["cell", "attempts"]].values.tolist() == [["nobody-seed0", 2]]  # ray.retries=1: tried twice
    assert "unknown operator preset 'nobody'" in failed["error"].iloc[0]
    traceback = (task_dir / "cells" / "nobody-seed0" / "error.txt").read_text()
    assert "from_preset" in traceback and "\x1b[" not in traceback
    summary = (task_dir / "summary.md").read_text()
    assert "## Failed cells" in summary and "nobody-seed0" in summary and "DC-SC" in summary
    episodes = pd.read_csv(task_dir / "episodes.csv")
    assert set(episodes["operator"]) == {"expert"} and len(episodes) > 0
    assert json.loads((task_dir / "cells" / "expert-seed0" / "cell.json").read_text())["attempts"] == 1


def test_task_prefixed_overrides_go_to_that_tasks_protocol_config():
    sweep, tasks = split_overrides(["ray.workers=4", "uav.protocol.max_steps=50", "tasks=[uav]"])
    assert sweep == ["ray.workers=4", "tasks=[uav]"]
    assert tasks == {"lunarlander": [], "uav": ["protocol.max_steps=50"]}


def test_dcsc_sweep_hands_its_arguments_to_the_recipe():
    args = build_parser().parse_args(["sweep", "ray.workers=1", "--quick", "--out", "DIR"])
    assert args.handler is _sweep and args.quick and args.out == Path("DIR") and args.overrides == ["ray.workers=1"]


def test_a_sweep_with_the_shipped_machine_reads_the_shipped_file_and_pretrains_nothing(tmp_path, monkeypatch):
    """`dcsc sweep ... <task>.pretrain.shipped=true`: the cells load the file `dcsc run` would."""
    from dcsc_torchrl.recipes.machines import machine_checkpoint
    from dcsc_torchrl.recipes.sweep import ensure_pretrained
    from dcsc_torchrl.shipped import shipped_path

    monkeypatch.chdir(tmp_path)
    task = get_task("uav")
    cfg = task_config(task, ["pretrain.shipped=true", "pretrain.seeds=[0]"])
    assert machine_checkpoint(task, cfg, 0) == shipped_path(task)
    assert Path(ensure_pretrained._function("uav", cfg, 0, False)) == shipped_path(task)
    assert list(tmp_path.iterdir()) == []
