"""Reference rows of a table: blind, oracle, static per stack, random at a co-design row's PDR."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.adaptation.base import RandomQos
from codesign_mb.cli import app
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_figures import markdown_table
from codesign_mb.studies.table_refs import (
    draw_references,
    fixed_references,
    random_sources,
    reference_legend,
    reference_stacks,
)
from codesign_mb.studies.table_rows import PIPELINES, TablePlant, TableRow
from codesign_mb.studies.table_select import best_row

TOY = ComponentSpec("toy_pick")
NONE = ComponentSpec("none")
STATIC = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})
AGE_RULE = ComponentSpec("age_rule", options={"low": 0.0, "high": 1.0, "max_age_steps": 4})
ROWS = (
    TableRow("toy, static QoS", TOY, NONE, STATIC),
    TableRow("toy, age rule (co-design)", TOY, NONE, AGE_RULE),
)
PLANTS = (
    TablePlant("toy slow", "toy", {"horizon": 60, "belt_speed_mps": 0.2}),
    TablePlant("toy fast", "toy", {"horizon": 60, "belt_speed_mps": 0.3}),
)


def _draws(policy: RandomQos, n: int) -> np.ndarray:
    return np.array([policy.request(np.zeros(3), 0).reliability for _ in range(n)])


# -- the random QoS policy ----------------------------------------------------------------------
@pytest.mark.parametrize("p", [0.0, 0.06, 0.3, 0.5, 1.0])
def test_random_qos_is_bernoulli_p(p: float) -> None:
    policy = RandomQos(probability=p, latency_steps=2)
    policy.reset(seed=7)
    n = 20_000
    q = _draws(policy, n)
    assert set(np.unique(q)) <= {0.0, 1.0}  # a packet is sent (q = 1) or not (q = 0)
    assert policy.request(np.zeros(3), 0).latency_steps == 2
    # Binomial(n, p): the mean within 4 standard errors, the draws uncorrelated step to step
    assert abs(q.mean() - p) <= 4 * math.sqrt(p * (1 - p) / n) + 1e-12
    if 0 < p < 1:
        lag1 = np.corrcoef(q[:-1], q[1:])[0, 1]
        assert abs(lag1) < 4 / math.sqrt(n)


def test_random_qos_is_seeded_through_reset() -> None:
    a, b = RandomQos(0.4), RandomQos(0.4)
    a.reset(seed=123)
    b.reset(seed=123)
    first = _draws(a, 200)
    assert np.array_equal(first, _draws(b, 200))  # same seed, same sequence
    a.reset(seed=123)
    assert np.array_equal(first, _draws(a, 200))  # reset(seed=) restarts the stream
    b.reset(seed=124)
    assert not np.array_equal(first, _draws(b, 200))
    c = RandomQos(0.4)
    c.reset(seed=123)
    head = _draws(c, 100)
    c.reset()  # no seed: the stream continues
    assert np.array_equal(np.concatenate([head, _draws(c, 100)]), first)


def test_random_qos_is_a_registered_kind_with_checked_options() -> None:
    env = make_plant(PlantSpec("toy"))
    spec = ComponentSpec("random", options={"probability": 0.25, "latency_steps": 1})
    policy = build("qos", spec, env)
    assert isinstance(policy, RandomQos) and policy.probability == 0.25
    with pytest.raises(ValueError, match=r"probability must be in \[0, 1\], got 1.5"):
        RandomQos(1.5)
    with pytest.raises(ValueError, match="latency_steps must be >= 0"):
        RandomQos(0.5, latency_steps=-1)


# -- which reference rows ------------------------------------------------------------------------
def test_reference_stacks_of_the_pipelines() -> None:
    def stacks(pipeline: str) -> list[tuple[str, str]]:
        return [(c.kind, e.kind) for c, e in reference_stacks(PIPELINES[pipeline]())]

    assert stacks("model-based") == [("mpc", "predictor"), ("mpc", "belt_imm")]
    assert stacks("model-free") == [("sac", "lstm"), ("sac", "mlp")]  # model-free, hybrid
    assert stacks("all") == [("sac", "mlp"), ("mpc", "predictor")]
    refs = fixed_references(PIPELINES["model-based"]())
    fixed = [
        ("blind", {"reliability": 0.0, "latency_steps": 1}),
        ("oracle", {"reliability": 1.0, "latency_steps": 0}),
        ("static", {"reliability": 1.0, "latency_steps": 1}),
    ]
    assert [(r.kind, r.row.qos.options) for r in refs] == fixed * 2  # one set per stack
    assert refs[3].row.name == "MPC + belt IMM, blind (q = 0)"
    sources = [r.name for r in random_sources(PIPELINES["model-based"]())]
    assert sources == [
        "MPC, no estimator, rule QoS",
        "MPC + predictor, rule QoS (co-design)",
        "MPC + belt IMM, event rule",
        "MPC + belt IMM, QoS planner (co-design)",
    ]


def test_references_default_on_for_pipelines_off_for_given_rows() -> None:
    assert TableConfig(pipeline="model-based").with_references()
    assert not TableConfig(pipeline="model-based", references=False).with_references()
    assert not TableConfig(rows=ROWS, plants=PLANTS).with_references()
    assert TableConfig(rows=ROWS, plants=PLANTS, references=True).with_references()
    clash = TableRow("toy pick, no estimator, blind (q = 0)", TOY, NONE, STATIC)
    with pytest.raises(ValueError, match="row names must be unique"):
        TableConfig(rows=(clash, ROWS[1]), plants=PLANTS, references=True)


def test_best_row_never_picks_a_reference() -> None:
    summary = pd.DataFrame(
        {
            "plant": ["a"] * 3,
            "row": ["static", "co-design", "random, same PDR as: co-design"],
            "status": ["ok"] * 3,
            "reference": [False, False, True],
            "success_rate": [1.0, 0.90, 0.99],
            "mean_requested_reliability": [1.0, 0.1, 0.1],
        }
    )
    assert best_row(summary, "a") == "static"


# -- a run with reference rows -------------------------------------------------------------------
@pytest.fixture(scope="module")
def run() -> tuple[pd.DataFrame, pd.DataFrame, list[int]]:
    import codesign_mb.studies.table as table_module

    calls: list[int] = []
    real = table_module.run_jobs

    def counting(jobs, **kwargs):
        calls.append(len(jobs))
        return real(jobs, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(table_module, "run_jobs", counting)
        config = TableConfig(rows=ROWS, plants=PLANTS, trials=60, references=True, workers=1)
        summary, episodes = run_table(config)
    return summary, episodes, calls


def test_reference_rows_follow_each_plants_rows_with_their_qos(run) -> None:
    summary, episodes, calls = run
    # pass 1: 2 rows + 3 fixed references, the static one the same cell as the static row;
    # pass 2: the random reference of the co-design row; one pool each, both plants in it
    assert calls == [2 * 4, 2 * 1]
    for plant in ("toy slow", "toy fast"):
        mine = summary[summary["plant"] == plant].set_index("kind", drop=False)
        assert mine["kind"].tolist() == ["row", "row", "blind", "oracle", "static", "random"]
        assert (mine["scenario"] == plant).all() and (mine["status"] == "ok").all()
        assert mine["reference"].tolist() == [False, False, True, True, True, True]
        assert not mine.loc[mine["reference"], "pareto"].any()
        eps = episodes[episodes["plant"] == plant].groupby("row")
        blind = eps.get_group(mine.loc["blind", "row"])
        assert (blind["mean_requested_reliability"] == 0).all()
        assert (blind["delivered_fraction"] == 0).all()
        oracle = eps.get_group(mine.loc["oracle", "row"])
        assert (oracle["mean_requested_reliability"] == 1).all()
        assert (oracle["mean_latency_steps"] == 0).all() and (oracle["mean_age"] == 0).all()
        static = eps.get_group(mine.loc["static", "row"])
        assert (static["mean_latency_steps"] == 1).all() and (static["mean_age"] == 1).all()
        # the static reference is the static row (same cell, same seeded episodes)
        row = mine[mine["row"] == "toy, static QoS"].iloc[0]
        assert mine.loc["static", "success_rate"] == row["success_rate"]


def test_random_reference_spends_the_co_design_rows_budget(run) -> None:
    summary, episodes, _ = run
    for plant in ("toy slow", "toy fast"):
        mine = summary[summary["plant"] == plant]
        random = mine[mine["kind"] == "random"].iloc[0]
        assert random["reference_of"] == "toy, age rule (co-design)"
        assert random["qos"] == "random"
        eps = episodes[episodes["plant"] == plant]
        codesign = eps[eps["row"] == "toy, age rule (co-design)"]
        drawn = eps[eps["row"] == random["row"]]
        p = codesign["mean_requested_reliability"].mean()
        assert 0.1 < p < 0.9
        # each episode's mean of Bernoulli(p) draws over its steps; the table averages them
        se = math.sqrt(p * (1 - p) * (1.0 / drawn["steps"]).sum()) / len(drawn)
        assert abs(random["mean_requested_reliability"] - p) < 4 * se
        assert (drawn["mean_latency_steps"] == round(codesign["mean_latency_steps"].mean())).all()


def test_markdown_marks_the_reference_rows(run) -> None:
    summary, _, _ = run
    text = markdown_table(summary)
    assert "| toy slow | toy, static QoS |" in text  # own rows unchanged
    assert "| toy slow | *toy pick, no estimator, blind (q = 0)* (reference: blind) |" in text
    assert "*random, same PDR as: toy, age rule (co-design)* (reference: random)" in text


def test_pareto_figure_draws_random_sending_from_blind_to_static(run, tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary, _, _ = run
    mine = summary[(summary["plant"] == "toy slow") & summary["reference"]]
    fig, ax = plt.subplots()
    greys: dict[tuple[str, ...], str] = {}
    kinds: set[str] = set()
    draw_references(ax, mine, greys, kinds)
    dotted = [line for line in ax.lines if line.get_linestyle() == ":"]
    assert len(dotted) == 1  # one stack
    by_kind = mine.set_index("kind")
    expected = by_kind.loc[["blind", "random", "static"]]
    assert dotted[0].get_xdata().tolist() == pytest.approx(
        expected["mean_requested_reliability"].tolist()
    )
    assert dotted[0].get_ydata().tolist() == pytest.approx(expected["success_rate"].tolist())
    assert kinds == {"blind", "oracle", "static", "random"}
    legend = reference_legend(kinds, greys)
    assert "ref.: random sending, toy pick, no estimator" in legend
    plt.close(fig)


# -- the command ---------------------------------------------------------------------------------
TOY_CONFIG = """
[table]
trials = 4
references = true

[table.plant]
name = "toy"
options = { horizon = 40 }

[[table.rows]]
name = "toy, static QoS"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 1.0, latency_steps = 1 } }

[[table.rows]]
name = "toy, age rule"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "age_rule", options = { low = 0.0, high = 1.0, max_age_steps = 4 } }
"""


def test_cli_json_has_the_fields_and_the_reference_rows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    runner = CliRunner()
    config = tmp_path / "table.toml"
    config.write_text(TOY_CONFIG)
    out = tmp_path / "results"
    result = runner.invoke(app, ["table", "-c", str(config), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    shown = json.loads(result.stdout)
    for row in shown:
        for field in (
            "row",
            "scenario",
            "success_rate",
            "success_ci_low",
            "success_ci_high",
            "mean_requested_reliability",
            "kind",
            "reference",
        ):
            assert field in row, field
        assert row["scenario"] == "toy"
        assert row["success_ci_low"] <= row["success_rate"] <= row["success_ci_high"]
    assert [r["kind"] for r in shown] == ["row", "row", "blind", "oracle", "static", "random"]
    assert (out / "fig_pareto.png").stat().st_size > 5000
    quick = runner.invoke(
        app,
        ["table", "-c", str(config), "--out", str(tmp_path / "q"), "--json", "--no-references"],
    )
    assert quick.exit_code == 0, quick.output
    assert [r["kind"] for r in json.loads(quick.stdout)] == ["row", "row"]


def test_report_keeps_reference_rows_off_the_pareto_front() -> None:
    import pandas as pd

    from codesign_mb.studies.report_sections import _tab_p_points

    summary = pd.DataFrame(
        {
            "row": ["co-design", "blind", "oracle"],
            "kind": ["row", "blind", "oracle"],
            "plant": ["p", "p", "p"],
            "trials": [10, 10, 10],
            "success_rate": [0.9, 0.3, 1.0],
            "ci_low": [0.6, 0.1, 0.7],
            "ci_high": [1.0, 0.6, 1.0],
            "mean_requested_reliability": [0.1, 0.0, 1.0],
        }
    )
    points = _tab_p_points(summary, ["row", "plant"])
    assert list(points["kind"]) == ["row", "blind", "oracle"]
    # blind (less network) and oracle (more success) would dominate-or-tie as rows; as
    # references they are never on the front, and the one real row is.
    assert list(points["pareto"]) == [True, False, False]


def test_checkpoints_trained_on_another_layout_are_named() -> None:
    """The shipped learned rows read the paper's packet (with velocity): not realistic's."""
    from codesign_mb.core.registry import PlantSpec
    from codesign_mb.plants.scenarios import scenario_options
    from codesign_mb.studies.table_cost import incompatible_checkpoints
    from codesign_mb.studies.table_rows import model_based_rows, model_free_rows

    learned = model_free_rows()[0]  # SAC + MLP, static QoS
    realistic = PlantSpec("conveyor", scenario_options("realistic"))
    assert incompatible_checkpoints(learned, PlantSpec("conveyor", {})) == []
    assert incompatible_checkpoints(learned, PlantSpec("conveyor", {"belt_speed_mps": 0.6})) == []
    named = incompatible_checkpoints(learned, realistic)
    assert len(named) == 2 and "stage_a" in named[0] and "stage_d" in named[1]
    assert all(incompatible_checkpoints(row, realistic) == [] for row in model_based_rows())
