"""``codesign wifi`` and ``codesign solve``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app

INSTANCES = Path(__file__).resolve().parents[1] / "solvers" / "instances"
runner = CliRunner()


def test_phy_table_json():
    result = runner.invoke(app, ["wifi", "phy-table", "--bandwidth", "40", "--json"])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    rate = {(r["ru_tones"], r["mcs"]): r["rate_mbps"] for r in rows}
    assert rate[(484, 11)] == pytest.approx(286.8, abs=0.05)
    assert rate[(484, 0)] == pytest.approx(17.2, abs=0.05)
    assert rate[(242, 7)] == pytest.approx(86.0, abs=0.05)


def test_phy_table_bad_bandwidth_is_one_line():
    result = runner.invoke(app, ["wifi", "phy-table", "--bandwidth", "30"])
    assert result.exit_code == 2
    assert "bandwidth_mhz must be one of" in result.output


@pytest.mark.parametrize("solver", ["highs", "clarabel"])
def test_solve_shipped_instance(solver):
    path = INSTANCES / "paper_6robots_static.json"
    result = runner.invoke(app, ["solve", str(path), "--solver", solver, "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["solver"] == solver and out["status"] == "optimal"
    assert out["optimum_frames"] == pytest.approx(out["frames_deliverable"], abs=1e-4)
    assert out["solve_time_s"] >= 0


def test_solve_errors():
    result = runner.invoke(app, ["solve", "missing.json"])
    assert result.exit_code == 2 and "does not exist" in result.output
    path = INSTANCES / "paper_6robots_static.json"
    result = runner.invoke(app, ["solve", str(path), "--solver", "cplex"])
    assert result.exit_code == 2 and "solver must be one of" in result.output


def test_trace_then_solve_with_compare(tmp_path):
    out = tmp_path / "t.json"
    r = runner.invoke(app, ["wifi", "trace", str(out), "--robots", "3", "--steps", "2"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["solve", str(out), "--compare", "--json"])
    assert r.exit_code == 0, r.output
    rec = json.loads(r.stdout)
    assert rec["greedy_frames"] <= rec["optimum_frames"] + 1e-6
    assert rec["convex_frames"] >= rec["greedy_frames"]


def test_capacity_small(tmp_path):
    pytest.importorskip("codesign_mb.plants.toy")
    r = runner.invoke(
        app,
        ["wifi", "capacity", "--robots", "1..2", "--channels", "paper", "--schedulers",
         "greedy", "--trials", "1", "--max-steps", "5", "--stack", "toy", "--out",
         str(tmp_path), "--json"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    assert {row["pipeline"] for row in rows} == {"static", "codesign"}
    assert {row["robots"] for row in rows} == {1, 2}
    for name in ("fig_wifi.png", "fig_wifi.parquet", "fig_wifi.csv", "fig_wifi.json"):
        assert (tmp_path / name).stat().st_size > 0
    meta = json.loads((tmp_path / "fig_wifi.json").read_text())
    assert meta["config"]["stack"] == "toy" and len(meta["extra"]["curves"]) == 4
    r = runner.invoke(app, ["wifi", "capacity", "--stack", "nope", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "stack must be one of" in r.output
