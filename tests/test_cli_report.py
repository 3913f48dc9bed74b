"""``codesign report``: figures and Markdown from whatever tables a results folder holds."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.cli import report as report_cli
from codesign_mb.core.results import ResultsDir, write_results
from codesign_mb.studies import (
    fig_cn,
    fig_wifi_figures,
    sweep_figures,
    table_figures,
    table_pareto_plot,
)
from codesign_mb.studies.report import ReportConfig, build_report, success_summary
from codesign_mb.studies.sweep import SweepConfig, run_sweep


def _episodes(rng: np.random.Generator, n: int, p: float, q: float) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "episode": range(n),
            "success": rng.random(n) < p,
            "mean_requested_reliability": np.clip(rng.normal(q, 0.02, n), 0, 1),
            "delivered_fraction": np.clip(rng.normal(q, 0.02, n), 0, 1),
        }
    )


def _write_all(out: Path) -> None:
    rng = np.random.default_rng(0)
    for pipeline, policies in {
        "learned": [("MLP state est., static QoS", 1.0, 1.0), ("MLP, dynamic QoS", 0.98, 0.13)],
        "model_based": [("predictor, static QoS", 1.0, 1.0), ("predictor, rule QoS", 0.95, 0.2)],
    }.items():
        frames = [
            _episodes(rng, 20, p, q).assign(pipeline=pipeline, policy=name)
            for name, p, q in policies
        ]
        # Split over two tables: tab_p.<suffix> are concatenated; pipeline from the suffix.
        write_results(
            out,
            table=pd.concat(frames).drop(columns="pipeline"),
            config=None,
            name=f"tab_p.{pipeline}",
        )
    cn = [
        _episodes(rng, 5, max(0.0, 1 - 0.1 * tau * v / 0.2), 1.0).assign(
            pipeline=pipe, estimator=est, belt_speed_mps=v, latency_steps=tau
        )
        for pipe, est in [("learned", "mlp"), ("learned", "none"), ("model_based", "predictor")]
        for v in (0.2, 0.6)
        for tau in range(4)
    ]
    write_results(out, table=pd.concat(cn), config=None, name="fig_cn")
    steps = pd.DataFrame(
        {
            "t": np.tile(np.arange(30), 2),
            "episode": np.repeat([0, 1], 30),
            "qos_reliability": rng.random(60),
            "delivered": rng.random(60) < 0.5,
            "lifted": np.tile(np.arange(30) > 20, 2),
            "success": np.repeat([False, True], 30),
        }
    )
    write_results(out, table=steps.assign(pipeline="learned"), config=None, name="fig_lat")
    # fig_wifi already aggregated: success_rate + trials.
    wifi = pd.DataFrame(
        [
            {"pipeline": pipe, "policy": pol, "n_robots": n, "trials": 10, "success_rate": s}
            for pipe in ("learned", "model_based")
            for pol, drop in (("static QoS", 0.2), ("dynamic QoS", 0.05))
            for n, s in ((2, 1.0), (4, 1 - 2 * drop), (6, 1 - 4 * drop))
        ]
    )
    write_results(out, table=wifi, config=None, name="fig_wifi")


def test_report_renders_every_table(tmp_path: Path) -> None:
    _write_all(tmp_path)
    run_sweep(
        SweepConfig(
            n_seeds=2,
            robot_counts=(1, 6),
            pipelines=("none", "predictor"),
            params={"horizon_steps": 20},
        ),
        tmp_path,
        backend="serial",
    )
    report = build_report(tmp_path, config=ReportConfig(dpi=40))
    assert report.skipped == {}
    assert set(report.figures) == {"tab_p", "fig_cn", "fig_lat", "fig_wifi", "sweep"}
    for figure in report.figures.values():
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = report.markdown.read_text()
    for needle in (
        "Table I",
        "Fig. 4",
        "Fig. 5",
        "Fig. 6",
        "Sweep sweep",
        "model-based",
        "| learned |",
        "78%",
        "![Fig. 4](./fig_cn.png)",
    ):
        assert needle in text
    # The report folder is not mistaken for results.
    assert "report" not in ResultsDir(tmp_path).names


def test_missing_and_malformed_tables_are_skipped(tmp_path: Path) -> None:
    write_results(
        tmp_path,
        table=pd.DataFrame({"pipeline": ["learned"], "policy": ["x"]}),
        config=None,
        name="tab_p",
    )
    report = build_report(tmp_path, tmp_path / "r")
    assert report.sections == []
    assert report.skipped["tab_p"] == "missing column success | successes | success_rate"
    assert report.skipped["fig_cn"] == "no such table in the results folder"
    assert "## Not rendered" in report.markdown.read_text()


def test_report_reads_the_tables_other_commands_write(tmp_path: Path) -> None:
    """Shapes written by ``codesign evaluate fig-cn`` and ``codesign wifi capacity``."""
    cn = pd.DataFrame(
        [
            {
                "sweep": sweep,
                "belt_speed_mps": v,
                "estimator": est,
                "latency_steps": tau,
                "reliability": q,
                "trials": 10,
                "successes": 10 - tau - (est == "none") * 3,
                "success_rate": (10 - tau - (est == "none") * 3) / 10,
            }
            for sweep, points in (
                ("delay", [(t, 1.0) for t in range(3)]),
                ("reliability", [(1, 0.5), (1, 0.2)]),
            )
            for v in (0.2, 0.6)
            for est in ("predictor", "none")
            for tau, q in points
        ]
    )
    write_results(tmp_path, table=cn, config=None, name="fig_cn")
    capacity = pd.DataFrame(
        [
            {
                "channel": "paper",
                "scheduler": s,
                "pipeline": p,
                "robots": n,
                "trial": k,
                "success_rate": 1.0 if p == "codesign" or n < 6 else 0.5,
                "mean_reliability": 0.4,
                "delivered_fraction": 0.9,
            }
            for s in ("greedy", "convex")
            for p in ("static", "codesign")
            for n in (2, 6)
            for k in range(2)
        ]
    )
    write_results(tmp_path, table=capacity, config=None, name="wifi_capacity")
    table = pd.DataFrame(
        {
            "row": ["MLP state est., static QoS", "MLP state est., dynamic QoS"],
            "estimator": ["mlp", "mlp"],
            "success_rate": [1.0, 0.98],
            "trials": [100, 100],
            "mean_requested_reliability": [1.0, 0.13],
        }
    )
    write_results(tmp_path, table=table, config={"pipeline": "model-free"}, name="tab_p")
    report = build_report(tmp_path, config=ReportConfig(dpi=40))
    assert set(report.figures) == {"fig_cn", "fig_wifi", "tab_p"}
    assert "| learned | MLP state est., dynamic QoS | mlp | 100 | 98% [93%, 99%] | 13% |" in (
        report.markdown.read_text()
    )
    text = report.markdown.read_text()
    assert "| predictor | 0.2 | 100% (10) | 90% (10) | 80% (10) |" in text
    assert "q=0.5" in text and "| static | greedy | paper | 100% | 50% |" in text


def test_report_pools_the_robot_episodes_of_capacity_trials(tmp_path: Path) -> None:
    """A ``codesign wifi capacity`` trial counts its N robots: 2 trials x 4 robots = 8."""
    trials = pd.DataFrame(
        [
            {"channel": "paper", "scheduler": "greedy", "pipeline": p, "robots": 4, "trial": k,
             "successes": s, "success_rate": s / 4}
            for p, successes in (("static", (3, 3)), ("codesign", (4, 4)))
            for k, s in enumerate(successes)
        ]
    )  # fmt: skip
    write_results(tmp_path, table=trials, config=None, name="fig_wifi")
    text = build_report(tmp_path, config=ReportConfig(dpi=40)).markdown.read_text()
    assert "| static | greedy | paper | 75% (8) |" in text
    assert "| codesign | greedy | paper | 100% (8) |" in text
    assert "the band is its 95% Wilson interval" in text


def test_success_summary_wilson() -> None:
    frame = pd.DataFrame({"g": ["a"] * 10, "success": [True] * 8 + [False] * 2})
    row = success_summary(frame, ["g"]).iloc[0]
    assert (row["trials"], row["success_rate"]) == (10, 0.8)
    assert round(row["ci_low"], 4) == 0.4902 and round(row["ci_high"], 4) == 0.9433


def test_cli_report(tmp_path: Path) -> None:
    _write_all(tmp_path)
    app = typer.Typer(pretty_exceptions_enable=False)
    report_cli.register(app)

    @app.callback()
    def _root() -> None:
        pass

    runner = CliRunner()
    result = runner.invoke(app, ["report", str(tmp_path), "--dpi", "40", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert Path(data["report"]).is_file() and set(data["figures"]) >= {"tab_p", "fig_wifi"}
    result = runner.invoke(app, ["report", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: results folder") and result.stderr.count("\n") == 1
    result = runner.invoke(app, ["report", str(tmp_path), "--confidence", "1.5"])
    assert result.stderr == "error: confidence must be in (0, 1), got 1.5\n"
    help_text = runner.invoke(app, ["report", "--help"]).stdout
    defaults = {f.name: f.default for f in dataclasses.fields(ReportConfig)}
    assert f"[default: {defaults['dpi']}]" in help_text
    assert f"[default: {defaults['confidence']}]" in help_text


def test_report_draws_with_the_studies_renderers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each figure has one renderer, the study's: the report calls it, it draws no copy."""
    _write_all(tmp_path)
    run_sweep(
        SweepConfig(n_seeds=1, robot_counts=(1,), params={"horizon_steps": 10}),
        tmp_path,
        backend="serial",
    )
    calls: dict[str, list[Path]] = {}
    for figure, module, name in (
        ("tab_p", table_pareto_plot, "plot_pareto"),
        ("fig_cn", fig_cn, "plot_fig_cn"),
        ("fig_lat", table_figures, "plot_timeline"),
        ("fig_wifi", fig_wifi_figures, "plot_capacity"),
        ("sweep", sweep_figures, "plot_sweep"),
    ):
        real = getattr(module, name)

        def spy(data, path, *args, _real=real, _figure=figure, **kwargs):
            calls.setdefault(_figure, []).append(Path(path))
            return _real(data, path, *args, **kwargs)

        monkeypatch.setattr(module, name, spy)
    report = build_report(tmp_path, config=ReportConfig(dpi=40))
    assert {name: len(paths) for name, paths in calls.items()} == dict.fromkeys(
        ("tab_p", "fig_cn", "fig_lat", "fig_wifi", "sweep"), 1
    )
    assert {name: paths[0] for name, paths in calls.items()} == report.figures


def test_report_sums_mpc_failures(tmp_path: Path) -> None:
    frame = pd.DataFrame(
        {
            "pipeline": ["model_based"] * 3 + ["learned"] * 3,
            "policy": ["MPC + predictor"] * 3 + ["SAC + MLP"] * 3,
            "success": [True, True, False, True, True, True],
            "mean_requested_reliability": [1.0] * 6,
            "mpc_failures": [1.0, 0.0, 4.0] + [np.nan] * 3,
        }
    )
    write_results(tmp_path, table=frame, config=None, name="tab_p")
    cn = pd.DataFrame(
        {
            "estimator": ["predictor"] * 4 + ["none"] * 4,
            "latency_steps": [0, 0, 1, 1] * 2,
            "success": [True] * 8,
            "mpc_failures": [0, 1, 0, 2, 0, 0, 0, 0],
        }
    )
    write_results(tmp_path, table=cn, config=None, name="fig_cn")
    text = build_report(tmp_path, config=ReportConfig(dpi=40)).markdown.read_text()
    assert "| model-based | MPC + predictor | 3 | 67% [21%, 94%] | 100% | 5 |" in text
    assert "Failed MPC solves (summed over the episodes): predictor: 3; none: 0." in text
    assert "| learned | SAC + MLP | 3 | 100% [44%, 100%] | 100% |  |" in text
