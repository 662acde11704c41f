"""Tables and figures of the experiments, from the CSV files only (paper Figs. 2-6).

Everything here reads ``episodes.csv`` / ``trace.csv`` as written by the shared-control
recipe, so a figure can be redrawn from a finished run without re-running anything. A
table is read whole or not at all (:func:`read_table`): a file cut mid-row, a ragged or
malformed row and a missing column are refused with the path and line, never summarised
from what could be parsed.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from dcsc_torchrl.config import UsageError  # noqa: E402
from dcsc_torchrl.methods import BEST_CONSTANT, METHODS  # noqa: E402
from dcsc_torchrl.runlog import write_atomic  # noqa: E402
from dcsc_torchrl.task import Task  # noqa: E402

if TYPE_CHECKING:
    from tensordict import TensorDictBase

REPORT_ORDER = [*(name for name, m in METHODS.items() if m.kind != "sweep"), BEST_CONSTANT.name]
"""The rows of the report's tables: every method, the constant sweep by its best beta."""
LEARNED = tuple(name for name, m in METHODS.items() if m.kind in ("learned", "frozen"))


CELL_COLUMNS = ("operator", "pretrain_seed", "method", "phase")
"""The columns every table of a run has: which cell and method a row is of."""
TRACE_COLUMNS = (*CELL_COLUMNS, "seed", "step", "reward", "human_confidence", "machine_confidence",
                 "confidence_ratio")
CALIBRATION_COLUMNS = ("b_m_p10", "b_m_p50", "b_m_p90", "gap_low_b_m", "gap_high_b_m", "spearman_b_m_gap")
NUMBERS = ("pretrain_seed", "group", "seed", "step", "reward", "success", "steps", "path_length", "return",
           "constant_beta", "mean_beta", "human_confidence", "machine_confidence", "confidence_ratio",
           *CALIBRATION_COLUMNS)
"""The columns that hold numbers (an empty cell is a missing one), in whichever table has them."""


class TableError(UsageError):
    """A results table that cannot be read whole: cut short, ragged, malformed or missing a column."""


def read_table(path: str | os.PathLike, columns: Sequence[str] = ()) -> pd.DataFrame:
    """A results CSV, read whole or refused with its path and line.

    Every row must have the header's fields, the file must end with a line break (every
    writer of the project ends it so: a file without one was cut mid-row, by a crash during
    a copy), ``columns`` must be there, and each of :data:`NUMBERS` it has must hold numbers.

    Raises:
        TableError: one line naming the path (and the line or column).
    """
    path = Path(path)
    if not path.is_file():
        raise TableError(f"no table at {path}")
    text = path.read_text(encoding="utf-8", errors="replace")
    if not text.strip():
        raise TableError(f"{path} is empty")
    reader = csv.reader(io.StringIO(text))
    header = next(reader)
    missing = [column for column in columns if column not in header]
    if missing:
        raise TableError(f"{path} has no column {', '.join(missing)} (it was not written by this version of dcsc?)")
    for row in reader:
        if len(row) != len(header):
            raise TableError(f"{path}, line {reader.line_num}: {len(row)} fields, the header has {len(header)}")
    if not text.endswith("\n"):
        raise TableError(f"{path}, line {reader.line_num}: cut short (no line break at the end): the file is not whole")
    frame = pd.read_csv(io.StringIO(text))
    for column in (c for c in NUMBERS if c in frame.columns):
        values = frame[column] if frame[column].dtype == bool else frame[column].replace({"True": 1, "False": 0})
        numbers = pd.to_numeric(values, errors="coerce")
        bad = numbers.isna() & frame[column].notna()
        if bad.any():
            row = int(bad.to_numpy().nonzero()[0][0])
            raise TableError(f"{path}, line {row + 2}: column {column} holds {frame[column].iloc[row]!r}, not a number")
        frame[column] = numbers
    return frame


def episode_table(results_dir: Path, task: Task) -> pd.DataFrame:
    """``episodes.csv`` of a task's results, checked (:func:`read_table`)."""
    return read_table(results_dir / "episodes.csv", (*CELL_COLUMNS, "group", "seed", *task.metrics))


def parse_vector(text: str) -> np.ndarray:
    """A vector as a CSV cell holds it (``"[0.1, -0.2]"``), read as numbers only: no code runs.

    Examples:
        >>> parse_vector("[0.5, nan]").tolist()
        [0.5, nan]
    """
    try:
        return np.array([float(x) for x in str(text).strip().removeprefix("[").removesuffix("]").split(",")])
    except ValueError:
        raise TableError(f"expected a list of numbers such as [0.1, -0.2], got {text!r}") from None


def theta_table(path: Path) -> pd.DataFrame:
    """``theta.csv``, checked (:func:`read_table`), its ``theta`` cells as vectors (``value``)."""
    theta = read_table(path, (*CELL_COLUMNS, "theta"))
    try:
        return theta.assign(value=theta["theta"].map(parse_vector))
    except TableError as err:
        raise TableError(f"{path}: column theta: {err}") from None


def group_size(frame: pd.DataFrame) -> str:
    """The scenarios per validation group of the rows: ``"10"``, ``"2-3"`` for unequal groups, ``"0"``."""
    sizes = frame.groupby("group")["seed"].nunique()
    low, high = (int(sizes.min()), int(sizes.max())) if len(sizes) else (0, 0)
    return str(low) if low == high else f"{low}-{high}"


QUICK_NOTE = ("**A `--quick` run.** Its tiny setting (a few short scenarios) tests the code paths, not the "
              "method: these numbers say nothing about DC-SC.\n")


def method_label(task: Task, method: str) -> str:
    """A method's name in tables and figures (the machine by its pretraining algorithm)."""
    if method == "machine":
        return task.machine_label
    return BEST_CONSTANT.label if method == BEST_CONSTANT.name else METHODS[method].label


Z95 = 1.959963984540054


def mean_ci(values: pd.Series) -> tuple[float, float]:
    """Mean and half-width of its 95% confidence interval (normal approximation)."""
    values = values.astype(float).dropna()
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    half = Z95 * values.std(ddof=1) / math.sqrt(n) if n > 1 else math.nan
    return float(values.mean()), float(half)


def _fmt(mean: float, half: float, metric: str) -> str:
    if math.isnan(mean):
        return "–"
    digits = 2 if metric == "success" else 1
    return f"{mean:.{digits}f} ± {half:.{digits}f}" if not math.isnan(half) else f"{mean:.{digits}f}"


def _methods(frame: pd.DataFrame) -> list[str]:
    return [m for m in REPORT_ORDER if m in set(frame["method"])]


def with_best_constant(frame: pd.DataFrame) -> pd.DataFrame:
    """Replaces the ``constant`` sweep's rows by those of its best beta, as method ``best_constant``.

    The best beta is picked per (operator, pretraining seed) by success rate, ties broken
    by return: an oracle that looks at the very scenarios it is scored on, an upper bound
    for any fixed blend rather than a method.
    """
    if "constant" not in set(frame["method"]):
        return frame
    sweep = frame[frame["method"] == "constant"]
    score = sweep.groupby(["operator", "pretrain_seed", "constant_beta"])[["success", "return"]].mean()
    best = score.sort_values(["success", "return"]).groupby(level=[0, 1]).tail(1).reset_index()
    keep = sweep.merge(best[["operator", "pretrain_seed", "constant_beta"]], on=["operator", "pretrain_seed",
                                                                              "constant_beta"])
    return pd.concat([frame[frame["method"] != "constant"], keep.assign(method="best_constant")], ignore_index=True)


def summary_table(frame: pd.DataFrame, task: Task, by: str | None = None) -> str:
    """A markdown table: one row per method (and ``by`` value), mean ± 95% CI per metric."""
    metrics = task.metrics
    keys = ["method"] + ([by] if by else [])
    header = "| " + " | ".join(keys + [f"{m} (mean ± 95% CI)" for m in metrics] + ["n"]) + " |"
    lines = [header, "|" + "---|" * (len(keys) + len(metrics) + 1)]
    for method in _methods(frame):
        sub = frame[frame["method"] == method]
        groups = sorted(sub[by].unique()) if by else [None]
        for value in groups:
            cell = sub if value is None else sub[sub[by] == value]
            stats = [_fmt(*mean_ci(cell[m]), m) for m in metrics]
            label = [method_label(task, method)] + ([str(value)] if by else [])
            lines.append("| " + " | ".join(label + stats + [str(len(cell))]) + " |")
    return "\n".join(lines)


def success_grid(frame: pd.DataFrame, task: Task) -> str:
    """Success in percent, one row per method and one column per operator preset, ``mean ± 95% CI``
    over the pooled pretraining seeds (the compact table of README and docs/records/results.md)."""
    operators = sorted(frame["operator"].unique())
    lines = ["| method | " + " | ".join(operators) + " |", "|---|" + "---:|" * len(operators)]
    for method in _methods(frame):
        cells = []
        for operator in operators:
            mean, half = mean_ci(frame.loc[(frame["method"] == method) & (frame["operator"] == operator), "success"])
            cells.append("–" if math.isnan(mean) else f"{100 * mean:.0f}" + (
                "" if math.isnan(half) else f" ± {100 * half:.0f}"))
        lines.append(f"| {method_label(task, method)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_task_summary(results_dir: str | os.PathLike, task: Task, main_operator: str, main_seed: int, *,
                       quick: bool = False) -> Path:
    """``summary.md`` of one task: the paper's table (main operator, first pretraining seed),
    its per-group table, and the beyond-the-paper tables (every preset, every seed).

    A ``quick`` run's summary says first that its numbers test the code paths, not the method.
    """
    results_dir = Path(results_dir)
    episodes = episode_table(results_dir, task)
    val = with_best_constant(episodes[episodes["phase"] == "validation"])
    main = val[(val["operator"] == main_operator) & (val["pretrain_seed"] == main_seed)]
    setting = "a quick run's tiny setting" if quick else "the paper's setting"
    parts = [
        f"# {task.name}: validation results\n",
        *([QUICK_NOTE] if quick else []),
        f"Operator `{main_operator}`, pretraining seed {main_seed}, {main['seed'].nunique()} scenarios in groups "
        f"of {group_size(main)} ({setting}). Mean ± 95% CI (normal approximation).\n",
        summary_table(main, task),
        "\n## Per group of scenarios (paper Figs. 2 / 4)\n",
        summary_table(main, task, by="group"),
        "\n## Every operator preset, pooled over pretraining seeds\n",
        "Success (%), mean ± 95% CI:\n",
        success_grid(val, task),
        "",
        summary_table(val, task, by="operator"),
        "\n## Every pretraining seed, pooled over presets\n",
        summary_table(val, task, by="pretrain_seed"),
        *_constant_sweep_section(episodes, task),
        *_overlap_section(val),
        *_theta_section(results_dir),
        *_calibration_section(results_dir),
        "",
    ]
    path = results_dir / "summary.md"
    text = "\n".join(parts)
    write_atomic(path, lambda f: f.write(text))
    return path


def constant_sweep(episodes: pd.DataFrame) -> pd.DataFrame:
    """Validation success and return per (operator, constant beta), pooled over pretraining seeds."""
    sweep = episodes[(episodes["phase"] == "validation") & (episodes["method"] == "constant")]
    if sweep.empty:  # a run without the constant method has no constant_beta column
        return pd.DataFrame(columns=["operator", "constant_beta", "success", "return"])
    return sweep.groupby(["operator", "constant_beta"])[["success", "return"]].mean().reset_index()


def _constant_sweep_section(episodes: pd.DataFrame, task: Task) -> list[str]:
    sweep = constant_sweep(episodes)
    if sweep.empty:
        return []
    table = sweep.pivot(index="operator", columns="constant_beta", values="success")
    betas = list(table.columns)
    learned = episodes[(episodes["phase"] == "validation") & episodes["method"].isin(LEARNED)]
    by_method = learned.groupby(["operator", "method"])[["success", "mean_beta"]].mean() if len(learned) else None
    header = "| operator | " + " | ".join(f"β={b:g}" for b in betas) + " | " + " | ".join(
        f"{method_label(task, m)} (mean β)" for m in LEARNED) + " |"
    lines = ["\n## Success against a constant β (validation, pooled over pretraining seeds)\n",
             "Every β of the sweep on the same scenarios; the learned arbiters' success with the mean β "
             "they gave the machine. The best constant is an oracle (chosen on the scenarios it is "
             "scored on).\n", header, "|" + "---|" * (1 + len(betas) + len(LEARNED))]
    for operator, row in table.iterrows():
        cells = [f"{row[b]:.2f}" for b in betas]
        for method in LEARNED:
            if by_method is not None and (operator, method) in by_method.index:
                success, beta = by_method.loc[(operator, method)]
                cells.append(f"{success:.2f} ({beta:.2f})")
            else:
                cells.append("–")
        lines.append(f"| {operator} | " + " | ".join(cells) + " |")
    return lines


def partner_overlap(validation: pd.DataFrame) -> pd.DataFrame:
    """Per operator, the share of scenarios each partner lands alone, both land and either lands.

    Pairs the ``operator`` and ``machine`` rows of the same (operator, pretraining seed,
    scenario). ``either`` is an oracle's score: handing each whole episode to a partner
    that succeeds on it alone (knowing the outcome) reaches it, so an arbiter above it
    must combine the partners *within* an episode, and a target above it cannot be met by
    choosing whom to trust per episode.
    """
    alone = validation[validation["method"].isin(["operator", "machine"])]
    wide = alone.pivot_table(index=["operator", "pretrain_seed", "seed"], columns="method", values="success")
    if not {"operator", "machine"} <= set(wide.columns):
        return pd.DataFrame(columns=["operator", "machine", "both", "either", "scenarios"])
    wide = wide.dropna()
    human, machine = wide["operator"] > 0, wide["machine"] > 0
    shares = pd.DataFrame({"operator": human, "machine": machine, "both": human & machine,
                           "either": human | machine}).astype(float)
    grouped = shares.groupby(level="operator")
    return grouped.mean().assign(scenarios=grouped.size())


def _overlap_section(validation: pd.DataFrame) -> list[str]:
    overlap = partner_overlap(validation)
    if overlap.empty:
        return []
    lines = ["\n## Whether the partners complement each other (validation, pooled over pretraining seeds)\n",
             "Success of each partner alone on the same scenarios, of both, and of either: *either* is an "
             "oracle that hands each whole episode to a partner that lands it alone. Above it an arbiter "
             "must combine the partners within an episode.\n",
             "| operator | operator alone | machine alone | both | either (per-scenario oracle) | scenarios |",
             "|---|---|---|---|---|---|"]
    for operator, row in overlap.iterrows():
        shares = " | ".join(f"{row[c]:.2f}" for c in ("operator", "machine", "both", "either"))
        lines.append(f"| {operator} | {shares} | {int(row['scenarios'])} |")
    return lines


def _theta_section(results_dir: Path) -> list[str]:
    path = results_dir / "theta.csv"
    if not path.exists():
        return []
    theta = theta_table(path)
    if theta.empty:
        return []
    lines = ["\n## θ over the online updates (first / after collaboration / last, mean over cells)\n",
             "| method | updates per cell (collaboration / validation) | θ first | θ after collaboration | θ last |",
             "|---|---|---|---|---|"]
    for method, sub in theta.groupby("method", sort=False):
        cells = list(sub.groupby(["operator", "pretrain_seed"]))
        def pick(frame, phase=None, last=True):
            part = frame if phase is None else frame[frame["phase"] == phase]
            return part["value"].iloc[-1 if last else 0] if len(part) else np.full_like(frame["value"].iloc[0], np.nan)
        first = np.mean([pick(c, last=False) for _, c in cells], axis=0)
        collab = np.mean([pick(c, "collaboration") for _, c in cells], axis=0)
        last = np.mean([pick(c) for _, c in cells], axis=0)
        n_collab = np.mean([(c["phase"] == "collaboration").sum() for _, c in cells])
        n_val = np.mean([(c["phase"] == "validation").sum() for _, c in cells])
        fmt = lambda v: ", ".join("–" if np.isnan(x) else f"{x:.3f}" for x in np.atleast_1d(v))  # noqa: E731
        lines.append(f"| {method} | {n_collab:.0f} / {n_val:.0f} | {fmt(first)} | {fmt(collab)} | {fmt(last)} |")
    return lines


def _calibration_section(results_dir: Path) -> list[str]:
    path = results_dir / "calibration.csv"
    if not path.exists():
        return []
    columns = list(CALIBRATION_COLUMNS)
    calibration = read_table(path, ["operator", *columns])
    pooled = calibration.groupby("operator")[columns].mean()
    lines = ["\n## Machine confidence on the calibration frames (operator alone, mean over seeds)\n",
             "b_m percentiles with the calibrated unit, and the critic's Q(s, a_machine) − Q(s, a_operator) "
             "on the quarter of frames with the lowest and the highest b_m (a working b_m marks worse machine "
             "actions with low confidence: gap_low < gap_high, Spearman > 0).\n",
             "| operator | " + " | ".join(columns) + " |", "|" + "---|" * (len(columns) + 1)]
    for operator, row in pooled.iterrows():
        lines.append(f"| {operator} | " + " | ".join(f"{row[c]:.3g}" for c in columns) + " |")
    return lines


def save_figure(fig: plt.Figure, path: Path, *, tight: bool = True) -> Path:
    """Writes ``fig`` to ``path`` as a PNG, atomically, and closes it."""
    if tight:
        fig.tight_layout()
    write_atomic(path, lambda f: fig.savefig(f, dpi=110, format="png"), binary=True)
    plt.close(fig)
    return path


def plot_performance(frame: pd.DataFrame, task: Task, path: Path, title: str) -> Path:
    """Figs. 2 / 4: success rate, steps or path length, and return per group of scenarios."""
    methods = _methods(frame)
    groups = sorted(frame["group"].unique())
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    width = 0.8 / max(len(methods), 1)
    for metric, ax in zip(task.metrics, axes, strict=True):
        for i, method in enumerate(methods):
            sub = frame[frame["method"] == method]
            stats = [mean_ci(sub[sub["group"] == g][metric]) for g in groups]
            means = [s[0] for s in stats]
            errs = [0 if math.isnan(s[1]) else s[1] for s in stats]
            ax.bar(np.arange(len(groups)) + i * width - 0.4 + width / 2, means, width, yerr=errs, capsize=2,
                   label=method_label(task, method))
        ax.set_xticks(np.arange(len(groups)), [f"group {g}" for g in groups])
        ax.set_xlabel(f"scenario group ({group_size(frame)} scenarios each)")
        ax.set_ylabel({"success": "success rate", "steps": "average steps", "path_length": "average path length",
                       "return": "average cumulative reward"}[metric])
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_confidence(trace: pd.DataFrame, task: Task, path: Path, title: str, method: str = "dcsc_centred") -> Path:
    """Figs. 3a / 6a: human and machine confidence, and beta, along a learned arbiter's episode."""
    if method not in set(trace["method"]):
        method = "dcsc"
    dcsc = trace[trace["method"] == method]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    top.plot(dcsc["step"], dcsc["human_confidence"], label="human confidence $b^h$")
    top.plot(dcsc["step"], dcsc["machine_confidence"], label="machine confidence $b^m$")
    top.set_ylabel("confidence")
    top.set_ylim(-0.02, 1.02)
    top.legend()
    top.grid(alpha=0.3)
    betas = [c for c in dcsc.columns if c.startswith("beta")]
    for column in betas:
        bottom.plot(dcsc["step"], dcsc[column], label=column.replace("beta", "β").replace("_", " "))
    bottom.plot(dcsc["step"], dcsc["confidence_ratio"], "--", alpha=0.7, label="confidence ratio $b_t$")
    bottom.set_xlabel("step")
    bottom.set_ylabel("machine authority β")
    bottom.legend()
    bottom.grid(alpha=0.3)
    fig.suptitle(f"{title}, {method_label(task, method)}")
    return save_figure(fig, path)


def plot_constant_sweep(episodes: pd.DataFrame, task: Task, path: Path, title: str) -> Path:
    """Success against a constant beta, one panel per operator, with the learned arbiters' points."""
    sweep = constant_sweep(episodes)
    operators = sorted(sweep["operator"].unique())
    learned = episodes[(episodes["phase"] == "validation") & episodes["method"].isin(LEARNED)]
    fig, axes = plt.subplots(1, len(operators), figsize=(4 * len(operators), 3.6), squeeze=False)
    markers = {"dcsc": "s", "dcsc_centred": "o", "dcsc_frozen": "^"}
    for ax, operator in zip(axes[0], operators, strict=True):
        sub = sweep[sweep["operator"] == operator]
        ax.plot(sub["constant_beta"], sub["success"], "-", color="gray", label="constant β")
        for method, group in learned[learned["operator"] == operator].groupby("method"):
            ax.plot(group["mean_beta"].mean(), group["success"].mean(), markers.get(method, "x"), ms=8,
                    label=method_label(task, method))
        ax.set_title(f"operator '{operator}'")
        ax.set_xlabel("machine authority β")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success rate")
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_theta(theta: pd.DataFrame, path: Path, title: str) -> Path:
    """theta over the online updates of every cell, one panel per learned arbiter (and dimension);
    ``theta`` as :func:`theta_table` reads it."""
    methods = list(dict.fromkeys(theta["method"]))
    fig, axes = plt.subplots(1, len(methods), figsize=(5 * len(methods), 3.6), squeeze=False)
    dims = ("ρ", "σ", "τ")
    for ax, method in zip(axes[0], methods, strict=True):
        for (operator, seed), cell in theta[theta["method"] == method].groupby(["operator", "pretrain_seed"]):
            values = np.stack(cell["value"].to_list())
            for d in range(values.shape[1]):
                label = f"{operator}/{seed}" + (f" θ_{dims[d]}" if values.shape[1] > 1 else "")
                ax.plot(np.arange(1, len(values) + 1), values[:, d], lw=1, label=label)
            split = (cell["phase"] == "collaboration").sum()
            ax.axvline(split, color="gray", ls=":", lw=0.8)
        ax.set_title(method)
        ax.set_xlabel("online update (dotted: collaboration ends)")
        ax.set_ylabel("θ")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=6, ncol=2)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_state_beta(frames: TensorDictBase, task: Task, path: Path, title: str) -> Path | None:
    """The machine's authority over the state: each frame of ``frames`` (``observation``,
    ``beta``) at the task's :attr:`~dcsc_torchrl.task.Task.state_coordinates`, coloured by beta;
    ``None`` for a task without them."""
    if task.state_coordinates is None:
        return None
    coordinates = task.state_coordinates(frames["observation"].reshape(-1, frames["observation"].shape[-1]))
    (x_name, x), (y_name, y) = coordinates.items()
    beta = frames["beta"].reshape(x.shape[0], -1).mean(-1)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    points = ax.scatter(x.numpy(), y.numpy(), c=beta.numpy(), s=2, cmap="coolwarm", vmin=0.0, vmax=1.0)
    fig.colorbar(points, ax=ax, label="β (the machine's share)")
    ax.set_xlabel(x_name)
    ax.set_ylabel(y_name)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)


def plot_authority(trace: pd.DataFrame, task: Task, path: Path, title: str) -> Path:
    """Figs. 3b / 6b: the machine's, the operator's and the shared action along DC-SC's episode."""
    method = "dcsc_centred" if "dcsc_centred" in set(trace["method"]) else "dcsc"
    dcsc = trace[trace["method"] == method]
    if task.discrete:
        fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True)
        for ax, who in zip(axes, ("machine", "operator", "shared"), strict=True):
            ax.step(dcsc["step"], dcsc[f"{who}_action"], where="post", label=f"{who} action")
            ax.set_yticks([0, 1, 2, 3], ["noop", "left", "main", "right"])
            ax.set_ylabel(who)
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
    else:
        dims = task.action_names
        fig, axes = plt.subplots(len(dims), 1, figsize=(9, 7), sharex=True)
        for ax, dim, label in zip(axes, dims, task.action_labels, strict=True):
            for who in ("machine", "operator", "shared"):
                ax.plot(dcsc["step"], dcsc[f"{who}_{dim}"], label=who, lw=2 if who == "shared" else 1)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    axes[-1].set_xlabel("step")
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_reward_over_time(trace: pd.DataFrame, task: Task, path: Path, title: str) -> Path:
    """Fig. 5a: cumulative reward along the traced scenario, per method."""
    fig, ax = plt.subplots(figsize=(8, 4.2))
    for method in _methods(trace):
        sub = trace[trace["method"] == method]
        ax.plot(sub["step"], sub["reward"].cumsum(), label=method_label(task, method))
    ax.set_xlabel("step")
    ax.set_ylabel("cumulative reward")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


def plot_uav_trajectories(trace: pd.DataFrame, scenario_seed: int, path: Path, title: str,
                          label: Callable[[str], str]) -> Path:
    """Fig. 5b: the 3-D paths of every method through the traced scenario, each named by ``label``."""
    import torch

    from dcsc_torchrl.envs.uav import sample_scenario
    from dcsc_torchrl.envs.uav_plot import plot_uav_episode

    scenario = sample_scenario(scenario_seed)
    paths = {}
    for method in _methods(trace):
        sub = trace[trace["method"] == method]
        positions = sub[["position_x", "position_y", "position_z"]].to_numpy()
        paths[method] = np.concatenate([scenario.start.reshape(1, 3).numpy(), positions])
    main = "dcsc" if "dcsc" in paths else next(iter(paths))
    fig = plot_uav_episode(torch.as_tensor(paths[main]), scenario.obstacle_params, scenario.goal,
                           title=title, label=label(main))
    ax = fig.axes[0]
    styles = {"machine": ("black", "--"), "operator": ("saddlebrown", ":"), "hula": ("magenta", "-.")}
    for method, points in paths.items():
        if method != main:
            color, style = styles.get(method, ("gray", "-"))
            ax.plot(points[:, 0], points[:, 1], points[:, 2], color=color, ls=style, lw=1.8,
                    label=label(method))
    ax.legend(fontsize=8)
    return save_figure(fig, path, tight=False)


def write_task_figures(results_dir: str | os.PathLike, task: Task, main_operator: str, main_seed: int) -> list[Path]:
    """Every figure of one task into ``results_dir`` (PNG)."""
    results_dir = Path(results_dir)
    episodes = episode_table(results_dir, task)
    trace = read_table(results_dir / "trace.csv", TRACE_COLUMNS)
    val = with_best_constant(episodes[(episodes["phase"] == "validation") & (episodes["operator"] == main_operator)
                                      & (episodes["pretrain_seed"] == main_seed)])
    trace = trace[trace["phase"] == "validation"]
    name = task.title
    paths = [
        plot_performance(val, task, results_dir / "fig_performance.png",
                         f"{name}: performance per scenario group (operator '{main_operator}')"),
        plot_confidence(trace, task, results_dir / "fig_confidence.png", f"{name}: confidence and authority"),
        plot_authority(trace, task, results_dir / "fig_actions.png", f"{name}: machine / operator / shared actions"),
        plot_reward_over_time(trace, task, results_dir / "fig_reward.png", f"{name}: reward over time, scenario 0"),
    ]
    if "dcsc_state" in set(trace["method"]):  # the state-dependent arbiter's own episode: beta frame by frame
        paths.append(plot_confidence(trace, task, results_dir / "fig_confidence_state.png",
                                     f"{name}: confidence and authority", method="dcsc_state"))
    if len(constant_sweep(episodes)):  # the validation sweep (calibration blends are constants too)
        paths.append(plot_constant_sweep(episodes, task, results_dir / "fig_constant_beta.png",
                                         f"{name}: success against a constant β (validation)"))
    if (results_dir / "theta.csv").exists() and (results_dir / "theta.csv").stat().st_size > 1:
        theta = theta_table(results_dir / "theta.csv")
        if len(theta):
            paths.append(plot_theta(theta, results_dir / "fig_theta.png", f"{name}: θ over the online updates"))
    if task.plot_trajectories is not None:
        paths.append(task.plot_trajectories(trace, int(trace["seed"].iloc[0]), results_dir / "fig_trajectory.png",
                                            f"{name}: trajectories, scenario 0", partial(method_label, task)))
    return paths
