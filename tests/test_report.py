"""The report's tables from hand-made episode rows (dcsc_torchrl/report.py)."""

from __future__ import annotations

import pandas as pd
import pytest

from dcsc_torchrl.report import Z95, method_label, partner_overlap, success_grid, with_best_constant
from dcsc_torchrl.tasks import get_task


def _rows(method: str, successes: list[int], operator: str = "expert", **extra) -> list[dict]:
    return [{"operator": operator, "pretrain_seed": 0, "seed": seed, "method": method, "success": success,
             "return": float(success), **extra} for seed, success in enumerate(successes)]


def test_partner_overlap_counts_both_and_either_on_the_same_scenarios():
    frame = pd.DataFrame(_rows("operator", [1, 1, 0, 0]) + _rows("machine", [1, 0, 1, 0])
                         + _rows("dcsc", [1, 1, 1, 1]))
    overlap = partner_overlap(frame)
    assert overlap.loc["expert"].to_dict() == pytest.approx(
        {"operator": 0.5, "machine": 0.5, "both": 0.25, "either": 0.75, "scenarios": 4})


def test_partner_overlap_pairs_scenarios_per_operator_and_needs_both_partners():
    frame = pd.DataFrame(_rows("operator", [1, 0]) + _rows("machine", [0, 0])
                         + _rows("operator", [0, 0], operator="noisy") + _rows("machine", [1, 1], operator="noisy"))
    overlap = partner_overlap(frame)
    assert overlap["either"].to_dict() == {"expert": 0.5, "noisy": 1.0}
    assert partner_overlap(pd.DataFrame(_rows("operator", [1, 0]))).empty


def test_best_constant_keeps_the_rows_of_the_best_beta_per_cell():
    frame = pd.DataFrame(_rows("constant", [0, 1], constant_beta=0.0) + _rows("constant", [1, 1], constant_beta=0.5)
                         + _rows("operator", [0, 1], constant_beta=float("nan")))
    best = with_best_constant(frame)
    kept = best[best["method"] == "best_constant"]
    assert set(kept["constant_beta"]) == {0.5}
    assert len(kept) == 2 and "constant" not in set(best["method"])


def test_the_success_grid_is_methods_by_operators_in_percent_with_their_ci():
    task = get_task("lunarlander")
    rows = _rows("operator", [1, 1, 1, 1]) + _rows("operator", [1, 0, 1, 0], operator="noisy")
    rows += _rows("machine", [0], operator="noisy")
    table = success_grid(pd.DataFrame(rows), task).splitlines()
    half = 100 * Z95 * pd.Series([1, 0, 1, 0]).std() / 2
    assert table == ["| method | expert | noisy |", "|---|---:|---:|",
                     f"| {method_label(task, 'machine')} | – | 0 |",
                     f"| {method_label(task, 'operator')} | 100 ± 0 | 50 ± {half:.0f} |"]
