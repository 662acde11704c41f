"""The ``dcsc`` command as a newcomer meets it: help, one-line errors, exit codes, checkpoints, resume.

Every bad input is a row of a table: the command line, the exit code, and what the one
line on stderr must name (the key, the file). Commands run in-process through
``dcsc_torchrl.cli.main``; subprocesses only where a fresh interpreter is the point (what
``--help`` imports, Ctrl-C). No test pretrains: the machine of the runs below is a small
untrained network written as a checkpoint.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from dcsc_torchrl import cli
from dcsc_torchrl.checkpoint import (
    CheckpointError,
    checkpoint_path,
    load_checkpoint,
    save_checkpoint,
    stale_temp_files,
)
from dcsc_torchrl.cli import build_parser, main
from dcsc_torchrl.config import ConfigError, config_diff, load_config, to_plain
from dcsc_torchrl.methods import METHOD_NAMES as METHODS
from dcsc_torchrl.networks import LUNAR_QVALUE_DIMS, lunar_actor, lunar_critic, lunar_machine_dims
from dcsc_torchrl.recipes import grid, machines, shared_control
from dcsc_torchrl.recipes.configs import RECIPES_DIR as RECIPES
from dcsc_torchrl.recipes.folder import RUN_RECORD, prepare_results

PRETRAIN_YAML = RECIPES / "pretrain_a2c_lunarlander.yaml"
TINY = ["scenarios.operator_runs=1", "scenarios.collaboration_runs=1", "scenarios.validation_scenarios=2",
        "protocol.group_size=1", "protocol.max_steps=30"]


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def machine_dir(tmp_path_factory) -> Path:
    """``pretrain.out_dir`` holding seed 0's checkpoint: a small untrained LunarLander machine
    that sees the pad (the protocol's default view)."""
    out = tmp_path_factory.mktemp("pretrain")
    torch.manual_seed(0)
    network = {"hidden": [16, 16], "actor_dropout": 0.05, "observes": "target"}
    actor = lunar_actor(network["hidden"], network["actor_dropout"], obs_dims=lunar_machine_dims("target"))
    qvalue = lunar_critic(network["hidden"], 4, obs_dims=LUNAR_QVALUE_DIMS)
    save_checkpoint(checkpoint_path(out, 0), task="lunarlander",
                    payload={"config": {"network": network}, "state": {"actor": actor.state_dict(),
                                                                        "qvalue": qvalue.state_dict()}})
    return out


def run_argv(out: Path, machine: Path, *extra: str) -> list[str]:
    """A two-cell ``dcsc run lunarlander --quick`` (presets expert, noisy) at a tiny scale."""
    return ["run", "lunarlander", "--quick", "--methods", "machine", "dcsc", "--out", str(out),
            f"pretrain.out_dir={machine}", *TINY, *extra]


@pytest.fixture(scope="module")
def full_run(machine_dir, tmp_path_factory) -> Path:
    """The uninterrupted run: its results folder."""
    out = tmp_path_factory.mktemp("full")
    assert main(run_argv(out, machine_dir)) == 0
    return out / "lunarlander"


# -- help -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv, expected",
    [
        (["--help"], "usage: dcsc [-h]"),
        (["pretrain", "--help"], "usage: dcsc pretrain"),
        (["pretrain", "uav", "--help"], "--resume"),
        (["play", "--help"], "usage: dcsc play"),
        (["run", "--help"], "usage: dcsc run"),
        (["run", "lunarlander", "--help"], "--methods"),
        (["run", "--help"], "<pretrain.out_dir>/seed<s>/checkpoint.pt, relative to the current folder"),
        (["run", "--help"], "a missing one is pretrained first"),
        (["sweep", "--help"], "usage: dcsc sweep"),
        (["reproduce", "--help"], "--quick"),
        (["report", "--help"], "usage: dcsc report"),
    ],
)
def test_every_subcommand_has_its_own_help(argv, expected, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 0
    assert expected in " ".join(capsys.readouterr().out.split())


def test_every_option_of_every_command_has_help_text():
    commands = next(a for a in build_parser()._actions if a.dest == "command")
    for name, sub in commands.choices.items():
        for action in sub._actions:
            assert action.help, f"dcsc {name} {action.option_strings or action.dest} has no help"


def test_help_and_config_errors_do_not_load_torch(tmp_path):
    """In a fresh interpreter: help, an argparse error and a config error leave torch unimported."""
    code = (
        "import sys\n"
        "from dcsc_torchrl.cli import main\n"
        "for argv in (['run', '--help'], ['pretrain', 'mars']):\n"
        "    try: main(argv)\n"
        "    except SystemExit: pass\n"
        "assert main(['pretrain', 'lunarlander', 'train.episodez=5']) == 2\n"
        "assert main(['run', 'uav', 'scenarios.validation_scenarios=-4']) == 2\n"
        "print(sorted(m for m in ('torch', 'torchrl', 'tensordict', 'ray') if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_overrides_may_stand_anywhere_even_after_nargs_options():
    args = build_parser().parse_args(["run", "lunarlander", "--quick", "--methods", "machine", "pretrain.out_dir=X",
                                      "--operators", "expert", "noisy", "seed=3"])
    assert args.methods == ["machine"] and args.operators == ["expert", "noisy"]
    assert args.overrides == ["pretrain.out_dir=X", "seed=3"] and args.quick


def test_run_help_names_every_method_it_accepts(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    assert "methods.METHODS" in capsys.readouterr().out
    assert main(["run", "lunarlander", "--methods", "nothing"]) == 2
    line = capsys.readouterr().err
    assert all(method in line for method in METHODS)


# -- one-line errors ------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv, needles",
    [
        (["pretrain", "lunarlander", "train.episodez=5"], ["unknown key train.episodez", "did you mean train.episodes?"]),
        (["pretrain", "lunarlander", "train.episodes=abc"], ["train.episodes: expected an int, got 'abc'"]),
        (["pretrain", "lunarlander", "train.episodes=2.5"], ["train.episodes: expected an int, got 2.5"]),
        (["pretrain", "lunarlander", "optim.lr=abc"], ["optim.lr: expected a number, got 'abc'"]),
        (["pretrain", "lunarlander", "optim.lr=-1e-3"], ["optim.lr: expected a value > 0"]),
        (["pretrain", "uav", "env=3"], ["env: expected a group of keys"]),
        (["pretrain", "lunarlander", "train.episodes"], ["override 'train.episodes' is not of the form key=value"]),
        (["run", "lunarlander", "scenarios.validation_scenarios=-4"], ["scenarios.validation_scenarios", ">= 1", "-4"]),
        (["run", "uav", "pretrain.seeds=[a]"], ["pretrain.seeds: expected a list of ints"]),
        (["run", "lunarlander", "--operators", "nobody"], ["unknown operator preset 'nobody'", "expert"]),
        (["run", "lunarlander", "--methods", "nothing"], ["unknown method 'nothing'"]),
        (["run", "lunarlander", "online.theta_critic=beta"], ["online.theta_critic", "action, authority", "'beta'"]),
        (["run", "uav", "online.theta_critic=authority"], ["online.critic_lr must be 0", "0.0001"]),
        (["run", "lunarlander", "warmup.blend_betas=[1.5]"], ["warmup.blend_betas", "[0, 1]", "1.5"]),
        (["run", "lunarlander", "arbiter.form=ratio"], ["arbiter.form must be one of paper, centred", "'ratio'"]),
        (["run", "lunarlander", "arbiter.constant_betas=[0.5,2.0]"], ["arbiter.constant_betas", "[0, 1]", "2.0"]),
        (["run", "lunarlander", "human.K=0"], ["human.K must be in (0.0, inf), got 0"]),
        (["run", "lunarlander", "human.eta=1.5"], ["human.eta must be in (0.0, 1.0), got 1.5"]),
        (["run", "uav", "machine.delta2=0.5"], ["machine.delta2 must be in (1.0, inf), got 0.5"]),
        (["run", "lunarlander", "protocol.shared_action=argmax"], ["protocol.shared_action", "sample, mode"]),
        (["run", "uav", "--methods", "rule"], ["task uav does not define method(s) rule", "no authority rule"]),
        (["sweep", "lunarlander.protocol.group_size=0"], ["protocol.group_size", ">= 1"]),
        (["sweep", "ray.workerz=2"], ["unknown key ray.workerz", "did you mean ray.workers?"]),
        (["reproduce", "--workers", "0"], ["--workers", "expected an integer >= 1, got 0"]),
        (["report", "a.b=1"], ["takes no key=value overrides"]),
    ],
)
def test_a_bad_input_is_one_line_naming_it_and_exit_2(argv, needles, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing may be pretrained or written: checked below
    try:
        code = main(argv)
    except SystemExit as exit_info:  # argparse's own errors
        code = exit_info.code
    assert code == 2
    line = one_line_error(capsys)
    for needle in needles:
        assert needle in line
    assert list(tmp_path.iterdir()) == []


def test_argparse_errors_are_one_line_with_the_commands_name(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["pretrain", "mars"])
    assert exit_info.value.code == 2
    line = one_line_error(capsys)
    assert line.startswith("dcsc pretrain: error:") and "lunarlander" in line and "dcsc pretrain --help" in line


def test_play_without_checkpoint_says_how_to_get_one(tmp_path, capsys):
    assert main(["play", "lunarlander", "--checkpoint", str(tmp_path / "missing.pt")]) == 2
    line = one_line_error(capsys)
    assert "dcsc pretrain lunarlander" in line and str(tmp_path / "missing.pt") in line


def test_play_looks_where_run_looks_then_flies_the_shipped_machine(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("DISPLAY", raising=False)  # the machine is chosen before the window opens
    cfg = load_config(RECIPES / "shared_control_lunarlander.yaml")
    main(["play", "lunarlander"])
    err = capsys.readouterr().err
    assert f"no lunarlander checkpoint at {checkpoint_path(cfg.pretrain.out_dir, cfg.pretrain.seeds[0])}" in err
    assert "shipped machine (lunarlander_target_seed0.pt)" in err  # the paper's machine, which sees the pad


# -- checkpoints ----------------------------------------------------------------------
def test_every_command_reads_one_checkpoint_layout():
    assert checkpoint_path("runs/x", 2) == Path("runs/x/seed2/checkpoint.pt")
    cfg = load_config(RECIPES / "shared_control_lunarlander.yaml")
    args = build_parser().parse_args(["play", "lunarlander"])
    assert args.checkpoint is None  # dcsc play then reads checkpoint_path(pretrain.out_dir, first seed)
    assert checkpoint_path(cfg.pretrain.out_dir, cfg.pretrain.seeds[0]).parts[-2:] == ("seed0", "checkpoint.pt")


@pytest.mark.parametrize(
    "content, needle",
    [
        (b"", "is empty"),
        (b"not a checkpoint at all", "is corrupt or truncated"),
        ("truncated", "is corrupt or truncated"),
    ],
)
def test_a_broken_checkpoint_is_one_line_naming_its_path(content, needle, machine_dir, tmp_path, capsys):
    broken = checkpoint_path(tmp_path / "pre", 0)
    broken.parent.mkdir(parents=True)
    if content == "truncated":
        whole = checkpoint_path(machine_dir, 0).read_bytes()
        content = whole[: len(whole) // 2]
    broken.write_bytes(content)
    code = main(["run", "lunarlander", "--quick", "--operators", "expert", "--methods", "machine",
                 "--out", str(tmp_path / "res"), f"pretrain.out_dir={tmp_path / 'pre'}", *TINY])
    assert code == 2
    line = one_line_error(capsys)
    assert str(broken) in line and needle in line and "weights_only" not in line


def test_checkpoints_are_readable_by_the_group_and_leave_no_temp_files(tmp_path):
    path = tmp_path / "run" / "checkpoint.pt"
    path.parent.mkdir()
    stale = path.parent / f".{path.name}.abc123.tmp"  # what a writer killed mid-write leaves
    stale.write_bytes(b"half")
    save_checkpoint(path, task="uav", payload={"x": torch.zeros(2)})
    assert stale_temp_files(path) == [] and not stale.exists()
    old = os.umask(0o022)
    try:
        save_checkpoint(path, task="uav", payload={"x": torch.zeros(2)})
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    with pytest.raises(CheckpointError, match="written for task 'uav'"):
        load_checkpoint(path, task="lunarlander")


def test_resume_refuses_another_config_and_names_the_keys(tmp_path, capsys):
    run_dir = tmp_path / "seed0"
    cfg = load_config(PRETRAIN_YAML, ["env.num_envs=3", f"logger.out_dir={run_dir}"], quick=True)
    save_checkpoint(run_dir / "checkpoint.pt", task="lunarlander", payload={"config": to_plain(cfg)})
    assert main(["pretrain", "lunarlander", "--quick", "--resume", "--out", str(run_dir)]) == 2
    line = one_line_error(capsys)
    assert str(run_dir / "checkpoint.pt") in line and "env.num_envs: 3 -> 2" in line


def test_resume_without_a_checkpoint_names_the_missing_file(tmp_path, capsys):
    assert main(["pretrain", "lunarlander", "--quick", "--resume", "--out", str(tmp_path / "none")]) == 2
    assert str(tmp_path / "none" / "checkpoint.pt") in one_line_error(capsys)


def test_config_diff_names_changed_added_and_removed_keys():
    assert config_diff({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "d": 2}}) == ["a.c: 2 -> (absent)",
                                                                               "a.d: (absent) -> 2"]
    with pytest.raises(ConfigError, match="no config file"):
        load_config(RECIPES / "missing.yaml")


# -- dcsc run: resume, folders that never contradict themselves ------------------------
def test_a_run_killed_after_its_first_cell_resumes_to_the_same_csvs(full_run, machine_dir, tmp_path, monkeypatch,
                                                                     capsys):
    real = grid.run_cell
    calls = []

    def killed_at_second_cell(*args, **kwargs):
        calls.append(kwargs["operator_name"])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(grid, "run_cell", killed_at_second_cell)
    assert main(run_argv(tmp_path, machine_dir)) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "dcsc: interrupted"
    task_dir = tmp_path / "lunarlander"
    halfway = pd.read_csv(task_dir / "episodes.csv")
    assert set(halfway["operator"]) == {"expert"}  # the summary describes what the tables hold
    assert "expert" in (task_dir / "summary.md").read_text()

    monkeypatch.setattr(grid, "run_cell", real)
    (task_dir / "episodes.csv.tmp").write_text("left by a kill")
    assert main(run_argv(tmp_path, machine_dir)) == 0
    assert f"results in {task_dir}" in capsys.readouterr().err
    for name in ("episodes.csv", "trace.csv", "theta.csv"):
        assert (task_dir / name).read_bytes() == (full_run / name).read_bytes(), name
    assert not list(task_dir.rglob("*.tmp"))


def test_a_run_resumed_next_to_a_machine_pretrained_again_is_refused(full_run, machine_dir, tmp_path, capsys):
    machine = tmp_path / "machine"
    shutil.copytree(machine_dir, machine)
    assert main([*run_argv(tmp_path, machine), "--operators", "expert"]) == 0
    data = torch.load(checkpoint_path(machine, 0), weights_only=False)
    data["state"]["actor"] = {k: v + 0.01 for k, v in data["state"]["actor"].items()}  # "pretrained again"
    torch.save(data, checkpoint_path(machine, 0))
    assert main(run_argv(tmp_path, machine)) == 2
    err = capsys.readouterr().err
    assert "expert-seed0 next to machine" in err and "pretrained again since?" in err and "--fresh" in err
    assert not (tmp_path / "lunarlander" / "cells" / "noisy-seed0").exists()  # refused before any cell ran
    cell = json.loads((tmp_path / "lunarlander" / "cells" / "expert-seed0" / "cell.json").read_text())
    cell["machine"] = "0123456789abcdef"  # two cells of one seed next to two machines: not gathered
    shutil.copytree(tmp_path / "lunarlander" / "cells" / "expert-seed0", tmp_path / "lunarlander" / "cells" / "noisy-seed0")
    (tmp_path / "lunarlander" / "cells" / "noisy-seed0" / "cell.json").write_text(json.dumps(cell))
    with pytest.raises(ConfigError, match="ran next to different machines"):
        grid.gather(tmp_path, grid.checked_grid("lunarlander", quick=True, overrides=[f"pretrain.out_dir={machine}"]))


def test_a_run_resumed_with_an_assistant_trained_again_is_refused(machine_dir, tmp_path, capsys):
    expert = tmp_path / "expert.pt"
    shutil.copy(checkpoint_path(machine_dir, 0), expert)
    argv = ["run", "lunarlander", "--quick", "--methods", "machine", "ida_expert", "--out", str(tmp_path),
            f"pretrain.out_dir={machine_dir}", f"ida.expert={expert}", *TINY]
    assert main([*argv, "--operators", "expert"]) == 0
    data = torch.load(expert, weights_only=False)
    data["state"]["qvalue"] = {k: v + 0.01 for k, v in data["state"]["qvalue"].items()}  # "trained again"
    torch.save(data, expert)
    assert main(argv) == 2
    assert f"holds results of another config (files.{expert}:" in capsys.readouterr().err


def test_dcsc_run_runs_its_cells_workers_at_a_time(machine_dir, tmp_path, monkeypatch, capsys):
    asked = []
    monkeypatch.setattr(shared_control, "executor", lambda workers: asked.append(workers) or grid.local_executor)
    assert main([*run_argv(tmp_path, machine_dir), "--operators", "expert", "--workers", "2"]) == 0
    assert asked == [2]  # Ray's executor (tests/test_sweep.py holds its rows to these)
    with pytest.raises(SystemExit) as exit_info:
        main([*run_argv(tmp_path, machine_dir), "--workers", "0"])
    assert exit_info.value.code == 2
    assert "argument --workers: expected an integer >= 1, got 0" in capsys.readouterr().err


def test_a_finished_run_run_again_runs_no_cell(full_run, machine_dir, monkeypatch):
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a finished cell ran again"))
    episodes = (full_run / "episodes.csv").read_bytes()
    assert main(run_argv(full_run.parent, machine_dir)) == 0
    assert (full_run / "episodes.csv").read_bytes() == episodes


def test_a_run_into_a_folder_of_another_config_is_refused(full_run, machine_dir, monkeypatch, capsys):
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a cell ran into a foreign folder"))
    assert main(run_argv(full_run.parent, machine_dir, "protocol.max_steps=31")) == 2
    line = one_line_error(capsys)
    assert str(full_run) in line and "protocol.max_steps: 30 -> 31" in line and "--fresh" in line


def test_an_old_folder_without_a_record_is_refused_and_fresh_starts_over(tmp_path, capsys):
    task_dir = tmp_path / "lunarlander"
    (task_dir / "cells" / "expert-seed0").mkdir(parents=True)
    (task_dir / "episodes.csv").write_text("old")
    (task_dir / "fig_performance.png").write_text("old")
    (task_dir / "notes.txt").write_text("mine")
    record = {"config": {"seed": 0}, "methods": ["machine"], "cells": ["expert-seed0"]}
    with pytest.raises(ConfigError, match=f"no {RUN_RECORD}"):
        prepare_results(task_dir, record, fresh=False)
    prepare_results(task_dir, record, fresh=True)
    assert sorted(p.name for p in task_dir.iterdir()) == ["notes.txt", RUN_RECORD]
    prepare_results(task_dir, record, fresh=False)  # the same config again: accepted


def test_a_grid_that_adds_cells_extends_the_folder_and_one_that_drops_cells_is_refused(tmp_path):
    task_dir = tmp_path / "lunarlander"
    record = {"config": {"seed": 0}, "methods": ["machine"], "cells": ["expert-seed0"]}
    prepare_results(task_dir, record, fresh=False)
    (task_dir / "cells" / "expert-seed0").mkdir(parents=True)
    (task_dir / "cells" / "expert-seed0" / "cell.json").write_text("{}")  # a finished cell: the folder is held
    grown = {**record, "cells": ["expert-seed0", "expert-seed1"]}
    prepare_results(task_dir, grown, fresh=False)
    assert yaml.safe_load((task_dir / RUN_RECORD).read_text())["cells"] == grown["cells"]
    with pytest.raises(ConfigError, match="cells"):
        prepare_results(task_dir, record, fresh=False)
    with pytest.raises(ConfigError, match="seed: 0 -> 1"):
        prepare_results(task_dir, {**grown, "config": {"seed": 1}}, fresh=False)


# -- logs and Ctrl-C --------------------------------------------------------------------
def test_building_an_env_logs_no_torchrl_info():
    from dcsc_torchrl.batched_envs import make_lunar_env

    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    logger = logging.getLogger("torchrl")
    logger.addHandler(handler)
    old = logger.level
    logger.setLevel(logging.INFO)
    try:
        make_lunar_env(2).close()
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)
    assert [r.getMessage() for r in records if r.levelno < logging.WARNING] == []


def test_ctrl_c_exits_130_with_one_line(tmp_path):
    """SIGINT while ``dcsc run`` pretrains its missing machine: exit 130, one line, no traceback."""
    process = subprocess.Popen([sys.executable, "-m", "dcsc_torchrl.cli", "run", "lunarlander", "--quick",
                                f"pretrain.out_dir={tmp_path / 'pre'}", "--out", str(tmp_path / 'res')],
                               stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                               # a child inherits an ignored SIGINT (from an earlier test's workers, or a
                               # shell's background job): restore the default, as a terminal has it
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []
    for line in process.stderr:  # wait until it is working, then press Ctrl-C
        seen.append(line)
        if "pretraining seed 0" in line:
            break
    process.send_signal(signal.SIGINT)
    rest = process.communicate(timeout=120)[1]
    err = "".join(seen) + rest
    assert process.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "dcsc: interrupted"


def test_the_cli_module_imports_no_heavy_library_at_module_level():
    assert not hasattr(cli, "torch") and not hasattr(cli, "shared_control")


def test_the_errors_shown_in_docs_cli_md_are_the_ones_printed(capsys, tmp_path, monkeypatch):
    import re
    import shlex

    text = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    examples = re.findall(r"^ +\$ dcsc (.+)\n +(.+)$", text, flags=re.M)
    assert len(examples) >= 4
    monkeypatch.chdir(tmp_path)
    for command, shown in examples:
        try:
            code = main(shlex.split(command))
        except SystemExit as exit_info:
            code = exit_info.code
        assert code == 2, command
        assert one_line_error(capsys) == shown.strip(), command


@pytest.mark.parametrize("quick", [False, True])
def test_dcsc_pretrain_writes_where_dcsc_run_reads(quick, monkeypatch, capsys):
    seen = {}

    def train(cfg, *, resume=False):
        seen["cfg"], seen["resume"] = cfg, resume

    monkeypatch.setitem(machines.PRETRAINING, "uav", train)
    assert main(["pretrain", "uav", *(["--quick"] if quick else []), "seed=2"]) == 0
    run_cfg = load_config(RECIPES / "shared_control_uav.yaml", quick=quick)
    expected = checkpoint_path(run_cfg.pretrain.out_dir, 2)
    cfg = seen["cfg"]
    assert Path(cfg.logger.out_dir) == expected.parent and cfg.seed == 2 and not seen["resume"]
    assert cfg.train.episodes == (load_config(RECIPES / "pretrain_ddpg_uav.yaml", quick=quick).train.episodes)
    assert f"checkpoint in {expected}" in capsys.readouterr().err


def test_dcsc_pretrain_honours_a_logger_out_dir_override_and_out_before_it(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setitem(machines.PRETRAINING, "uav", lambda cfg, *, resume=False: seen.append(cfg.logger.out_dir))
    assert main(["pretrain", "uav", "--quick", f"logger.out_dir={tmp_path / 'mine'}"]) == 0
    assert main(["pretrain", "uav", "--quick", "--out", str(tmp_path / "out"), f"logger.out_dir={tmp_path / 'mine'}"]) == 0
    assert seen == [str(tmp_path / "mine"), str(tmp_path / "out")]


def test_debug_shows_the_real_exception_and_a_bug_is_one_line_exit_1(monkeypatch, capsys):
    with pytest.raises(ConfigError, match="train.episodez"):
        main(["--debug", "pretrain", "lunarlander", "train.episodez=5"])
    monkeypatch.setenv("DCSC_DEBUG", "1")
    with pytest.raises(ConfigError):
        main(["pretrain", "lunarlander", "train.episodes=abc"])
    monkeypatch.delenv("DCSC_DEBUG")

    def bug(args):
        raise RuntimeError("something broke\nover two lines")

    monkeypatch.setitem(cli.COMMANDS, "report", (*cli.COMMANDS["report"][:2], bug))
    assert main(["report"]) == 1
    assert one_line_error(capsys) == ("dcsc: error: RuntimeError: something broke over two lines "
                                      "(run with --debug for the traceback)")
