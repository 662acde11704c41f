"""One wide CSV table per run, flushed row by row, its learning-curve figure, progress lines,
and the atomic writer of every results file.

A write that fails (a full disk, a folder made read-only) leaves what was on disk before
as it was and raises an ``OSError`` that names the file: ``dcsc`` reports it in one line.
"""

from __future__ import annotations

import csv
import math
import os
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any, TextIO

import pandas as pd


def _naming(err: OSError, path: Path) -> OSError:
    """``err`` as an ``OSError`` of the same kind naming ``path`` (a failed ``write`` names no file)."""
    return type(err)(err.errno, err.strerror or str(err), str(path)) if err.errno else err


def write_atomic(path: str | os.PathLike, write: Callable[[IO], Any], *, binary: bool = False) -> Path:
    """Writes ``path`` through ``write(file)`` into ``<path>.tmp``, then renames it over ``path``.

    A reader never sees half a file, and a write that fails (a full disk) leaves the old
    file as it was, removes the temporary one and raises an ``OSError`` naming ``path``.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "a.txt"
        >>> write_atomic(path, lambda f: f.write("one line\\n")).read_text()
        'one line\\n'
    """
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp")
    try:
        with open(tmp, "wb") if binary else open(tmp, "w", newline="", encoding="utf-8") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise _naming(err, path) from err
    return path


class Progress:
    """A progress bar on a terminal, a plain line every ``every`` seconds elsewhere.

    ``tqdm(disable=None)`` is silent when stderr is not a terminal (a log file, CI, ``nohup``):
    a long run then prints nothing for minutes. This keeps tqdm's bar on a terminal and
    otherwise writes ``desc: n/total unit (elapsed) postfix`` lines, the first and the last
    always. It has tqdm's ``update`` / ``set_postfix`` / ``close`` and is a context manager.

    Args:
        total: the number of steps.
        desc: what is counted (``"lunarlander cells"``).
        unit: the unit of a step.
        initial: steps done before (a resumed run).
        every: seconds between two plain lines (0: a line per update).
        file: where to write (stderr).

    Examples:
        >>> import io
        >>> out = io.StringIO()
        >>> with Progress(2, "cells", "cell", every=0, file=out) as bar:
        ...     bar.update()
        ...     bar.update()
        >>> out.getvalue().splitlines()[-1].split(" (")[0]
        'cells: 2/2 cell'
    """

    def __init__(self, total: int, desc: str, unit: str = "it", *, initial: int = 0, every: float = 30.0,
                 file: TextIO | None = None) -> None:
        self.total, self.desc, self.unit, self.n, self.every = total, desc, unit, initial, every
        self.file = file if file is not None else sys.stderr
        self.postfix = ""
        self._start = self._last = time.monotonic()
        self._bar: Any = None
        self._closed = False
        if getattr(self.file, "isatty", lambda: False)():
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, file=self.file)
        else:
            self._line()

    def _line(self) -> None:
        elapsed = time.monotonic() - self._start
        postfix = f" {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {self.n}/{self.total} {self.unit} ({elapsed:.0f} s){postfix}", file=self.file,
              flush=True)
        self._last = time.monotonic()
        self._shown = self.n

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif self.n >= self.total or time.monotonic() - self._last >= self.every:
            self._line()

    def set_postfix(self, **values: object) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())
        if self._bar is not None:
            self._bar.set_postfix(values)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.n != self._shown:
            self._line()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunLog:
    """Appends rows to a CSV through pandas; every append is on disk when it returns.

    The column order is fixed by the first row (or ``columns``); a run that stops halfway
    keeps every row written. A resumed run calls :meth:`truncate` to drop the rows logged
    after its checkpoint, so the resumed table equals an uninterrupted one. Nothing is
    written (not even the folder) before the first :meth:`append`, which refuses a file of
    other columns there (:meth:`check_header`) and leaves no half row when a write fails.

    Args:
        path: the CSV file.
        columns: the table's columns, in order.

    Examples:
        >>> import tempfile
        >>> log = RunLog(Path(tempfile.mkdtemp()) / "train.csv", ["episode", "return"])
        >>> log.append({"episode": 1, "return": -120.5})
        >>> log.read()["return"].tolist()
        [-120.5]
    """

    def __init__(self, path: str | os.PathLike, columns: list[str]) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self._checked = False

    def check_header(self) -> None:
        """Refuses a file there whose header is not this log's columns: rows appended to it would
        sit under other columns (a table of another version, another table). The first
        :meth:`append` checks it; a caller may check before any work.

        Raises:
            ValueError: one line naming the file.
        """
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, newline="", encoding="utf-8", errors="replace") as f:
            header = next(csv.reader(f), [])
        if header != self.columns:
            raise ValueError(f"{self.path} has other columns than this log's ({','.join(header)[:80]}): move it "
                             "away, or write to another folder")

    def append(self, row: Mapping[str, object]) -> None:
        """Appends ``row`` (on disk when this returns); a write that fails leaves the file as it was.

        Raises:
            ValueError: the file there has other columns (:meth:`check_header`).
            OSError: the write failed (a full disk), naming the file; no partial row is left.
        """
        if not self._checked:
            self.check_header()
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._checked = True
        unknown = set(row) - set(self.columns)
        if unknown:
            raise KeyError(f"columns {sorted(unknown)} are not in this log's columns {self.columns}")
        for key, value in row.items():
            if isinstance(value, float) and math.isnan(value):
                raise ValueError(f"refusing to log NaN for column {key!r}")
        frame = pd.DataFrame([{c: row.get(c) for c in self.columns}], columns=self.columns)
        size = self.path.stat().st_size if self.path.exists() else 0
        data = memoryview(frame.to_csv(header=size == 0, index=False).encode("utf-8"))
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            while data:
                data = data[os.write(fd, data):]
            os.fsync(fd)
        except OSError as err:
            os.ftruncate(fd, size)  # no half row left for the next append to run on from
            raise _naming(err, self.path) from err
        finally:
            os.close(fd)

    def read(self) -> pd.DataFrame:
        if not self.path.exists():
            return pd.DataFrame(columns=self.columns)
        return pd.read_csv(self.path)

    def truncate(self, column: str, last: int) -> None:
        """Keeps only the rows with ``row[column] <= last`` (atomic rewrite)."""
        frame = self.read()
        kept = frame[frame[column] <= last]
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        kept.to_csv(tmp, index=False)
        os.replace(tmp, self.path)


def plot_learning_curve(
    csv_path: str | os.PathLike,
    png_path: str | os.PathLike,
    *,
    title: str,
    x: str = "episode",
    y: str = "return",
    window: int = 20,
) -> Path:
    """Plots ``y`` against ``x`` from a run's CSV, with a rolling mean, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frame = pd.read_csv(csv_path)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(frame[x], frame[y], alpha=0.35, lw=0.8, label=f"{y} per {x}")
    ax.plot(frame[x], frame[y].rolling(window, min_periods=1).mean(), lw=2, label=f"rolling mean ({window})")
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    png_path = Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return png_path
