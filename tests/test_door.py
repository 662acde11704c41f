"""Nothing silently wrong (issue #37): every bad config, option or file is refused at the door.

"At the door" means before any frame is stepped or any folder is written: each case below
is a command line, the exit code (2) and what its one line on stderr must name (the key,
the value, the file), with nothing written in the folder it ran in. The cases that are not
mistakes (a repeated operator, a second folder, another working directory) assert the
behaviour a user expects instead. Only :func:`quick_run` runs cells (one tiny cell with the
shipped machine); every other test stops at the door or reads its folder.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from dcsc_torchrl import report, runlog
from dcsc_torchrl.checkpoint import FORMAT_VERSION, checkpoint_path, save_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.config import NULLABLE, load_config
from dcsc_torchrl.recipes import grid
from dcsc_torchrl.recipes.configs import RECIPES_DIR as RECIPES
from dcsc_torchrl.recipes.folder import RUN_RECORD, prepare_results
from dcsc_torchrl.runlog import RunLog, write_atomic
from dcsc_torchrl.tasks import get_task

LUNAR = RECIPES / "shared_control_lunarlander.yaml"
TINY = ["pretrain.shipped=true", "pretrain.seeds=[0]", "scenarios.operator_runs=1", "scenarios.machine_alone_runs=1",
        "scenarios.collaboration_runs=1", "scenarios.validation_scenarios=2", "protocol.group_size=1",
        "protocol.max_steps=20"]


def exit_code(argv: list[str]) -> int:
    """``dcsc argv``'s exit code, argparse's own errors included."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def quick_argv(out: Path, *extra: str) -> list[str]:
    """A one-cell ``dcsc run lunarlander --quick`` with the shipped machine, two methods, tiny episodes."""
    return ["run", "lunarlander", "--quick", "--out", str(out), "--methods", "machine", "dcsc", *TINY, *extra]


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[Path, str]:
    """The operator, the methods and the pretraining seed each given twice, into an --out with a
    space and accents: (the task folder, stderr)."""
    out = tmp_path_factory.mktemp("door") / "résultats d'été"
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main([*quick_argv(out, "--operators", "expert", "expert"), "--methods", "machine", "dcsc", "dcsc",
                     "pretrain.seeds=[0,0]"])
    assert code == 0, err.getvalue()
    return out / "lunarlander", err.getvalue()


# -- refused at the door: one line naming the key or value, exit 2, nothing written ------------
REFUSED = [
    # the cases of issue #37
    (["run", "lunarlander", "operator.main=nobody"], ["operator.main: unknown operator preset 'nobody'", "expert"]),
    (["run", "lunarlander", "task=uav"], ["task is fixed by the config file ('lunarlander')", "'uav'"]),
    (["play", "lunarlander", "--episodes", "-1"], ["--episodes", "expected an integer >= 1, got -1"]),
    (["run", "lunarlander", "online.gamma=1.5"], ["online.gamma: expected a value in [0, 1], got 1.5"]),
    (["run", "uav", "online.tau=2"], ["online.tau: expected a value in (0, 1], got 2"]),
    (["run", "lunarlander", "machine.num_samples=1"], ["machine.num_samples: expected a value >= 2, got 1"]),
    (["run", "lunarlander", "arbiter.hula_threshold=-1"], ["arbiter.hula_threshold: expected a value >= 0, got -1"]),
    (["run", "lunarlander", "protocol.max_steps=abc"], ["protocol.max_steps: expected an int, got 'abc'"]),
    (["run", "lunarlander", "arbiter.hula_threshold=abc"], ["arbiter.hula_threshold: expected a number, got 'abc'"]),
    (["run", "lunarlander", "pretrain.seeds=[]"], ["pretrain.seeds: expected at least one entry, got []"]),
    (["run", "uav", "operator.presets=[]"], ["operator.presets: expected at least one entry, got []"]),
    (["run", "lunarlander", "pretrain.seeds=[-1]"], ["pretrain.seeds: expected a value >= 0 for every entry, got [-1]"]),
    # more of an adversary's
    (["run", "lunarlander", "online.theta_lr=.nan"], ["online.theta_lr: expected a finite number, got nan"]),
    (["run", "lunarlander", "online.critic_lr=.inf"], ["online.critic_lr: expected a finite number, got inf"]),
    (["run", "lunarlander", "warmup.blend_betas=[.nan]"], ["warmup.blend_betas: expected a finite number"]),
    (["run", "lunarlander", "--quick", "protocol.group_size=3"],
     ["protocol.group_size: expected a divisor of scenarios.validation_scenarios (4), got 3"]),
    (["run", "lunarlander", "--quick", "protocol.group_size=10"], ["protocol.group_size", "(4), got 10"]),
    (["run", "uav", "arbiter.constant_betas=[-0.1,0.5]"], ["arbiter.constant_betas: expected a value in [0, 1]"]),
    (["run", "lunarlander", "arbiter=1"], ["arbiter: expected a group of keys", "got 1"]),
    (["run", "lunarlander", "seed={a: 1}"], ["seed: expected an int, got {'a': 1}"]),
    (["run", "lunarlander", "scenarios.first_validation_seed=9990"],
     ["scenarios.first_validation_seed 9990: the validation seeds 9990..10039 meet the calibration seeds"]),
    (["run", "lunarlander", "scenarios.operator_runs=10001"],
     ["scenarios.operator_runs 10001", "meet the collaboration seeds 20000..20019"]),
    (["run", "lunarlander", "threads=0"], ["threads: expected a value >= 1, got 0"]),
    (["run", "lunarlander", "seed=-3"], ["seed: expected a value >= 0, got -3"]),
    (["run", "lunarlander", "pretrain.recipe=[train.episodez=3]"],
     ["pretrain.recipe: unknown key train.episodez in pretrain_a2c_lunarlander.yaml"]),
    (["run", "lunarlander", "pretrain.recipe=[optim.lr=0]"], ["pretrain.recipe: optim.lr: expected a value > 0"]),
    (["run", "lunarlander", "--methods", "machine", "nothing"], ["--methods: unknown method 'nothing'"]),
    (["sweep", "operators=[expert,nobody]"], ["operators: unknown operator preset 'nobody'"]),
    (["sweep", "tasks=[]"], ["tasks: expected at least one entry"]),
    (["sweep", "methods=[dcsc,nothing]"], ["methods: unknown method 'nothing'"]),
    (["sweep", "lunarlander.task=uav"], ["task is fixed by the config file"]),
    (["sweep", "pretrain_seeds=[-2]"], ["pretrain_seeds: expected a value >= 0 for every entry"]),
    (["sweep", "ray.address=[a]"], ["ray.address: expected a string, got ['a']"]),
    (["pretrain", "uav", "loss.gamma=1.01"], ["loss.gamma: expected a value in [0, 1], got 1.01"]),
    (["pretrain", "lunarlander", "network.actor_dropout=1"], ["network.actor_dropout: expected a value in [0, 1)"]),
    (["play", "lunarlander", "--seed", "-1"], ["--seed", "expected an integer >= 0, got -1"]),
    (["play", "lunarlander", "--participant", " "], ["--participant", "expected a name on one line"]),
    (["report", "--out", "missing"], ["--out missing: no results there", "lunarlander/episodes.csv"]),
]


@pytest.mark.parametrize("argv, needles", REFUSED, ids=[" ".join(argv) for argv, _ in REFUSED])
def test_a_bad_input_is_refused_at_the_door_in_one_line(argv, needles, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert exit_code(argv) == 2
    line = one_line(capsys)
    for needle in needles:
        assert needle in line, line
    assert list(tmp_path.iterdir()) == []


def test_every_null_key_of_every_recipe_has_a_declared_type():
    for path in RECIPES.glob("*.yaml"):
        tree = yaml.safe_load(path.read_text())
        tree.pop("quick", None)
        nulls = [key for key, value in pd.json_normalize(tree, sep=".").iloc[0].items() if value is None]
        assert set(nulls) <= set(NULLABLE), (path.name, nulls)


def test_a_repeated_entry_of_a_list_of_things_run_once_is_dropped_with_a_warning(capsys):
    cfg = load_config(LUNAR, ["arbiter.constant_betas=[0.5,0.5,1.0]", "operator.presets=[noisy,noisy]"])
    assert list(cfg.arbiter.constant_betas) == [0.5, 1.0] and list(cfg.operator.presets) == ["noisy"]
    err = capsys.readouterr().err
    assert "arbiter.constant_betas lists 0.5 more than once" in err and "operator.presets lists noisy" in err


# -- --out where nothing can be written --------------------------------------------------------
@pytest.mark.parametrize("command", [["run", "lunarlander"], ["sweep"], ["reproduce"], ["pretrain", "uav"],
                                     ["play", "lunarlander", "--assist", "none"]])
def test_an_out_that_is_a_file_is_one_line_naming_it(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a cell ran"))
    (tmp_path / "taken").write_text("a file")
    assert exit_code([*command, "--out", "taken"]) == 2
    line = one_line(capsys)
    assert "--out " in line and "taken is a file, not a folder" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_an_out_on_a_read_only_location_is_one_line_naming_it(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    readonly = Path("/sys/dcsc-results")  # sysfs takes no new entry, even from root
    try:
        os.rmdir(tempfile.mkdtemp(dir="/sys"))
        pytest.skip("/sys takes new entries here")
    except OSError:
        pass
    assert exit_code(["run", "lunarlander", "--out", str(readonly), "pretrain.shipped=true",
                      "pretrain.seeds=[0]"]) == 2
    assert f"--out {readonly / 'lunarlander'}: cannot write in /sys" in one_line(capsys)


# -- checkpoints of another version, or not a machine's ---------------------------------------
CHECKPOINTS = [
    ({"format_version": FORMAT_VERSION, "task": "lunarlander", "state": {}}, "lacks config.network, state.actor"),
    ({"format_version": 0, "task": "lunarlander", "config": {}}, "is of format version 0, this dcsc-torchrl reads"),
    ({"task": "lunarlander", "config": {}}, "is of format version None"),
    ({"format_version": FORMAT_VERSION + 1, "task": "lunarlander"}, f"format version {FORMAT_VERSION + 1}"),
    ({"weights": torch.zeros(2)}, "is not a dcsc-torchrl checkpoint"),
]


@pytest.mark.parametrize("data, needle", CHECKPOINTS)
@pytest.mark.parametrize("command", ["play", "run"])
def test_a_checkpoint_of_another_version_is_one_line_naming_it(command, data, needle, tmp_path, capsys):
    path = checkpoint_path(tmp_path / "pre", 0)
    path.parent.mkdir(parents=True)
    torch.save(data, path)
    argv = (["play", "lunarlander", "--checkpoint", str(path), "--out", str(tmp_path / "play")] if command == "play"
            else ["run", "lunarlander", "--out", str(tmp_path / "res"), f"pretrain.out_dir={tmp_path / 'pre'}",
                  "pretrain.seeds=[0]"])
    assert exit_code(argv) == 2
    line = one_line(capsys)
    assert str(path) in line and needle in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pre"]


def test_a_machine_checkpoint_written_by_save_checkpoint_without_a_network_is_refused(tmp_path, capsys):
    path = save_checkpoint(tmp_path / "ckpt.pt", task="lunarlander", payload={"state": {"actor": {}}})
    assert exit_code(["play", "lunarlander", "--checkpoint", str(path), "--out", str(tmp_path / "p")]) == 2
    assert "lacks config.network, state.qvalue" in one_line(capsys)


# -- dcsc report: a table read whole or not at all --------------------------------------------
def without_phase(text: str) -> str:
    header, rest = text.split("\n", 1)
    return header.replace("phase", "stage") + "\n" + rest


def a_word_for_a_number(text: str) -> str:
    header, first, second, rest = text.split("\n", 3)
    cells = second.split(",")
    cells[header.split(",").index("success")] = "yes"
    return "\n".join([header, first, ",".join(cells), rest])


DAMAGES: dict[str, tuple[Callable[[str], str], str]] = {
    "no phase column": (without_phase, "has no column phase"),
    "cut mid-row (a copy that crashed)": (lambda text: text[:-7], "cut short"),
    "a ragged row": (lambda text: text + "1,2,3\n", "3 fields, the header has"),
    "a word for a number": (a_word_for_a_number, "line 3: column success holds 'yes', not a number"),
}


@pytest.mark.parametrize("case", list(DAMAGES))
def test_report_refuses_an_episodes_csv_that_is_not_whole(case, quick_run, tmp_path, capsys):
    task_dir, _ = quick_run
    out = tmp_path / "copy"
    shutil.copytree(task_dir, out / "lunarlander")
    damage, needle = DAMAGES[case]
    episodes = out / "lunarlander" / "episodes.csv"
    episodes.write_text(damage(episodes.read_text()))
    assert exit_code(["report", "--out", str(out)]) == 2
    line = one_line(capsys)
    assert str(episodes) in line and needle in line


def test_report_reads_theta_as_numbers_and_never_runs_a_cell(quick_run, tmp_path, capsys):
    task_dir, _ = quick_run
    shutil.copytree(task_dir, tmp_path / "lunarlander")
    theta = tmp_path / "lunarlander" / "theta.csv"
    frame = pd.read_csv(theta)
    marker = tmp_path / "pwned"
    frame.loc[0, "theta"] = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    frame.to_csv(theta, index=False)
    assert exit_code(["report", "--out", str(tmp_path)]) == 2
    line = one_line(capsys)
    assert str(theta) in line and "column theta" in line and not marker.exists()


def test_the_figure_labels_the_real_group_size(quick_run, monkeypatch):
    task_dir, _ = quick_run
    labels = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path, **_: labels.append(fig.axes[0].get_xlabel()) or path)
    report.write_task_figures(task_dir, get_task("lunarlander"), "expert", 0)
    assert labels[0] == "scenario group (1 scenarios each)"


# -- the behaviour a user expects ---------------------------------------------------------------
def test_a_repeated_operator_seed_or_method_runs_once_with_a_warning(quick_run):
    task_dir, err = quick_run
    assert [p.name for p in (task_dir / "cells").iterdir()] == ["expert-seed0"]
    episodes = pd.read_csv(task_dir / "episodes.csv")
    assert not episodes.duplicated(["operator", "pretrain_seed", "method", "phase", "seed"]).any()
    assert sorted(set(episodes["method"])) == ["dcsc", "machine", "operator"]
    for needle in ("--operators lists expert more than once", "--methods lists dcsc more than once",
                   "pretrain.seeds lists 0 more than once"):
        assert needle in err


def test_a_quick_runs_summary_says_its_numbers_test_the_code_not_the_method(quick_run):
    task_dir, _ = quick_run
    summary = (task_dir / "summary.md").read_text()
    assert summary.splitlines()[2].startswith("**A `--quick` run.**") and "the paper's setting" not in summary
    assert "2 scenarios in groups of 1" in summary and "| nan" not in summary


def test_report_words_a_quick_run_as_its_run_did(quick_run, tmp_path):
    task_dir, _ = quick_run
    shutil.copytree(task_dir, tmp_path / "lunarlander")
    assert exit_code(["report", "--out", str(tmp_path)]) == 0
    assert report.QUICK_NOTE in (tmp_path / "summary.md").read_text()


def test_a_second_run_into_a_folder_in_use_is_refused_and_a_stale_lock_does_not_block(quick_run, monkeypatch,
                                                                                       capsys):
    task_dir, _ = quick_run
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a finished cell ran again"))
    argv = quick_argv(task_dir.parent, "--operators", "expert")
    with open(task_dir / ".lock", "a+") as held:  # what a running `dcsc run` holds
        fcntl.flock(held, fcntl.LOCK_EX)
        assert exit_code(argv) == 2
        line = one_line(capsys)
        assert f"{task_dir} is in use by another dcsc run" in line and "--out" in line
    (task_dir / ".lock").write_text("999999\n")  # left by a killed run: the kernel released its lock
    assert exit_code(argv) == 0


def test_the_same_command_from_another_folder_resumes(quick_run, tmp_path, monkeypatch):
    task_dir, _ = quick_run
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a finished cell ran again"))
    monkeypatch.chdir(tmp_path)
    assert exit_code(quick_argv(task_dir.parent, "--operators", "expert")) == 0
    record = yaml.safe_load((task_dir / RUN_RECORD).read_text())
    assert record["config"]["pretrain"]["out_dir"] == "runs/quick/pretrain_lunarlander"  # as given, not resolved


def test_an_older_record_with_an_absolute_pretrain_folder_still_resumes(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    record = {"config": {"pretrain": {"out_dir": "runs/x"}}, "methods": ["machine"], "cells": ["expert-seed0"]}
    older = {**record, "config": {"pretrain": {"out_dir": str(tmp_path / "runs/x")}}}
    prepare_results(tmp_path / "lunarlander", older, fresh=False)
    prepare_results(tmp_path / "lunarlander", record, fresh=False)


def test_a_folder_where_no_cell_finished_takes_the_corrected_command(tmp_path, capsys):
    task_dir = tmp_path / "lunarlander"
    prepare_results(task_dir, {"config": {"online": {"gamma": 0.9}}, "methods": [], "cells": ["a"]}, fresh=False)
    (task_dir / "cells" / "a").mkdir(parents=True)
    (task_dir / "cells" / "a" / "episodes.csv").write_text("half a cell")
    corrected = {"config": {"online": {"gamma": 0.99}}, "methods": [], "cells": ["a"]}
    prepare_results(task_dir, corrected, fresh=False)
    assert "no cell of its earlier config (config.online.gamma: 0.9 -> 0.99) finished" in capsys.readouterr().err
    assert yaml.safe_load((task_dir / RUN_RECORD).read_text()) == corrected and not (task_dir / "cells").exists()


# -- a disk that fills ------------------------------------------------------------------------------
def full_disk(*_, **__):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_while_gathering_is_one_line_naming_the_file_and_loses_nothing(quick_run, monkeypatch, capsys):
    task_dir, _ = quick_run
    monkeypatch.setattr(grid, "run_cell", lambda *a, **k: pytest.fail("a finished cell ran again"))
    before = (task_dir / "episodes.csv").read_bytes()

    def half_then_full(self, buf=None, *args, **kwargs):
        buf.write("task,operator,pretrain_se")
        full_disk()

    monkeypatch.setattr(pd.DataFrame, "to_csv", half_then_full)
    assert exit_code(quick_argv(task_dir.parent, "--operators", "expert")) == 2
    line = one_line(capsys)
    assert line == f"dcsc: error: cannot use {task_dir / 'episodes.csv'}: No space left on device"
    assert (task_dir / "episodes.csv").read_bytes() == before and not list(task_dir.glob("*.tmp"))


def test_a_full_disk_mid_row_leaves_the_log_as_it_was(tmp_path, monkeypatch):
    log = RunLog(tmp_path / "episodes.csv", ["episode", "return"])
    log.append({"episode": 1, "return": 1.5})
    before = log.path.read_bytes()
    real_write = os.write
    monkeypatch.setattr(runlog.os, "write", lambda fd, data: real_write(fd, bytes(data[:3])) and full_disk())
    with pytest.raises(OSError, match=re.escape(f"No space left on device: '{log.path}'")):
        log.append({"episode": 2, "return": 2.5})
    monkeypatch.setattr(runlog.os, "write", real_write)
    assert log.path.read_bytes() == before
    log.append({"episode": 2, "return": 2.5})
    assert log.read()["episode"].tolist() == [1, 2]


def test_an_atomic_write_that_fails_keeps_the_old_file(tmp_path):
    path = write_atomic(tmp_path / "summary.md", lambda f: f.write("old\n"))
    with pytest.raises(OSError, match=re.escape(str(path))):
        write_atomic(path, lambda f: f.write("new, half") and full_disk())
    assert path.read_text() == "old\n" and list(tmp_path.iterdir()) == [path]


def test_play_refuses_a_folder_whose_csv_has_other_columns(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    (tmp_path / "episodes.csv").write_text("when,who\n1,me\n")
    assert exit_code(["play", "lunarlander", "--assist", "none", "--out", str(tmp_path)]) == 2
    line = one_line(capsys)
    assert str(tmp_path / "episodes.csv") in line and "other columns" in line
