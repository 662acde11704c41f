"""A task's results folder: what a run writes there, its record of the config, and the lock
that keeps one run at a time in it (resume, ``--fresh``; docs/cli.md)."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from dcsc_torchrl.config import (
    ConfigError,
    UsageError,
    config_diff,
    warn,
)
from dcsc_torchrl.runlog import write_atomic

TABLES = ("episodes", "trace", "theta", "calibration")


RUN_RECORD = "run_config.yaml"


OUTPUTS = (*(f"{name}.csv" for name in TABLES), "summary.md", "failed_cells.csv", "cells", "fig_*.png")
"""What a run writes in ``<out>/<task>/`` (removed by ``--fresh``, with :data:`RUN_RECORD`)."""


def write_csv(rows: list[dict], path: Path) -> None:
    """All rows so far, written atomically (:func:`~dcsc_torchrl.runlog.write_atomic`: a full disk
    leaves the file as it was, and an error naming it)."""
    write_atomic(path, lambda f: pd.DataFrame(rows).to_csv(f, index=False))


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
        if "files" not in old:  # a record written before it kept the assistants' files
            new.pop("files", None)
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
