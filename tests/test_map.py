"""The map of where shared control pays: its table against hand-computed cells, and
``dcsc map --quick`` writing the table and the heatmap."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from dcsc_torchrl.cli import main
from dcsc_torchrl.recipes.map import machine_overrides, map_config
from dcsc_torchrl.sharing_map import paper_claims, sharing_map


def episodes(machine: str, results: dict[str, list[int]], operator: str = "o") -> list[dict]:
    return [{"machine": machine, "operator": operator, "pretrain_seed": 0, "phase": "validation", "seed": seed,
             "method": method, "success": bool(ok), "return": 100.0 * ok}
            for method, outcomes in results.items() for seed, ok in enumerate(outcomes)]


def test_each_method_is_set_against_the_better_partner_scenario_by_scenario():
    rows = episodes("sees", {"operator": [1, 1, 0, 0], "machine": [0, 1, 1, 1], "dcsc": [1, 1, 1, 1],
                             "hula": [0, 1, 1, 0]})
    rows += episodes("blind", {"operator": [1, 1, 1, 0], "machine": [0, 0, 0, 0], "dcsc": [1, 1, 1, 0]})
    table = sharing_map(pd.DataFrame(rows)).set_index(["machine", "method"])
    sees = table.loc["sees"]
    assert set(sees["better_partner"]) == {"machine"} and sees.loc["dcsc", "partner_success"] == 0.75
    assert sees.loc["dcsc", "delta"] == pytest.approx(0.25)
    assert sees.loc["hula", "delta"] == pytest.approx(-0.25)  # 0-0, 1-1, 1-1, 0-1
    assert sees.loc["either", "success"] == 1.0
    # the CI is the paired one: differences (0, 0, 0, -1) for hula
    assert sees.loc["hula", "delta_ci"] == pytest.approx(1.959963984540054 * 0.5 / 2)
    blind = table.loc["blind"]
    assert blind.loc["dcsc", "better_partner"] == "operator" and blind.loc["dcsc", "delta"] == 0.0


def test_the_best_constant_is_the_sweeps_best_beta_and_a_missing_partner_leaves_no_row():
    rows = episodes("m", {"operator": [0, 0], "machine": [1, 0]})
    rows += [{**row, "constant_beta": beta} for beta, outcomes in ((0.5, [1, 1]), (1.0, [1, 0]))
             for row in episodes("m", {"constant": outcomes})]
    rows += episodes("m", {"operator": [1, 1]}, operator="alone")
    table = sharing_map(pd.DataFrame(rows))
    best = table[table["method"] == "best_constant"].iloc[0]
    assert best["success"] == 1.0 and best["delta"] == 0.5
    assert "alone" not in set(table["operator"])


def test_each_machines_protocol_is_its_folder_view_seeds_and_recipe():
    cfg = map_config()
    converged = machine_overrides(cfg, "target-converged")
    assert "pretrain.observes=target" in converged and any(s.startswith("pretrain.recipe=[loss.algorithm=ppo")
                                                          for s in converged)
    assert "pretrain.recipe=[]" in machine_overrides(cfg, "blind-500")
    assert machine_overrides(cfg, "blind-500")[0].endswith("blind-500")


def test_a_map_naming_an_unknown_machine_is_refused_at_the_door(tmp_path, capsys):
    assert main(["map", "--out", str(tmp_path / "m"), "selected=[target-500,nowhere]"]) == 2
    assert "selected: unknown machine 'nowhere'" in capsys.readouterr().err
    assert main(["map", "--out", str(tmp_path / "m"), "machines.blind-500.observes=pad"]) == 2
    assert "machines.blind-500: pretrain.observes: unknown machine view 'pad'" in capsys.readouterr().err
    assert main(["map", "--out", str(tmp_path / "m"), "selected=[]"]) == 2  # no machine: not a StopIteration later
    assert "selected: expected at least one entry, got []" in capsys.readouterr().err
    assert main(["map", "--out", str(tmp_path / "m"), "arbiters.surrogates=[]"]) == 2
    assert "arbiters.surrogates: expected at least one operator preset, got []" in capsys.readouterr().err
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())


def test_quick_map_writes_its_table_and_heatmap(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "map"
    assert main(["map", "--quick", "--workers", "1", "--out", str(out), "selected=[blind-500]",
                 "operators=[surrogate_noisy]"]) == 0
    table = pd.read_csv(out / "map.csv")
    assert set(table["machine"]) == {"blind-500"} and set(table["operator"]) == {"surrogate_noisy"}
    assert {"operator", "machine", "dcsc_centred", "best_constant", "either", "ida_expert", "reddy",
            "dcsc_state"} <= set(table["method"])
    assert all(not math.isnan(value) for value in table["delta"])
    text = (out / "map.md").read_text()
    assert "A `--quick` run" in text and "| blind-500 | surrogate_noisy |" in text
    tally = text.split("## Each method over the cells")[1]  # one row per method, its cells counted
    assert "| DC-SC (centred) | 1 |" in tally and "| either partner (oracle) | 1 |" in tally
    assert (out / "fig_map.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "blind-500" / "lunarlander" / "episodes.csv").exists()
    # the assistants' inputs, made first: the expert machine (target-500 in --quick) and both copilots
    assert (tmp_path / "runs" / "quick" / "map" / "target-500" / "seed0" / "checkpoint.pt").is_file()
    for name in ("surrogates", "humanlike"):
        assert (tmp_path / "runs" / "quick" / "map" / f"copilot-{name}" / "copilot.pt").is_file()
        # and the state-dependent arbiters, next to the map's machine, after it was pretrained
        assert (tmp_path / "runs" / "quick" / "map" / "blind-500" / f"arbiter-{name}" / "arbiter.pt").is_file()


def test_leave_one_out_pretrains_one_arbiter_per_operator_without_it(capsys):
    from dcsc_torchrl.recipes.map import arbiter_pools, map_config

    assert not map_config().arbiters_leave_one_out and "dcsc_state" in map_config().methods  # the two pools
    cfg = map_config(["operators=[expert,noisy,surrogate_laggy]", "arbiters_leave_one_out=true"])
    assert arbiter_pools(cfg) == {"without-expert": ["noisy", "surrogate_laggy"],
                                  "without-noisy": ["expert", "surrogate_laggy"],
                                  "without-surrogate_laggy": ["expert", "noisy"]}
    from dcsc_torchrl.recipes.map import machine_arbiters

    files = machine_arbiters(map_config(), "blind-500")  # each machine's own two, named in its grid alone
    assert [(path.parent.name, path.parent.parent.name) for path in files] == [
        ("arbiter-surrogates", "blind-500"), ("arbiter-humanlike", "blind-500")]
    assert arbiter_pools(map_config())["surrogates"] == [
        "surrogate_expert", "surrogate_noisy", "surrogate_laggy"]
    assert main(["map", "operators=[expert]", "methods=[operator,dcsc_state]", "arbiters_leave_one_out=true"]) == 2
    assert "arbiters_leave_one_out: an arbiter pretrained without the cell's operator needs another operator" in (
        capsys.readouterr().err)


def test_the_papers_claims_are_checked_paired_per_scenario():
    def rows(method, success, steps, ret):
        return [{"machine": "m", "operator": "o", "pretrain_seed": 0, "phase": "validation", "seed": seed,
                 "method": method, "success": ok, "steps": st, "return": r}
                for seed, (ok, st, r) in enumerate(zip(success, steps, ret, strict=True))]

    n = 20
    episodes = pd.DataFrame(
        rows("dcsc_centred", [1] * n, [100] * n, [200.0] * n)
        + rows("machine", [0] * n, [300] * n, [-50.0] * n)
        + rows("hula", [1] * (n - 1) + [0], [100] * n, [200.0] * (n - 1) + [150.0]))
    claims = paper_claims(episodes, "dcsc_centred").iloc[0]
    assert claims["above the machine"] == "yes" and claims["≥ 90%"] == "yes"
    assert claims["above HULA"] == "within CI"  # one scenario better: its mean is above, its CI is not
    assert claims["shorter than machine and HULA"] == "no"  # level with HULA
    assert claims["higher return than machine and HULA"] == "within CI"
    assert paper_claims(episodes[episodes["method"] != "hula"], "dcsc_centred").empty
