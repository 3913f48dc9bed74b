"""``codesign tune`` and the evaluation protocol: thresholds and selections on ``dev`` only."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.adaptation.rules import tune_threshold
from codesign_mb.cli import app
from codesign_mb.core.registry import ComponentSpec, PlantSpec, factory, plant_factory
from codesign_mb.core.results import ResultsDir, file_digest
from codesign_mb.core.seeds import SEED_SETS, episode_seeds, seed_set
from codesign_mb.evaluation.evaluate import evaluate
from codesign_mb.plants.scenarios import scenario_options
from codesign_mb.stages.stage_a import StageAConfig
from codesign_mb.stages.stage_c import StageCConfig
from codesign_mb.stages.training import selection_seeds, stage_seeds
from codesign_mb.studies import tune as tune_module
from codesign_mb.studies import tuned as tuned_module
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_figures import expanded_rows, table_inputs, write_table_outputs
from codesign_mb.studies.table_rows import (
    PLANT_PRESETS,
    TablePlant,
    TableRow,
    codesign_rule_row,
    row_for_plant,
)
from codesign_mb.studies.tune import TuneConfig, run_tune, tuned_entry
from codesign_mb.studies.tuned import (
    RULE_THRESHOLD_DEFAULT_M,
    TUNED,
    plant_config,
    read_tuned,
    rule_options,
    write_tuned,
)

# The toy conveyor with no estimator: the scripted pick acts on the last packet as is, so it
# needs fresh packets and its success falls as the rule's threshold grows (0.01 m: all,
# 0.05 m: none, on 20 dev episodes).
TOY = PlantSpec("toy", {"horizon": 60, "belt_speed_mps": 0.3})
TOY_ROW = TableRow(
    "toy pick, rule QoS",
    ComponentSpec("toy_pick"),
    ComponentSpec("none"),
    ComponentSpec("rule", options={"threshold_m": TUNED, "low": 0.0}),
)


@pytest.fixture
def tuned_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The tuned file the rows read, moved to a temporary folder."""
    monkeypatch.setattr(tuned_module, "models_dir", lambda: tmp_path)
    return tmp_path / "tuned" / "rule_threshold.json"


def _entry(plant: PlantSpec, threshold_m: float, **changes: Any) -> dict[str, Any]:
    """A tuned-file entry for ``plant`` and the co-design row's rule (as ``--write`` makes)."""
    return {
        "threshold_m": threshold_m,
        "target_success": 0.98,
        "target_met": True,
        "seed_set": "dev",
        "episodes_per_probe": 100,
        "rule_options": rule_options(codesign_rule_row().qos.options),
        "plant": plant_config(plant),
        **changes,
    }


def _synthetic_evaluate(edge_m: float, calls: list[tuple[float, int, int]]) -> Any:
    """A stand-in for ``evaluate``: every episode succeeds below ``edge_m``, none above."""

    def fake(controller, estimator, qos, plant, trials, seed, **kwargs):
        threshold = qos.kwargs["threshold_m"]
        calls.append((threshold, trials, seed))
        return pd.DataFrame(
            {
                "episode": range(trials),
                "success": [threshold <= edge_m] * trials,
                "mean_requested_reliability": [min(1.0, 0.001 / threshold)] * trials,
                "delivered_fraction": [min(1.0, 0.001 / threshold)] * trials,
                "steps": [60] * trials,
            }
        )

    return fake


# -- the bisection ---------------------------------------------------------------------------
@pytest.mark.parametrize("edge_m", [0.0031, 0.04, 0.7])
def test_bisection_brackets_the_edge_of_a_monotone_measure(edge_m: float) -> None:
    low, high, iterations = 0.002, 1.0, 8
    probes_seen: list[float] = []

    def measure(threshold: float) -> tuple[float, float]:
        probes_seen.append(threshold)
        return (1.0 if threshold <= edge_m else 0.5), 0.001 / threshold

    best, probes = tune_threshold(
        measure, target_success=0.98, low=low, high=high, iterations=iterations
    )
    assert [p.threshold for p in probes] == probes_seen
    # The largest feasible probe, within one final bracket (log-width / 2^iterations) below
    # the edge.
    width = (high / low) ** (1 / 2**iterations)
    assert edge_m / width <= best <= edge_m
    assert best == max(p.threshold for p in probes if p.success_rate >= 0.98)
    # Each probe is the geometric middle of the bracket the earlier ones left.
    lo, hi = low, high
    for p in probes:
        assert p.threshold == pytest.approx(math.sqrt(lo * hi))
        lo, hi = (p.threshold, hi) if p.success_rate >= 0.98 else (lo, p.threshold)


def test_run_tune_probes_the_dev_seeds_and_keeps_the_largest_feasible_threshold(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[float, int, int]] = []
    monkeypatch.setattr(tune_module, "evaluate", _synthetic_evaluate(0.05, calls))
    result = run_tune(TuneConfig(scenario="constant-0.6", trials=7, iterations=6))
    assert {(trials, seed) for _, trials, seed in calls} == {(7, SEED_SETS["dev"])}
    assert len(calls) == 6 and result.target_met and result.limited_by == ""
    assert result.threshold_m == max(t for t, _, _ in calls if t <= 0.05)
    assert result.probes["chosen"].sum() == 1
    assert result.chosen["threshold_m"] == result.threshold_m
    assert result.chosen["success_rate"] == 1.0
    assert result.chosen["mean_requested_reliability"] == pytest.approx(0.001 / result.threshold_m)


def test_run_tune_measures_low_when_no_probe_meets_the_target(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[float, int, int]] = []
    monkeypatch.setattr(tune_module, "evaluate", _synthetic_evaluate(0.001, calls))
    result = run_tune(TuneConfig(trials=3, iterations=4, low_m=0.002))
    assert len(calls) == 5 and calls[-1][0] == 0.002  # the fallback is measured, not assumed
    assert result.threshold_m == 0.002 and not result.target_met
    assert result.limited_by == "low" and result.chosen["success_rate"] == 0.0


def test_run_tune_says_when_the_bracket_top_set_the_threshold(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[float, int, int]] = []
    monkeypatch.setattr(tune_module, "evaluate", _synthetic_evaluate(10.0, calls))
    result = run_tune(TuneConfig(trials=3, iterations=4, high_m=1.0))
    assert result.target_met and result.limited_by == "high"
    assert result.threshold_m == max(t for t, _, _ in calls) < 1.0


def test_tune_on_the_toy_meets_the_target_on_a_fresh_evaluation() -> None:
    config = TuneConfig(plant=TOY, row=TOY_ROW, trials=20, iterations=5, target_success=0.95)
    result = run_tune(config)
    assert result.target_met
    assert 0.002 < result.threshold_m < 0.05  # all at 0.01 m, none at 0.05 m (see TOY)
    # An independent evaluation of the chosen threshold on the same dev episodes.
    qos = ComponentSpec("rule", options={"threshold_m": result.threshold_m, "low": 0.0})
    table = evaluate(
        factory("controller", TOY_ROW.controller),
        factory("estimator", TOY_ROW.estimator),
        factory("qos", qos),
        plant_factory(TOY),
        20,
        seed_set("dev"),
        workers=1,
    )
    assert table["success"].mean() >= 0.95
    assert table["success"].mean() == result.chosen["success_rate"]
    assert table["mean_requested_reliability"].mean() == pytest.approx(
        result.chosen["mean_requested_reliability"]
    )
    assert sorted(result.episodes["seed"].unique()) == sorted(episode_seeds(seed_set("dev"), 20))


# -- the protocol: dev only ------------------------------------------------------------------
def test_tune_refuses_the_test_seed_set(runner: CliRunner) -> None:
    with pytest.raises(ValueError, match="refusing to tune on the 'test' seed set"):
        TuneConfig(seed_set="test")
    with pytest.raises(ValueError, match="seed set must be one of"):
        TuneConfig(seed_set="train")
    result = runner.invoke(app, ["tune", "--seed-set", "test", "-n", "1"])
    assert result.exit_code == 2
    assert "refusing to tune on the 'test' seed set" in result.stderr


def test_dev_and_test_seed_sets_are_disjoint_for_the_counts_used() -> None:
    # Spawned seeds are prefix-stable, so disjointness at n covers every smaller count.
    n = 10_000
    assert n >= max(TuneConfig().trials, TableConfig().trials, 200)  # 200: issue 14's runs
    dev, test = episode_seeds(seed_set("dev"), n), episode_seeds(seed_set("test"), n)
    assert episode_seeds(seed_set("dev"), 100) == dev[:100]
    assert not set(dev) & set(test)
    # keep_best selects on dev (the same episodes for every stage), ...
    for config in (StageAConfig(), StageCConfig()):
        assert selection_seeds(config.eval_episodes) == dev[: config.eval_episodes]
    # ... and the shipped checkpoints' selection and final evaluations (stage roots 2 and 3
    # of seed 0) never used a test episode.
    for root in (2, 3):
        assert not set(stage_seeds(root, 1_000)) & set(test)


# -- the tuned file and the tables -------------------------------------------------------------
def test_the_tuned_file_round_trips_and_keeps_other_scenarios(tmp_path: Path) -> None:
    path = tmp_path / "rule_threshold.json"
    paper = PlantSpec("conveyor", scenario_options("paper"))
    fast = PlantSpec("conveyor", scenario_options("constant-0.6"))
    write_tuned("paper", _entry(paper, 0.123), path)
    write_tuned("constant-0.6", _entry(fast, 0.05), path)
    write_tuned("paper", _entry(paper, 0.2), path)  # replaces paper's, keeps constant-0.6's
    stored = read_tuned(path)
    assert set(stored) == {"paper", "constant-0.6"}
    assert stored["paper"] == json.loads(json.dumps(_entry(paper, 0.2)))
    assert stored["constant-0.6"]["threshold_m"] == 0.05
    with pytest.raises(ValueError, match="threshold_m must be a number > 0"):
        write_tuned("paper", _entry(paper, -1.0), path)
    assert read_tuned(tmp_path / "absent.json") == {}


def test_rows_take_the_threshold_tuned_for_their_plant(tuned_path: Path) -> None:
    write_tuned("paper", _entry(PLANT_PRESETS["0.2"].spec, 0.123), tuned_path)
    row = codesign_rule_row()
    assert row.qos.options["threshold_m"] == TUNED
    # The 0.2 m/s preset is the paper scenario's plant: it gets paper's threshold.
    on_slow = row_for_plant(row, PLANT_PRESETS["0.2"])
    assert on_slow.qos.options == {**row.qos.options, "threshold_m": 0.123}  # the rest kept
    assert on_slow.threshold_source.startswith("tuned on dev for paper")
    # Not tuned (yet): the documented default, saying so.
    on_fast = row_for_plant(row, PLANT_PRESETS["0.6"])
    assert on_fast.qos.options["threshold_m"] == RULE_THRESHOLD_DEFAULT_M
    assert "no tuned value" in on_fast.threshold_source
    custom = TablePlant("0.3 m/s", options={"belt_speed_mps": 0.3})
    assert row_for_plant(row, custom).qos.options["threshold_m"] == RULE_THRESHOLD_DEFAULT_M
    # A row with a number keeps it; a row without the rule is untouched.
    fixed = TableRow("fixed", row.controller, row.estimator, ComponentSpec("rule", options={
        "threshold_m": 0.02}))  # fmt: skip
    assert row_for_plant(fixed, PLANT_PRESETS["0.2"]) == fixed


def test_a_stale_tuned_threshold_falls_back_with_a_warning(tuned_path: Path) -> None:
    paper = PLANT_PRESETS["0.2"].spec
    gated = {**rule_options({"low": 0.0}), "innovation_gate": 3.0}  # tuned on another rule
    write_tuned("paper", _entry(paper, 0.123, rule_options=gated), tuned_path)
    with pytest.warns(RuntimeWarning, match="rerun `codesign tune --write`"):
        resolved = row_for_plant(codesign_rule_row(), PLANT_PRESETS["0.2"])
    assert resolved.qos.options["threshold_m"] == RULE_THRESHOLD_DEFAULT_M
    assert "stale" in resolved.threshold_source
    # The scenario's plant changed since it was tuned: also stale, not silently kept.
    write_tuned("paper", _entry(PLANT_PRESETS["0.6"].spec, 0.123), tuned_path)
    with pytest.warns(RuntimeWarning, match="tuned on another plant config"):
        resolved = row_for_plant(codesign_rule_row(), TablePlant("paper", scenario="paper"))
    assert resolved.qos.options["threshold_m"] == RULE_THRESHOLD_DEFAULT_M


def test_the_table_runs_and_records_each_plants_threshold(tuned_path: Path) -> None:
    slow = TablePlant("toy slow", "toy", {"horizon": 30, "belt_speed_mps": 0.1})
    fast = TablePlant("toy fast", "toy", {"horizon": 30, "belt_speed_mps": 0.3})
    write_tuned("toy-slow", _entry(slow.spec, 0.0123, rule_options=rule_options(
        TOY_ROW.qos.options)), tuned_path)  # fmt: skip
    config = TableConfig(rows=(TOY_ROW,), plants=(slow, fast), trials=2)
    summary, episodes = run_table(config)
    by_plant = summary.set_index("plant")
    assert by_plant.loc["toy slow", "rule_threshold_m"] == 0.0123
    assert by_plant.loc["toy slow", "rule_threshold_source"].startswith("tuned on dev for toy-slow")
    assert by_plant.loc["toy fast", "rule_threshold_m"] == RULE_THRESHOLD_DEFAULT_M
    assert json.loads(by_plant.loc["toy fast", "qos_options"]) == {
        "threshold_m": RULE_THRESHOLD_DEFAULT_M,
        "low": 0.0,
    }
    # table.json records the rows as run on each plant and the digest of the tuned file.
    write_table_outputs(summary, episodes, tuned_path.parent / "table", config)
    meta = ResultsDir(tuned_path.parent / "table").meta("tab_p")
    expanded = meta["extra"]["rows"]
    assert expanded == json.loads(json.dumps(expanded_rows(config)))
    assert expanded["toy slow"][0]["qos"]["options"]["threshold_m"] == 0.0123
    assert expanded["toy fast"][0]["threshold_source"].startswith("default")
    digests = meta["provenance"]["checkpoints"]
    assert digests == {"tuned/rule_threshold.json": file_digest(tuned_path)}


def test_the_table_records_the_digest_of_every_checkpoint_it_reads(tuned_path: Path) -> None:
    write_tuned("paper", _entry(PLANT_PRESETS["0.2"].spec, 0.123), tuned_path)
    config = TableConfig(pipeline="all")
    inputs = table_inputs(config)
    named = {
        spec.checkpoint
        for row in config.table_rows()
        for spec in (row.controller, row.estimator, row.qos)
        if spec.checkpoint
    }
    wanted = {c for c in named if _exists(c)}  # a missing one is in the summary's status
    assert "checkpoints/stage_d/qos" in wanted
    assert set(inputs) == wanted | {"tuned/rule_threshold.json"}
    assert inputs["tuned/rule_threshold.json"] == tuned_path


def test_plant_presets_are_the_scenarios() -> None:
    for name, scenario in (
        ("0.2", "constant-0.2"),
        ("0.6", "constant-0.6"),
        ("variable", "variable"),
    ):
        preset = PLANT_PRESETS[name]
        assert preset.scenario == scenario and preset.options == scenario_options(scenario)
    with pytest.raises(ValueError, match="options are not those of scenario 'paper'"):
        TablePlant("paper?", options={"belt_speed_mps": 0.6}, scenario="paper")
    summary_scenario = TableConfig(plants=("0.6",)).table_plants()[0].scenario
    assert summary_scenario == "constant-0.6"


# -- the command -------------------------------------------------------------------------------
def test_tune_command_writes_its_probes_and_the_tuned_file_with_provenance(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[float, int, int]] = []
    monkeypatch.setattr(tune_module, "evaluate", _synthetic_evaluate(0.05, calls))
    tuned, out = tmp_path / "tuned.json", tmp_path / "out"
    args = ["tune", "--scenario", "constant-0.6", "-n", "4", "--iterations", "5"]
    args += ["-o", str(out), "--write", "--tuned-file", str(tuned), "--json"]
    monkeypatch.setattr(sys, "argv", ["codesign", *args])  # the command line it records
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.stderr
    printed = json.loads(result.stdout)
    entry = read_tuned(tuned)["constant-0.6"]
    assert (
        entry["threshold_m"] == printed["threshold_m"] == max(t for t, _, _ in calls if t <= 0.05)
    )
    assert entry["seed_set"] == "dev" and entry["seed"] == SEED_SETS["dev"]
    assert entry["episodes_per_probe"] == 4 and entry["bracket_m"] == [0.002, 1.0]
    assert [p["threshold_m"] for p in entry["probes"]] == [t for t, _, _ in calls]
    assert entry["command"].startswith("codesign tune --scenario constant-0.6")
    assert {"commit", "versions", "date"} <= set(entry) and entry["versions"]["numpy"]
    assert entry["plant"] == plant_config(PLANT_PRESETS["0.6"].spec)
    results = ResultsDir(out)
    assert set(results.names) == {"tune_probes", "tune_episodes"}
    meta = results.meta("tune_probes")
    assert "commit" in meta["provenance"] and meta["extra"]["threshold_m"] == entry["threshold_m"]
    assert meta["config"]["seed_set"] == "dev"
    # What the tables then read for that plant:
    monkeypatch.setattr(tuned_module, "tuned_file", lambda: tuned)  # read by the rows
    row = row_for_plant(codesign_rule_row(), PLANT_PRESETS["0.6"])
    assert row.qos.options["threshold_m"] == entry["threshold_m"]


def test_tune_command_writes_nothing_when_the_target_is_missed(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tune_module, "evaluate", _synthetic_evaluate(0.001, []))
    tuned = tmp_path / "tuned.json"
    args = ["tune", "-n", "2", "--iterations", "2", "-o", str(tmp_path / "out")]
    result = runner.invoke(app, [*args, "--write", "--tuned-file", str(tuned)])
    assert result.exit_code == 2 and "nothing written" in result.stderr
    assert not tuned.exists()
    assert ResultsDir(tmp_path / "out").table("tune_probes")["meets_target"].sum() == 0


def test_a_custom_plant_cannot_be_written_by_scenario() -> None:
    result = tune_module.TuneResult(
        config=TuneConfig(plant=TOY, row=TOY_ROW),
        threshold_m=0.01,
        target_met=True,
        chosen={},
        probes=pd.DataFrame(),
        episodes=pd.DataFrame(),
        wall_time_s=0.0,
    )
    with pytest.raises(ValueError, match="custom plant"):
        tuned_entry(result)


def test_the_shipped_thresholds_are_current_and_tuned_on_dev() -> None:
    """Fails when the rule, the co-design row or a scenario changed since the file was made:
    rerun ``codesign tune --scenario NAME -n 100 -j 2 --write`` (see the file's commands)."""
    shipped = read_tuned()
    assert {"realistic", "paper", "constant-0.6", "variable"} <= set(shipped)
    for scenario, entry in shipped.items():
        plant = PlantSpec("conveyor", scenario_options(scenario))
        assert entry["seed_set"] == "dev" and entry["seed"] == SEED_SETS["dev"], scenario
        assert entry["target_met"] and entry["success_rate"] >= entry["target_success"]
        assert entry["plant"] == plant_config(plant), f"{scenario}: the scenario changed"
        assert entry["rule_options"] == rule_options(codesign_rule_row().qos.options), (
            f"{scenario}: the rule changed since it was tuned"
        )
        resolved = row_for_plant(codesign_rule_row(), TablePlant(scenario, scenario=scenario))
        assert resolved.qos.options["threshold_m"] == entry["threshold_m"]


def test_tune_sizes_are_capped_with_a_message_naming_the_cap() -> None:
    from codesign_mb.core.config import ConfigError

    with pytest.raises(ConfigError, match=r"trials .*episodes or seeds of one run"):
        TuneConfig(scenario="paper", trials=10**9)
    with pytest.raises(ConfigError, match=r"iterations .*bisection probes"):
        TuneConfig(scenario="paper", iterations=10**6)


def _exists(checkpoint: str) -> bool:
    from codesign_mb.core.registry import resolve_checkpoint

    try:
        resolve_checkpoint(checkpoint)
    except ValueError:
        return False
    return True
