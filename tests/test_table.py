"""``codesign table``: rows x plants, missing checkpoints, training cost, the Pareto front."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.core.registry import ComponentSpec
from codesign_mb.plants.scenarios import SCENARIOS
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_cost import CPU_COLUMNS, training_cost
from codesign_mb.studies.table_figures import markdown_table
from codesign_mb.studies.table_rows import PLANT_PRESETS, TablePlant, TableRow, stack_of
from codesign_mb.studies.table_select import best_row, pareto_front

TOY_TABLE = """
[table]
trials = 2

[[table.plants]]
label = "toy slow"
name = "toy"
options = {{ horizon = 40, belt_speed_mps = 0.1 }}

[[table.plants]]
label = "toy fast"
name = "toy"
options = {{ horizon = 40, belt_speed_mps = 0.3 }}

[[table.rows]]
name = "scripted, static QoS"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "none" }}
qos = {{ kind = "static", options = {{ reliability = 1.0, latency_steps = 1 }} }}

[[table.rows]]
name = "scripted, 30% QoS"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "none" }}
qos = {{ kind = "static", options = {{ reliability = 0.3, latency_steps = 1 }} }}

[[table.rows]]
name = "scripted, SAC QoS"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "none" }}
qos = {{ kind = "learned", checkpoint = "{missing}" }}
"""


def _dominated_brute_force(success: list[float], reliability: list[float]) -> list[bool]:
    """Point i is on the front iff it is finite and no finite j dominates it."""
    n = len(success)
    front = []
    for i in range(n):
        if not (math.isfinite(success[i]) and math.isfinite(reliability[i])):
            front.append(False)
            continue
        dominated = any(
            math.isfinite(success[j])
            and math.isfinite(reliability[j])
            and success[j] >= success[i]
            and reliability[j] <= reliability[i]
            and (success[j] > success[i] or reliability[j] < reliability[i])
            for j in range(n)
            if j != i
        )
        front.append(not dominated)
    return front


# -- the Pareto front and the best row ---------------------------------------------------------
def test_pareto_front_on_a_hand_made_frame() -> None:
    frame = pd.DataFrame(
        {
            "row": ["static", "rule", "sac", "worse rule", "tie of rule", "nothing", "missing"],
            "success_rate": [1.00, 0.98, 0.90, 0.95, 0.98, 0.0, math.nan],
            "mean_requested_reliability": [1.00, 0.06, 0.13, 0.06, 0.06, 0.0, math.nan],
        }
    )
    got = pareto_front(frame["success_rate"], frame["mean_requested_reliability"])
    # static: most success; rule and its tie: equal, neither dominates the other; sac is
    # dominated by rule (more success, less network); "nothing" uses no network at all.
    assert got.tolist() == [True, True, False, False, True, True, False]
    assert got.tolist() == _dominated_brute_force(
        frame["success_rate"].tolist(), frame["mean_requested_reliability"].tolist()
    )


def test_pareto_front_agrees_with_brute_force_on_random_points() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 15))
        s = rng.integers(0, 5, n) / 4.0  # coarse grids: many ties
        r = rng.integers(0, 5, n) / 4.0
        s[rng.random(n) < 0.1] = np.nan
        assert pareto_front(s, r).tolist() == _dominated_brute_force(s.tolist(), r.tolist())


def test_best_row_prefers_least_network_above_the_bar_else_most_success() -> None:
    summary = pd.DataFrame(
        {
            "plant": ["a", "a", "a", "a", "b", "b"],
            "row": ["static", "rule", "sac", "skipped", "static", "rule"],
            "status": ["ok", "ok", "ok", "missing checkpoint: x", "ok", "ok"],
            "success_rate": [1.0, 0.98, 0.99, math.nan, 0.90, 0.95],
            "mean_requested_reliability": [1.0, 0.06, 0.13, math.nan, 1.0, 0.1],
        }
    )
    assert best_row(summary, "a") == "rule"
    assert best_row(summary, "a", min_success=0.99) == "sac"
    assert best_row(summary, "b") == "rule"  # nobody reaches 98 %: the most successful
    assert best_row(summary, "c") is None


# -- config ------------------------------------------------------------------------------------
def test_pipelines_have_their_default_plants() -> None:
    assert [p.label for p in TableConfig().table_plants()] == ["0.2 m/s"]
    assert [p.label for p in TableConfig(pipeline="model-based").table_plants()] == ["realistic"]
    plants = TableConfig(pipeline="all").table_plants()
    assert [p.scenario for p in plants] == ["realistic", "constant-0.2", "constant-0.6", "variable"]
    assert [p.options for p in plants] == [  # the scenarios' own options, not a copy of them
        SCENARIOS[p.scenario].options for p in plants
    ]
    picked = TableConfig(pipeline="all", plants=("variable", "0.2")).table_plants()
    assert picked == (PLANT_PRESETS["variable"], PLANT_PRESETS["0.2"])
    with pytest.raises(ValueError, match=r"plants\[0\] must be one of 0.2, 0.6, variable"):
        TableConfig(plants=("0.4",))
    with pytest.raises(ValueError, match="plant labels must be unique"):
        TableConfig(plants=("0.2", TablePlant("0.2 m/s", options={"belt_speed_mps": 0.3})))


def test_all_pipeline_covers_the_grid() -> None:
    rows = TableConfig(pipeline="all").table_rows()
    pairs = {(r.controller.kind, r.estimator.kind, r.qos.kind) for r in rows}
    for stack in (("sac", "mlp"), ("mpc", "predictor")):
        for qos in ("static", "rule", "learned"):
            assert (*stack, qos) in pairs
    assert ("sac", "predictor", "static") in pairs and ("mpc", "mlp", "static") in pairs
    assert ("sac", "none", "learned") in pairs  # the paper's "no estimator, dynamic QoS"
    learned = {r.name: r.qos.checkpoint for r in rows if r.qos.kind == "learned"}
    assert learned["SAC + MLP, hybrid SAC QoS"] == "checkpoints/stage_d/qos"
    assert learned["SAC + MLP, model-free SAC QoS"] == "checkpoints/stage_d_model_free/qos"
    assert learned["MPC + predictor, SAC QoS"] == "checkpoints/stage_c_mpc"
    assert {stack_of(r) for r in rows} == {"model-free", "hybrid", "model-based", "mixed"}


# -- training cost -----------------------------------------------------------------------------
def _meta(folder: Path, meta: dict, *files: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "training.json").write_text(json.dumps(meta))
    for name in files:
        (folder / name).write_bytes(b"")


def test_training_cost_follows_the_lineage_and_counts_each_run_once(tmp_path: Path) -> None:
    a, b, c, d = (tmp_path / s for s in ("stage_a", "stage_b", "stage_c", "stage_d"))
    sac = {"kind": "sac", "checkpoint": str(a / "model.zip")}
    _meta(
        a, {"env_steps": 20, "wall_time_s": 1.0, "demonstrations": {"demo_steps": 10}}, "model.zip"
    )
    _meta(b, {"env_steps": 300, "wall_time_s": 2.0, "config": {"controller": sac}}, "mlp.pt")
    mlp_b = {"kind": "mlp", "checkpoint": str(b / "mlp.pt")}
    _meta(
        c,
        {"env_steps": 4000, "wall_time_s": 4.0, "config": {"controller": sac, "estimator": mlp_b}},
    )
    _meta(
        d,
        {
            "env_steps": 99999,  # estimator + qos: never counted as a whole
            "wall_time_s": 999.0,
            "estimator": {"env_steps": 50000, "wall_time_s": 8.0},
            "config": {"controller": sac, "estimator": mlp_b, "qos_policy": str(c)},
        },
        "mlp.pt",
    )
    mlp_d = {"kind": "mlp", "checkpoint": str(d / "mlp.pt")}
    _meta(
        d / "qos",
        {
            "env_steps": 600000,
            "wall_time_s": 16.0,
            "config": {"controller": sac, "estimator": mlp_d, "warm_start": str(c)},
        },
    )
    codesign = TableRow(
        "co-design",
        ComponentSpec(**sac),
        ComponentSpec(**mlp_d),
        ComponentSpec("learned", str(d / "qos")),
    )
    cost = training_cost(codesign)
    assert cost.env_steps == 30 + 300 + 4000 + 50000 + 600000
    assert cost.wall_time_s == pytest.approx(1 + 2 + 4 + 8 + 16)
    assert len(cost.sources) == 5 and cost.unknown == ()
    (d / "mlp.pt").unlink()  # a checkpoint without its file: counted as unknown, not guessed
    partial = training_cost(codesign)
    assert partial.unknown == (str(d / "mlp.pt"),)
    assert partial.env_steps == 30 + 4000 + 600000 + 300  # qos/, its warm start, A; B via C
    model_based = TableRow(
        "mpc", ComponentSpec("mpc"), ComponentSpec("predictor"), ComponentSpec("rule")
    )
    assert training_cost(model_based).env_steps == 0
    mixed = TableRow(
        "mpc + mlp", ComponentSpec("mpc"), ComponentSpec(**mlp_b), ComponentSpec("static")
    )
    assert training_cost(mixed).env_steps == 330  # the MLP was fitted on SAC's episodes


# -- a tiny run --------------------------------------------------------------------------------
def test_table_rows_by_plants_missing_checkpoint_and_figures(
    runner: CliRunner, tmp_path: Path
) -> None:
    missing = tmp_path / "no_such_qos"
    config = tmp_path / "table.toml"
    config.write_text(TOY_TABLE.format(missing=missing))
    out = tmp_path / "results"
    result = runner.invoke(app, ["table", "-c", str(config), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    assert "warning: row 'scripted, SAC QoS' skipped: missing checkpoint" in result.stderr
    shown = json.loads(result.stdout)
    assert [(r["plant"], r["row"]) for r in shown] == [
        (p, r)
        for p in ("toy slow", "toy fast")
        for r in ("scripted, static QoS", "scripted, 30% QoS", "scripted, SAC QoS")
    ]
    table = pd.read_parquet(out / "tab_p.parquet")
    for column in (
        "success_rate",
        "success_ci_low",
        "success_ci_high",
        "mean_requested_reliability",
        "delivered_fraction",
        "train_env_steps",
        "train_wall_time_s",
        "cpu_ms_per_step",
        *CPU_COLUMNS,
        "status",
        "pareto",
        "plant",
    ):
        assert column in table.columns, column
    ok = table[table["status"] == "ok"]
    assert len(ok) == 4 and (ok["trials"] == 2).all()
    assert ok["mean_requested_reliability"].tolist() == pytest.approx([1.0, 0.3, 1.0, 0.3])
    assert (ok["train_env_steps"] == 0).all()  # scripted pick, static QoS: nothing learned
    assert (ok["cpu_ms_per_step"] > 0).all()
    assert ok["cpu_ms_per_step"].to_numpy() == pytest.approx(ok[list(CPU_COLUMNS)].sum(axis=1))
    skipped = table[table["status"] != "ok"]
    assert len(skipped) == 2
    assert skipped["status"].str.startswith(f"missing checkpoint: {missing}").all()
    assert skipped["success_rate"].isna().all() and not skipped["pareto"].any()
    for _, part in table.groupby("plant"):
        assert part["pareto"].tolist() == _dominated_brute_force(
            part["success_rate"].tolist(), part["mean_requested_reliability"].tolist()
        )
    episodes = pd.read_parquet(out / "tab_p_episodes.parquet")
    assert len(episodes) == 8 and set(episodes["plant"]) == {"toy slow", "toy fast"}
    assert (out / "fig_pareto.png").stat().st_size > 5000
    assert "| toy fast | scripted, SAC QoS | missing checkpoint" in (out / "tab_p.md").read_text()
    if ok[ok["plant"] == "toy slow"]["success_rate"].max() > 0:
        assert (out / "fig_lat.png").is_file()
        assert json.loads((out / "fig_lat.json").read_text())["extra"]["plant"] == "toy slow"

    # --on-missing error: nothing runs, the message names the checkpoint
    strict = runner.invoke(
        app, ["table", "-c", str(config), "--out", str(tmp_path / "x"), "--on-missing", "error"]
    )
    assert strict.exit_code == 2
    assert "missing checkpoints" in strict.stderr and str(missing) in strict.stderr
    assert not (tmp_path / "x").exists()


def test_one_pool_for_all_rows_and_plants(monkeypatch: pytest.MonkeyPatch) -> None:
    import codesign_mb.studies.table as table_module

    calls: list[int] = []
    real = table_module.run_jobs

    def counting(jobs, **kwargs):
        calls.append(len(jobs))
        return real(jobs, **kwargs)

    monkeypatch.setattr(table_module, "run_jobs", counting)
    toy = ComponentSpec("toy_pick")
    rows = tuple(
        TableRow(
            f"q={q}",
            toy,
            ComponentSpec("none"),
            ComponentSpec("static", options={"reliability": q}),
        )
        for q in (1.0, 0.5)
    )
    plants = tuple(
        TablePlant(f"v={v}", "toy", {"horizon": 20, "belt_speed_mps": v}) for v in (0.1, 0.2)
    )
    summary, episodes = run_table(TableConfig(rows=rows, plants=plants, trials=1))
    assert calls == [4]  # one call (one pool) for the 2 rows x 2 plants
    assert len(summary) == 4 and len(episodes) == 4


def test_cli_plant_option_names_the_presets(runner: CliRunner) -> None:
    result = runner.invoke(app, ["table", "--plant", "0.2", "--plant", "0.4"])
    assert result.exit_code == 2
    assert "plants[1] must be one of 0.2, 0.6, variable" in result.stderr


def test_mpc_failures_are_summed_into_the_summary_and_its_markdown(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import codesign_mb.studies.table as table_module

    real = table_module.run_jobs

    def first_row_has_an_mpc(jobs, **kwargs):
        for j, episode in real(jobs, **kwargs):
            if j == 0:  # the MPC's per-episode solver metrics (MpcController.episode_metrics)
                episode = {
                    **episode,
                    "mpc_solves": 20.0,
                    "mpc_failures": float(episode["episode"] + 2),
                    "mpc_solve_ms_median": 1.0,
                    "mpc_solve_ms_p99": 2.0,
                    "mpc_solve_ms_max": 3.0,
                }
            yield j, episode

    monkeypatch.setattr(table_module, "run_jobs", first_row_has_an_mpc)
    toy, none = ComponentSpec("toy_pick"), ComponentSpec("none")
    rows = tuple(
        TableRow(name, toy, none, ComponentSpec("static", options={"reliability": q}))
        for name, q in (("with an MPC", 1.0), ("without", 0.5))
    )
    plants = (TablePlant("toy", "toy", {"horizon": 20}),)
    summary, _ = run_table(TableConfig(rows=rows, plants=plants, trials=3))
    assert summary["mpc_failures"].iloc[0] == 2 + 3 + 4  # episodes 0, 1, 2
    assert math.isnan(summary["mpc_failures"].iloc[1])
    header, _, with_mpc, without = markdown_table(summary).splitlines()
    column = header.split(" | ").index("MPC failures")
    assert with_mpc.split(" | ")[column] == "9"
    assert without.split(" | ")[column] == ""
    assert "MPC failures" not in markdown_table(summary.iloc[1:])  # no MPC, no column


def test_several_root_seeds_pool_the_episodes_of_each_seed() -> None:
    toy, none = ComponentSpec("toy_pick"), ComponentSpec("none")
    rows = (TableRow("q=0.3", toy, none, ComponentSpec("static", options={"reliability": 0.3})),)
    plants = (TablePlant("toy", "toy", {"horizon": 30, "belt_speed_mps": 0.3}),)
    pooled, episodes = run_table(TableConfig(rows=rows, plants=plants, trials=4, seeds=(0, 5)))
    alone = [run_table(TableConfig(rows=rows, plants=plants, trials=4, seed=s)) for s in (0, 5)]
    assert len(episodes) == 8 and sorted(set(episodes["root_seed"])) == [0, 5]
    for (summary, eps), seed in zip(alone, (0, 5), strict=True):  # the same episodes, per seed
        mine = episodes[episodes["root_seed"] == seed]
        assert sorted(mine["seed"]) == sorted(eps["seed"])
        assert mine["success"].sum() == eps["success"].sum() == summary["successes"].iloc[0]
    assert pooled["successes"].iloc[0] == sum(s["successes"].iloc[0] for s, _ in alone)
    rates = [100 * s["success_rate"].iloc[0] for s, _ in alone]
    assert pooled["success_by_seed"].iloc[0] == f"0: {rates[0]:.0f} %, 5: {rates[1]:.0f} %"
    with pytest.raises(ValueError, match="seeds must be distinct"):
        TableConfig(rows=rows, plants=plants, seeds=(1, 1))


def test_learned_realistic_config_compares_with_the_planner_row_as_the_table_runs_it() -> None:
    from codesign_mb.cli.common import load_config
    from codesign_mb.studies.table_rows import PLANNER_ROW, model_based_rows

    root = Path(__file__).resolve().parents[1]
    cfg = load_config(TableConfig, root / "configs" / "table_learned_realistic.toml", {})
    mine = next(r for r in cfg.table_rows() if r.name == PLANNER_ROW)
    theirs = next(r for r in model_based_rows() if r.name == PLANNER_ROW)
    for role in ("controller", "estimator"):
        assert getattr(mine, role) == getattr(theirs, role)
    assert mine.qos.kind == theirs.qos.kind
    assert {**theirs.qos.options, "lookahead": True} == {**mine.qos.options, "lookahead": True}
