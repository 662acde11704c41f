"""One wide CSV table per run, flushed row by row, and its learning-curve figure."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import pandas as pd


class RunLog:
    """Appends rows to a CSV through pandas; every append is on disk when it returns.

    The column order is fixed by the first row (or ``columns``); a run that stops halfway
    keeps every row written. A resumed run calls :meth:`truncate` to drop the rows logged
    after its checkpoint, so the resumed table equals an uninterrupted one.

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
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def append(self, row: Mapping[str, object]) -> None:
        unknown = set(row) - set(self.columns)
        if unknown:
            raise KeyError(f"columns {sorted(unknown)} are not in this log's columns {self.columns}")
        for key, value in row.items():
            if isinstance(value, float) and math.isnan(value):
                raise ValueError(f"refusing to log NaN for column {key!r}")
        frame = pd.DataFrame([{c: row.get(c) for c in self.columns}], columns=self.columns)
        header = not self.path.exists() or self.path.stat().st_size == 0
        with open(self.path, "a", newline="") as f:
            frame.to_csv(f, header=header, index=False)
            f.flush()
            os.fsync(f.fileno())

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
