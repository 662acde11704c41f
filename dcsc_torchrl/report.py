"""Tables and figures of the experiments, from the CSV files only (paper Figs. 2-6).

Everything here reads ``episodes.csv`` / ``trace.csv`` as written by the shared-control
recipe, so a figure can be redrawn from a finished run without re-running anything.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

METHOD_ORDER = ["machine", "operator", "hula", "dcsc"]
METHOD_LABEL = {"lunarlander": {"machine": "A2C", "operator": "operator", "hula": "HULA", "dcsc": "DC-SC"},
                "uav": {"machine": "DDPG", "operator": "operator", "hula": "HULA", "dcsc": "DC-SC"}}
METRICS = {"lunarlander": ["success", "steps", "return"], "uav": ["success", "path_length", "return"]}
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
    return [m for m in METHOD_ORDER if m in set(frame["method"])]


def summary_table(frame: pd.DataFrame, task: str, by: str | None = None) -> str:
    """A markdown table: one row per method (and ``by`` value), mean ± 95% CI per metric."""
    metrics = METRICS[task]
    keys = ["method"] + ([by] if by else [])
    header = "| " + " | ".join(keys + [f"{m} (mean ± 95% CI)" for m in metrics] + ["n"]) + " |"
    lines = [header, "|" + "---|" * (len(keys) + len(metrics) + 1)]
    for method in _methods(frame):
        sub = frame[frame["method"] == method]
        groups = sorted(sub[by].unique()) if by else [None]
        for value in groups:
            cell = sub if value is None else sub[sub[by] == value]
            stats = [_fmt(*mean_ci(cell[m]), m) for m in metrics]
            label = [METHOD_LABEL[task][method]] + ([str(value)] if by else [])
            lines.append("| " + " | ".join(label + stats + [str(len(cell))]) + " |")
    return "\n".join(lines)


def write_task_summary(results_dir: str | os.PathLike, task: str, main_operator: str, main_seed: int) -> Path:
    """``summary.md`` of one task: the paper's table (main operator, first pretraining seed),
    its per-group table, and the beyond-the-paper tables (every preset, every seed)."""
    results_dir = Path(results_dir)
    episodes = pd.read_csv(results_dir / "episodes.csv")
    val = episodes[episodes["phase"] == "validation"]
    main = val[(val["operator"] == main_operator) & (val["pretrain_seed"] == main_seed)]
    parts = [
        f"# {task}: validation results\n",
        f"Operator `{main_operator}`, pretraining seed {main_seed}, {main['seed'].nunique()} scenarios "
        "(the paper's setting). Mean ± 95% CI (normal approximation).\n",
        summary_table(main, task),
        "\n## Per group of scenarios (paper Figs. 2 / 4)\n",
        summary_table(main, task, by="group"),
        "\n## Every operator preset, pooled over pretraining seeds\n",
        summary_table(val, task, by="operator"),
        "\n## Every pretraining seed, pooled over presets\n",
        summary_table(val, task, by="pretrain_seed"),
        "",
    ]
    path = results_dir / "summary.md"
    path.write_text("\n".join(parts))
    return path


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_performance(frame: pd.DataFrame, task: str, path: Path, title: str) -> Path:
    """Figs. 2 / 4: success rate, steps or path length, and return per group of scenarios."""
    methods = _methods(frame)
    groups = sorted(frame["group"].unique())
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    width = 0.8 / max(len(methods), 1)
    for metric, ax in zip(METRICS[task], axes, strict=True):
        for i, method in enumerate(methods):
            sub = frame[frame["method"] == method]
            stats = [mean_ci(sub[sub["group"] == g][metric]) for g in groups]
            means = [s[0] for s in stats]
            errs = [0 if math.isnan(s[1]) else s[1] for s in stats]
            ax.bar(np.arange(len(groups)) + i * width - 0.4 + width / 2, means, width, yerr=errs, capsize=2,
                   label=METHOD_LABEL[task][method])
        ax.set_xticks(np.arange(len(groups)), [f"group {g}" for g in groups])
        ax.set_xlabel("scenario group (10 scenarios each)")
        ax.set_ylabel({"success": "success rate", "steps": "average steps", "path_length": "average path length",
                       "return": "average cumulative reward"}[metric])
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def plot_confidence(trace: pd.DataFrame, task: str, path: Path, title: str) -> Path:
    """Figs. 3a / 6a: human and machine confidence, and beta, along DC-SC's episode."""
    dcsc = trace[trace["method"] == "dcsc"]
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
    fig.suptitle(title)
    return _save(fig, path)


def plot_authority(trace: pd.DataFrame, task: str, path: Path, title: str) -> Path:
    """Figs. 3b / 6b: the machine's, the operator's and the shared action along DC-SC's episode."""
    dcsc = trace[trace["method"] == "dcsc"]
    if task == "lunarlander":
        fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True)
        for ax, who in zip(axes, ("machine", "operator", "shared"), strict=True):
            ax.step(dcsc["step"], dcsc[f"{who}_action"], where="post", label=f"{who} action")
            ax.set_yticks([0, 1, 2, 3], ["noop", "left", "main", "right"])
            ax.set_ylabel(who)
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
    else:
        fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
        for ax, dim in zip(axes, ("rho", "sigma", "tau"), strict=True):
            for who in ("machine", "operator", "shared"):
                ax.plot(dcsc["step"], dcsc[f"{who}_{dim}"], label=who, lw=2 if who == "shared" else 1)
            ax.set_ylabel({"rho": "ρ0", "sigma": "σ0", "tau": "τ"}[dim])
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    axes[-1].set_xlabel("step")
    fig.suptitle(title)
    return _save(fig, path)


def plot_reward_over_time(trace: pd.DataFrame, task: str, path: Path, title: str) -> Path:
    """Fig. 5a: cumulative reward along the traced scenario, per method."""
    fig, ax = plt.subplots(figsize=(8, 4.2))
    for method in _methods(trace):
        sub = trace[trace["method"] == method]
        ax.plot(sub["step"], sub["reward"].cumsum(), label=METHOD_LABEL[task][method])
    ax.set_xlabel("step")
    ax.set_ylabel("cumulative reward")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return _save(fig, path)


def plot_uav_trajectories(trace: pd.DataFrame, scenario_seed: int, path: Path, title: str) -> Path:
    """Fig. 5b: the 3-D paths of every method through the traced scenario."""
    import torch

    from envs.uav import sample_scenario
    from envs.uav_plot import plot_uav_episode

    scenario = sample_scenario(scenario_seed)
    paths = {}
    for method in _methods(trace):
        sub = trace[trace["method"] == method]
        positions = sub[["position_x", "position_y", "position_z"]].to_numpy()
        paths[method] = np.concatenate([scenario.start.reshape(1, 3).numpy(), positions])
    main = "dcsc" if "dcsc" in paths else next(iter(paths))
    fig = plot_uav_episode(torch.as_tensor(paths[main]), scenario.obstacle_params, scenario.goal,
                           title=title, label=METHOD_LABEL["uav"][main])
    ax = fig.axes[0]
    styles = {"machine": ("black", "--"), "operator": ("saddlebrown", ":"), "hula": ("magenta", "-.")}
    for method, points in paths.items():
        if method != main:
            color, style = styles.get(method, ("gray", "-"))
            ax.plot(points[:, 0], points[:, 1], points[:, 2], color=color, ls=style, lw=1.8,
                    label=METHOD_LABEL["uav"][method])
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_task_figures(results_dir: str | os.PathLike, task: str, main_operator: str, main_seed: int) -> list[Path]:
    """Every figure of one task into ``results_dir`` (PNG)."""
    results_dir = Path(results_dir)
    episodes = pd.read_csv(results_dir / "episodes.csv")
    trace = pd.read_csv(results_dir / "trace.csv")
    val = episodes[(episodes["phase"] == "validation") & (episodes["operator"] == main_operator)
                   & (episodes["pretrain_seed"] == main_seed)]
    trace = trace[trace["phase"] == "validation"]
    name = {"lunarlander": "LunarLander (moving pad)", "uav": "UAV path planning"}[task]
    paths = [
        plot_performance(val, task, results_dir / "fig_performance.png",
                         f"{name}: performance per scenario group (operator '{main_operator}')"),
        plot_confidence(trace, task, results_dir / "fig_confidence.png", f"{name}: confidence and authority (DC-SC)"),
        plot_authority(trace, task, results_dir / "fig_actions.png", f"{name}: machine / operator / shared actions"),
        plot_reward_over_time(trace, task, results_dir / "fig_reward.png", f"{name}: reward over time, scenario 0"),
    ]
    if task == "uav":
        paths.append(plot_uav_trajectories(trace, int(trace["seed"].iloc[0]), results_dir / "fig_trajectory.png",
                                           "UAV path planning: trajectories, scenario 0"))
    return paths
