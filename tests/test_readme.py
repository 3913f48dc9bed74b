"""README's results block: rendered from the stored results, checked against them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from codesign_mb.core.config import to_mapping
from codesign_mb.core.results import write_results
from codesign_mb.core.stats import wilson_interval
from codesign_mb.studies import paper, paper_studies
from codesign_mb.studies.fig_wifi import CapacityConfig
from codesign_mb.studies.paper import run_paper
from codesign_mb.studies.paper_studies import PaperConfig
from codesign_mb.studies.readme import (
    BEGIN,
    END,
    export_results,
    read_block,
    render_results,
    replace_block,
    update_readme,
)
from codesign_mb.studies.readme_tables import ci, header, pct

ROOT = Path(__file__).resolve().parents[1]


def test_readme_results_block_is_the_rendering_of_docs_results() -> None:
    """Every number between README's results markers comes from the committed docs/results.

    On failure: `codesign readme` (from docs/results) or `make paper` (a new run).
    """
    block = read_block((ROOT / "README.md").read_text())
    assert block == render_results(ROOT / "docs" / "results")
    run = json.loads((ROOT / "docs" / "results" / "paper.json").read_text())
    for name, study in run["studies"].items():
        if name in paper_studies.STUDIES[:-1]:
            assert (ROOT / "docs" / "results" / f"{name}.json").is_file()
            assert f"`{study['command']}`" in block
    for figure in (ROOT / "docs" / "figures").glob("fig_*.png"):
        if f"docs/figures/{figure.name}" in block:
            assert figure.stat().st_size > 5000


def test_percentages_and_intervals() -> None:
    assert pct(1.0) == "100 %" and pct(0.63) == "63 %" and pct(0.0) == "0 %"
    assert pct(0.004) == "0.4 %" and pct(0.0951) == "10 %" and pct(None) == ""
    assert pct(0.995) == "99.5 %" and pct(0.9949) == "99 %" and pct(0.9999) == "100.0 %"
    assert ci(*wilson_interval(100, 100)) == "[96.3, 100]"
    assert ci(*wilson_interval(0, 100)) == "[0, 3.7]"
    assert ci(*wilson_interval(63, 100)) == "[53.2, 71.8]"
    assert ci(*wilson_interval(71, 100)) == "[61.5, 79.0]"  # one decimal but at 0 and 100


# -- a constructed results folder, through the real run with the studies replaced ----------------
def _row(name: str, successes: int, reliability: float, **more: Any) -> dict[str, Any]:
    low, high = wilson_interval(successes, 100)
    return {
        "plant": "realistic",
        "row": name,
        "kind": "row",
        "reference": False,
        "reference_of": "",
        "status": "ok",
        "success_rate": successes / 100,
        "success_ci_low": low,
        "success_ci_high": high,
        "mean_requested_reliability": reliability,
        "delivered_fraction": 0.9 * reliability,
        "paper_success_rate": None,
        "paper_mean_reliability": None,
        "pareto": False,
        **more,
    }


def _fake_lqg(settings: dict[str, Any], out: Path) -> None:
    rows = pd.DataFrame(
        {
            "reliability": [1.0, 0.5],
            "mean_cost": [5.7912, 10.3249],
            "cost_ci95": [0.1234, 0.5],
            "mean_age": [0.0, 1.0449],
            "delivered_fraction": [1.0, 0.497],
        }
    )
    extra = {
        "scenario": "lqg",
        "plant": "inverted_pendulum",
        "episodes": 8,
        "horizon": 250,
        "latency_steps": 0,
        "seed": 0,
        "riccati_cost": 5.72131,
        "critical_reliability_lower_bound": 0.31036,
    }
    write_results(out, table=rows, config=None, name="lqg", extra=extra)


def _fake_table(name: str, settings: dict[str, Any], out: Path, *_: Any) -> dict[str, Path]:
    rows = [
        _row("MPC + predictor, rule QoS (co-design)", 63, 0.1512),
        _row("MPC + predictor, blind (q = 0)", 6, 0.0, kind="blind", reference=True),
        {**_row("SAC + MLP, SAC QoS", 0, 0.0), "status": "missing checkpoint: checkpoints/x"},
    ]
    write_results(out, table=pd.DataFrame(rows), config=None, name="tab_p")
    return {}


def _fake_fig_cn(settings: dict[str, Any], out: Path, *_: Any) -> None:
    points = [
        {"sweep": "delay", "belt_speed_mps": 0.2, "estimator": e, "latency_steps": d,
         "reliability": 1.0, "trials": 100, "successes": s, "success_rate": s / 100,
         "success_ci_low": 0.0, "success_ci_high": 1.0}
        for e, d, s in (("none", 0, 100), ("none", 4, 0), ("predictor", 0, 100),
                        ("predictor", 4, 100))
    ] + [
        {"sweep": "reliability", "belt_speed_mps": 0.2, "estimator": "none", "latency_steps": 1,
         "reliability": q, "trials": 100, "successes": s, "success_rate": s / 100,
         "success_ci_low": 0.0, "success_ci_high": 1.0}
        for q, s in ((1.0, 100), (0.3, 43))
    ]  # fmt: skip
    write_results(out, table=pd.DataFrame(points), config=None, name="fig_cn")


def _fake_fig_wifi(settings: dict[str, Any], out: Path, *_: Any) -> None:
    success = {  # (pipeline, scheduler) -> success of two trials at N = 1, 2, 4
        ("static", "greedy"): ((1, 1), (1, 0.5), (0.5, 0.5)),
        ("codesign", "greedy"): ((1, 1), (1, 1), (1, 1)),
    }
    trials = [
        {"channel": "paper", "scheduler": s, "pipeline": p, "robots": n, "trial": k,
         "success_rate": float(rates[k]), "mean_reliability": 0.5,
         "delivered_fraction": 0.5}
        for (p, s), by_n in success.items()
        for n, rates in zip((1, 2, 4), by_n, strict=True)
        for k in range(2)
    ]  # fmt: skip
    config = CapacityConfig(robots=(1, 2, 4), channels=("paper",), schedulers=("greedy",))
    write_results(out, table=pd.DataFrame(trials), config=to_mapping(config), name="fig_wifi")


@pytest.fixture
def constructed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A `codesign paper` folder whose studies wrote hand-made tables."""
    monkeypatch.setattr(paper, "_run_lqg", _fake_lqg)
    monkeypatch.setattr(paper, "_run_table", _fake_table)
    monkeypatch.setattr(paper, "_run_fig_cn", _fake_fig_cn)
    monkeypatch.setattr(paper, "_run_fig_wifi", _fake_fig_wifi)
    out = tmp_path / "paper"
    config = PaperConfig(only=("lqg", "table_realistic", "fig_cn", "fig_wifi"), workers=2)
    run_paper(config, out, command="codesign paper -o results/paper")
    return out


def test_renderer_on_a_constructed_results_folder(constructed: Path, tmp_path: Path) -> None:
    docs = tmp_path / "docs"
    export_results(constructed, docs)
    names = sorted(p.name for p in (docs / "results").iterdir())
    assert names == [
        "fig_cn.json",
        "fig_wifi.json",
        "lqg.json",
        "paper.json",
        "table_realistic.json",
    ]
    block = render_results(docs / "results")
    lines = block.splitlines()
    # the table: success with its Wilson interval, reliabilities, references, skipped rows
    assert "| MPC + predictor, rule QoS (co-design) | 63 % [53.2, 71.8] | 15 % | 14 % |" in lines
    assert "| *MPC + predictor, blind (q = 0)* | 6 % [2.8, 12.5] | 0 % | 0 % |" in lines
    assert "| SAC + MLP, SAC QoS | not run: missing checkpoint: checkpoints/x |  |  |" in lines
    assert (
        "(`codesign table --scenario realistic --pipeline model-based -n 200 --seed 0 "
        "--bound 'MPC + belt IMM, QoS planner (co-design)'`, `test` seed set, 200 episodes "
        "per row)"
    ) in block
    # the linear baseline
    assert "| q | 1 | 0.5 |" in lines and "| mean LQG cost | 5.79 | 10.32 |" in lines
    assert "| mean age (steps) | 0.00 | 1.04 |" in lines and "| delivered | 100 % | 50 % |" in lines
    assert "Riccati cost at q = 1: 5.72, critical q >= 0.310" in block
    # Fig. 4: one line per belt speed and estimator, one column per delay / reliability
    assert "| delay (steps) | 0 | 4 |" in lines and "| 0.2 m/s, none | 100 % | 0 % |" in lines
    assert "| q | 1 | 0.3 |" in lines and "| 0.2 m/s, none | 100 % | 43 % |" in lines
    # Fig. 6: mean success of the trials; capacity = most robots with every N >= 95 %
    assert "| pipeline, scheduler | N = 1 | N = 2 | N = 4 | robots at 95 % |" in lines
    # with the 95 % Wilson interval over a point's trials x N robot-episodes (scipy's)
    # and the capacity of "not significantly below 95 %": N = 2's upper bound 95.4 % is not
    static = "| static, greedy | 100 % [34.2, 100] | 75 % [30.1, 95.4] | 50 % [21.5, 78.5] |"
    codesign = "| codesign, greedy | 100 % [34.2, 100] | 100 % [51.0, 100] | 100 % [67.6, 100] |"
    assert f"{static} 1 (2 not below it) |" in lines
    assert f"{codesign} >= 4 (>= 4 not below it) |" in lines
    assert (
        "Co-design over static capacity: greedy 4 / 1 = 4 (at least); greedy (not significantly "
        "below the target, Wilson) 4 / 2 = 2 (at least)."
    ) in lines
    assert "a curve stops once its success at one is below 50 % (its larger N: not run)" in block
    assert "`codesign`: mpc + predictor, QoS covariance_triggered (threshold_m 0.02" in block
    # provenance and wall times
    run = json.loads((docs / "results" / "paper.json").read_text())
    assert f"at commit `{str(run['provenance']['commit'])[:7]}" in block
    assert "run on the `test` seed set (root seed 0)" in block
    assert "`codesign paper -o results/paper`" in block and "| all |  |" in block
    assert "2 worker processes" in block


def test_readme_block_replaced_in_place_and_a_changed_number_makes_it_stale(
    constructed: Path, tmp_path: Path
) -> None:
    docs, readme = tmp_path / "docs", tmp_path / "README.md"
    export_results(constructed, docs)
    readme.write_text(f"# title\n\nprose 12 %\n{BEGIN}\nold 99 %\n{END}\ntail\n")
    assert update_readme(readme, docs) is True
    text = readme.read_text()
    assert text.startswith("# title\n\nprose 12 %\n") and text.endswith(f"{END}\ntail\n")
    assert "old 99 %" not in text and "63 % [53.2, 71.8]" in text
    assert update_readme(readme, docs, check=True) is False
    assert replace_block(text, read_block(text)) == text
    stored = docs / "results" / "table_realistic.json"
    data = json.loads(stored.read_text())
    data["rows"][0]["success_rate"] = 0.64
    stored.write_text(json.dumps(data))
    assert update_readme(readme, docs, check=True) is True
    assert "63 % [53.2, 71.8]" in readme.read_text()  # check changes nothing


def test_header_names_each_commit_of_a_run_resumed_across_commits() -> None:
    run = {
        "command": "codesign paper -o results/paper",
        "seeds": "test",
        "seed": 0,
        "created": "2026-12-01T20:39:19+00:00",
        "provenance": {"commit": "b" * 40},
        "studies": {"lqg": {"commit": "a" * 40}, "fig_cn": {"commit": "b" * 40 + "+dirty"}},
    }
    text = header(run)
    assert "run on the `test` seed set (root seed 0) at commits `aaaaaaa` (`lqg`); " in text
    assert "`bbbbbbb` (with uncommitted changes) (`fig_cn`) on 2026-12-01." in text
    run["studies"] = {"lqg": {"commit": "b" * 40}, "fig_cn": {"commit": "b" * 40}}
    assert "at commit `bbbbbbb` on 2026-12-01." in header(run)


def test_markers_must_be_there_once() -> None:
    with pytest.raises(ValueError, match="markers"):
        read_block("no markers")
    with pytest.raises(ValueError, match="markers"):
        read_block(f"{END}\n{BEGIN}\n")


def test_explain_table_renders_reasons_errors_and_nees() -> None:
    from codesign_mb.studies.readme_tables import explain_table

    row = {
        "row": "MPC + predictor, rule QoS (co-design)",
        "status": "ok",
        "rule_threshold_m": 0.0139,
        "failures_dropped": 1,
        "failures_missed_grasp": 3,
        "failures_off_belt": 0,
        "failures_timeout": None,
        "mean_time_to_grasp_s": 2.345,
        "est_error_mm_belt": 28.04,
        "est_error_mm_grasp": 6.66,
        "est_error_mm_carried": 11.4,
        **{
            f"nees_{p}": v
            for p, v in zip(("belt", "grasp", "carried"), (4.36, 4.44, 12.5), strict=True)
        },
        **{f"nees_{p}_low": 2.9 for p in ("belt", "grasp", "carried")},
        **{f"nees_{p}_high": 3.1 for p in ("belt", "grasp", "carried")},
        "nees_inside_belt": 0.912,
        "nees_inside_grasp": 0.5,
        "nees_inside_carried": None,
    }
    skipped = {"row": "SAC + MLP", "status": "incompatible checkpoint: x"}
    none = {
        **row,
        "row": "*blind*",
        "rule_threshold_m": None,
        "nees_belt": None,
        "nees_grasp": None,
        "nees_carried": None,
    }
    lines = explain_table([row, skipped, none]).splitlines()
    assert "| failures (dropped / missed grasp / off belt / timeout) |" in lines[2]
    assert lines[4] == (
        "| MPC + predictor, rule QoS (co-design) | 0.0139 m | 1 / 3 / 0 / 0 | 2.35 s | "
        "28.0 / 6.7 / 11.4 | 4.4 [2.90, 3.10] / 4.4 [2.90, 3.10] / 12.5 [2.90, 3.10] | "
        "91 % / 50 % /  |"
    )
    assert lines[5].startswith("| *blind* |  | 1 / 3 / 0 / 0 |")
    assert lines[5].endswith("|  | 91 % / 50 % /  |")  # no NEES, the shares it was given
    assert len(lines) == 6  # the skipped row has no metrics


def test_crosscheck_section_shows_both_sides_and_counts_the_cells_within_tolerance():
    from codesign_mb.studies.readme_crosscheck import crosscheck_section

    rows = [
        {"mcs": 0, "capture": "staggered", "ours_greedy": 4, "ours_convex": 4, "ns3_su": 5,
         "gap": -0.2, "within_tolerance": True},
        {"mcs": 7, "capture": "synchronised", "ours_greedy": 40, "ours_convex": 31,
         "ns3_su": 20, "gap": 1.0, "within_tolerance": False},
    ]  # fmt: skip
    text = crosscheck_section({"rows": rows, "tolerance": 0.25, "assumptions": {"ours": "x"}})
    assert "within 25 % in 1 of 2 cells" in text
    assert "| 0 | staggered | 4 | 4 | 5 | -20 % |" in text
    assert "| 7 | synchronised | 40 | 31 | 20 | +100 % |" in text
    assert "ns-3 OFDMA" not in text  # a set-up the file does not hold has no column
    assert "- ours: x" in text


def test_export_of_some_studies_keeps_the_others(constructed: Path, tmp_path: Path) -> None:
    """`codesign paper --only fig_wifi --readme`: fig_wifi's docs replaced, the rest kept."""
    docs = tmp_path / "docs"
    export_results(constructed, docs)
    kept = (docs / "results" / "lqg.json").read_text()
    before = json.loads((docs / "results" / "paper.json").read_text())
    (docs / "results" / "fig_wifi.json").write_text("{}")
    export_results(constructed, docs, studies=["fig_wifi"])
    assert (docs / "results" / "lqg.json").read_text() == kept
    assert json.loads((docs / "results" / "fig_wifi.json").read_text())["study"] == "fig_wifi"
    after = json.loads((docs / "results" / "paper.json").read_text())
    assert after["studies"] == before["studies"] and after["command"] == before["command"]
    total = sum(s["wall_time_s"] for s in after["studies"].values())
    assert after["studies_wall_time_s"] == pytest.approx(total, abs=0.1)
    with pytest.raises(ValueError, match="unknown studies"):
        export_results(constructed, docs, studies=["fig_6"])


def test_time_table_says_what_a_resumed_study_reused() -> None:
    from codesign_mb.studies.readme_tables import wall_times

    run = {
        "studies": {
            "fig_wifi": {"command": "c", "wall_time_s": 600.0, "cpu_time_s": 1200.0,
                         "resumed_records": 720},
            "lqg": {"command": "d", "wall_time_s": 8.0, "cpu_time_s": 5.0},
        },
        "studies_wall_time_s": 608.0,
        "studies_cpu_time_s": 1205.0,
    }  # fmt: skip
    text = wall_times(run)
    assert "| `fig_wifi` | `c` | 10.0 min (+ 720 stored records reused) |" in text
    assert "| `lqg` | `d` | 8 s | 5 s |" in text


def test_a_study_counts_the_records_an_interrupted_run_left(tmp_path: Path) -> None:
    store = tmp_path / ".records"
    assert paper._stored_records(store) == 0
    store.mkdir()
    (store / "a.jsonl").write_text('{"x": 1}\n{"x": 2}\n\n')
    (store / "b.jsonl").write_text('{"x": 3}\n')
    assert paper._stored_records(store) == 3
