"""The map of where shared control pays: for every machine x operator, each method's
validation success against the better partner alone, paired per scenario, with 95% CIs.

Input: the validation rows of several grids (``episodes.csv``), one per machine, with a
``machine`` column naming it. Output: one row per (machine, operator, method) with the
method's success, the better partner's, their per-scenario difference and its CI
(:func:`sharing_map`), a markdown table of the differences (:func:`map_markdown`), each
method's count of cells above, level with and below the better partner (:func:`map_tally`), a
heatmap (:func:`plot_map`) and, cell by cell, which of the paper's claims hold
(:func:`paper_claims`). docs/records/results.md opens with it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from dcsc_torchrl.methods import BEST_CONSTANT, METHODS  # noqa: E402
from dcsc_torchrl.report import mean_ci, save_figure, with_best_constant  # noqa: E402

EITHER = "either"
"""The per-scenario oracle: each whole episode handed to a partner that lands it alone."""

MAP_COLUMNS = ("machine", "operator", "method", "success", "success_ci", "better_partner", "partner_success",
               "delta", "delta_ci", "scenarios")
"""The columns of :func:`sharing_map`'s table (``delta`` = method − better partner, paired per scenario)."""


def map_method_order(methods: Sequence[str]) -> list[str]:
    """The map's methods in report order: the registry's, then the two oracles."""
    order = [*METHODS, BEST_CONSTANT.name, EITHER]
    return [m for m in order if m in set(methods)]


def _paired(validation: pd.DataFrame) -> pd.DataFrame:
    """One column per method, one row per (pretraining seed, scenario): success, with the
    best constant β and the per-scenario oracle as two more methods."""
    frame = with_best_constant(validation.assign(success=validation["success"].astype(float)))
    wide = frame.pivot_table(index=["pretrain_seed", "seed"], columns="method", values="success", aggfunc="first")
    if {"operator", "machine"} <= set(wide.columns):
        wide[EITHER] = wide[["operator", "machine"]].max(axis=1)
    return wide


def sharing_map(episodes: pd.DataFrame) -> pd.DataFrame:
    """The map's rows (:data:`MAP_COLUMNS`) from ``episodes`` with a ``machine`` column.

    Per (machine, operator): the better partner is whichever of ``operator`` and
    ``machine`` alone lands more often on the validation scenarios (pooled over the
    pretraining seeds); each method's ``delta`` is the mean over the same scenarios of its
    success minus that partner's, with the 95% CI of that paired mean. A ``delta_ci`` whose
    interval lies above 0 is a method that lands above both partners there.

    Examples:
        >>> rows = [{"machine": "m", "operator": "o", "pretrain_seed": 0, "phase": "validation", "seed": s,
        ...          "method": method, "success": float(ok)}
        ...         for s, (op, ma, dc) in enumerate([(1, 0, 1), (0, 1, 1), (0, 0, 1), (1, 0, 0)])
        ...         for method, ok in (("operator", op), ("machine", ma), ("dcsc", dc))]
        >>> table = sharing_map(pd.DataFrame(rows)).set_index("method")
        >>> row = table.loc["dcsc"]
        >>> float(row["success"]), row["better_partner"], float(row["delta"])
        (0.75, 'operator', 0.25)
        >>> float(table.loc["either", "success"])
        0.75
    """
    validation = episodes[episodes["phase"] == "validation"]
    rows = []
    for (machine, operator), cell in validation.groupby(["machine", "operator"], sort=False):
        wide = _paired(cell)
        if not {"operator", "machine"} <= set(wide.columns):
            continue
        partner = "operator" if wide["operator"].mean() >= wide["machine"].mean() else "machine"
        for method in map_method_order(list(wide.columns)):
            paired = wide[method].notna() & wide[partner].notna()
            ours, theirs = wide.loc[paired, method], wide.loc[paired, partner]
            success, success_ci = mean_ci(ours)
            delta, delta_ci = mean_ci(ours - theirs)
            rows.append({"machine": machine, "operator": operator, "method": method, "success": success,
                         "success_ci": success_ci, "better_partner": partner,
                         "partner_success": float(theirs.mean()), "delta": delta, "delta_ci": delta_ci,
                         "scenarios": int(paired.sum())})
    return pd.DataFrame(rows, columns=list(MAP_COLUMNS))


def _label(method: str) -> str:
    if method == EITHER:
        return "either partner (oracle)"
    return BEST_CONSTANT.label if method == BEST_CONSTANT.name else METHODS[method].label


def _points(value: float) -> str:
    return "–" if math.isnan(value) else f"{100 * value:+.0f}"


def map_markdown(table: pd.DataFrame) -> str:
    """The map as markdown: per (machine, operator), each partner alone, then each method's
    difference to the better partner in points (± the 95% CI); **bold** above both partners."""
    methods = [m for m in map_method_order(list(table["method"].unique())) if m not in ("operator", "machine")]
    header = ["machine", "operator", "operator alone", "machine alone", *(_label(m) for m in methods), "n"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * 2 + "---:|" * (len(header) - 2)]
    for (machine, operator), cell in table.groupby(["machine", "operator"], sort=False):
        by = cell.set_index("method")
        alone = [f"{100 * by.loc[p, 'success']:.0f}%" if p in by.index else "–" for p in ("operator", "machine")]
        entries = []
        for method in methods:
            if method not in by.index:
                entries.append("–")
                continue
            delta, half = by.loc[method, "delta"], by.loc[method, "delta_ci"]
            text = _points(delta) + ("" if math.isnan(half) else f" ± {100 * half:.0f}")
            entries.append(f"**{text}**" if delta - half > 0 else text)
        lines.append("| " + " | ".join([machine, operator, *alone, *entries, str(int(by["scenarios"].max()))]) + " |")
    return "\n".join(lines) + "\n"


TALLY_COLUMNS = ("method", "cells", "above", "level", "below", "within_2", "mean_delta")
"""The columns of :func:`map_tally`'s table."""


def map_tally(table: pd.DataFrame) -> pd.DataFrame:
    """Per method of :func:`sharing_map`'s ``table`` (the partners aside), over its cells: how
    many it lands above both partners (the whole 95% CI of ``delta`` above 0), level with the
    better one (the CI holding 0), below it (the whole CI below 0), at most 2 points below it
    (``delta >= -0.02``), and its mean ``delta``.

    Examples:
        >>> table = pd.DataFrame({"method": ["dcsc"] * 3, "delta": [0.2, 0.0, -0.3], "delta_ci": [0.1, 0.0, 0.1]})
        >>> row = map_tally(table).iloc[0]
        >>> [int(row[c]) for c in ("cells", "above", "level", "below", "within_2")]
        [3, 1, 1, 1, 2]
    """
    rows = []
    for method in map_method_order(list(table["method"].unique())):
        if method in ("operator", "machine"):
            continue
        cells = table[table["method"] == method]
        low, high = cells["delta"] - cells["delta_ci"].fillna(0.0), cells["delta"] + cells["delta_ci"].fillna(0.0)
        rows.append({"method": method, "cells": len(cells), "above": int((low > 0).sum()),
                     "level": int(((low <= 0) & (high >= 0)).sum()), "below": int((high < 0).sum()),
                     "within_2": int((cells["delta"] >= -0.02 - 1e-9).sum()), "mean_delta": cells["delta"].mean()})
    return pd.DataFrame(rows, columns=list(TALLY_COLUMNS))


def tally_markdown(tally: pd.DataFrame) -> str:
    """:func:`map_tally`'s table as markdown (the mean in points)."""
    lines = ["| method | cells | above both partners | level with the better | below it | within 2 points of it "
             "| mean (points) |", "|---|" + "---:|" * 6]
    lines += [f"| {_label(row['method'])} | {row['cells']} | {row['above']} | {row['level']} | {row['below']} "
              f"| {row['within_2']} | {_points(row['mean_delta'])} |" for _, row in tally.iterrows()]
    return "\n".join(lines) + "\n"


def plot_map(table: pd.DataFrame, path: Path, title: str) -> Path:
    """The map as a heatmap: rows (machine, operator), columns the methods, colour the
    difference to the better partner (points), each cell annotated with it and its CI."""
    methods = [m for m in map_method_order(list(table["method"].unique())) if m not in ("operator", "machine")]
    keys = list(dict.fromkeys(zip(table["machine"], table["operator"], strict=True)))
    indexed = table.set_index(["machine", "operator", "method"])
    values = np.full((len(keys), len(methods)), np.nan)
    halves = np.full_like(values, np.nan)
    for i, key in enumerate(keys):
        for j, method in enumerate(methods):
            if (*key, method) in indexed.index:
                values[i, j] = 100 * indexed.loc[(*key, method), "delta"]
                halves[i, j] = 100 * indexed.loc[(*key, method), "delta_ci"]
    limit = max(10.0, float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 10.0)
    fig, ax = plt.subplots(figsize=(1.3 * len(methods) + 6.5, 0.42 * len(keys) + 1.8))
    image = ax.imshow(values, cmap="RdBu", vmin=-limit, vmax=limit, aspect="auto")
    for i in range(len(keys)):
        for j in range(len(methods)):
            if np.isfinite(values[i, j]):
                ci = "" if not np.isfinite(halves[i, j]) else f"\n±{halves[i, j]:.0f}"
                weight = "bold" if values[i, j] - (halves[i, j] if np.isfinite(halves[i, j]) else 0) > 0 else "normal"
                ax.text(j, i, f"{values[i, j]:+.0f}{ci}", ha="center", va="center", fontsize=7, fontweight=weight)
    ax.set_xticks(range(len(methods)), [_label(m) for m in methods], rotation=30, ha="right", fontsize=8)
    def alone(key: tuple[str, str], partner: str) -> str:
        return (f"{100 * indexed.loc[(*key, partner), 'success']:.0f}%" if (*key, partner) in indexed.index
                else "–")

    ax.set_yticks(range(len(keys)), [f"{machine} · {operator} (operator {alone((machine, operator), 'operator')}, "
                                     f"machine {alone((machine, operator), 'machine')})"
                                     for machine, operator in keys], fontsize=8)
    fig.colorbar(image, ax=ax, label="success − better partner alone (points)")
    ax.set_title(title, fontsize=10)
    return save_figure(fig, path)


CLAIMS = ("above the machine", "above HULA", "≥ 90%", "shorter than machine and HULA", "higher return than machine and HULA")
"""The paper's claims for DC-SC (§6: Tables 2 and 4), as :func:`paper_claims` checks them."""


def _verdict(differences: pd.Series) -> str:
    """``yes`` when the paired 95% CI of ``differences`` lies above 0, ``no`` when its mean is
    not above 0, ``within CI`` between the two."""
    mean, half = mean_ci(differences)
    if math.isnan(mean) or mean <= 0:
        return "no"
    return "yes" if not math.isnan(half) and mean - half > 0 else "within CI"


def _above_both(values: pd.DataFrame, method: str) -> str:
    """:func:`_verdict` of ``method``'s column against both the machine's and HULA's: ``yes``
    only where both are, ``no`` where either is."""
    verdicts = [_verdict(values[method] - values[other]) for other in ("machine", "hula")]
    return "yes" if all(v == "yes" for v in verdicts) else "no" if "no" in verdicts else "within CI"


def paper_claims(episodes: pd.DataFrame, method: str) -> pd.DataFrame:
    """Per (machine, operator), whether ``method`` meets the paper's claims (:data:`CLAIMS`)
    on the validation scenarios, each comparison paired per scenario: success above the
    machine alone and above HULA, a success of at least 90%, fewer steps per episode than
    both and a higher return than both (``yes`` / ``within CI`` / ``no``; a mean of 90%
    is ``yes`` for the third)."""
    validation = episodes[episodes["phase"] == "validation"]
    rows = []
    for (machine, operator), cell in validation.groupby(["machine", "operator"], sort=False):
        wide = {metric: cell.pivot_table(index=["pretrain_seed", "seed"], columns="method",
                                         values=metric, aggfunc="first").astype(float)
                for metric in ("success", "steps", "return")}
        if not {method, "machine", "hula"} <= set(wide["success"].columns):
            continue
        success = wide["success"]
        rows.append({"machine": machine, "operator": operator, "method": method,
                     CLAIMS[0]: _verdict(success[method] - success["machine"]),
                     CLAIMS[1]: _verdict(success[method] - success["hula"]),
                     CLAIMS[2]: "yes" if success[method].mean() >= 0.9 else "no",
                     CLAIMS[3]: _above_both(-wide["steps"], method), CLAIMS[4]: _above_both(wide["return"], method)})
    return pd.DataFrame(rows, columns=["machine", "operator", "method", *CLAIMS])


def claims_markdown(claims: pd.DataFrame) -> str:
    """:func:`paper_claims`'s table as markdown."""
    header = ["machine", "operator", *CLAIMS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(row[c]) for c in header) + " |" for _, row in claims.iterrows()]
    return "\n".join(lines) + "\n"
