"""``codesign paper``: the studies of README's results in one resumable run, and its manifest."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.cli.common import load_config
from codesign_mb.cli.paper import _STUDY_NAMES
from codesign_mb.core.results import ResultsDir
from codesign_mb.core.seeds import SEED_SETS
from codesign_mb.studies import paper
from codesign_mb.studies.demo import LqgDemoConfig, run_lqg_demo
from codesign_mb.studies.fig_wifi import CapacityConfig
from codesign_mb.studies.paper import MANIFEST, read_study, run_paper
from codesign_mb.studies.paper_studies import (
    FIG_WIFI_GRID,
    STUDIES,
    PaperConfig,
    study_command,
    study_settings,
)
from codesign_mb.studies.readme import BEGIN, END, read_block

ROOT = Path(__file__).resolve().parents[1]


def test_config_rejects_unknown_studies_and_seed_sets() -> None:
    with pytest.raises(ValueError, match="only must name studies among lqg"):
        PaperConfig(only=("table",))
    with pytest.raises(ValueError, match="seed set must be one of test, dev"):
        PaperConfig(seeds="train")
    with pytest.raises(ValueError, match="trials must be an integer >= 1"):
        PaperConfig(trials=0)
    assert PaperConfig(skip=("figures", "fig_wifi")).selected() == STUDIES[:-2]
    assert PaperConfig(only=("fig_cn", "lqg")).selected() == ("lqg", "fig_cn")
    assert ", ".join(STUDIES) == _STUDY_NAMES  # the CLI's help names them without importing


def test_every_study_runs_on_the_test_seeds_and_says_its_command() -> None:
    for name in STUDIES[:-1]:
        settings = study_settings(name, PaperConfig())
        assert settings["seed"] == SEED_SETS["test"] and settings["seeds"] == "test"
        assert study_command(name, settings).startswith("codesign ")
    for benchmark in ("table_realistic", "table_variable"):  # the benchmark's 200 per row
        assert study_settings(benchmark, PaperConfig(trials=7))["trials"] == 200
    dev = study_settings("table_paper", PaperConfig(seeds="dev", trials=7))
    assert dev["seed"] == SEED_SETS["dev"] and dev["trials"] == 7
    assert study_command("table_paper", dev) == (
        f"codesign table --scenario paper --pipeline all -n 7 --seed {SEED_SETS['dev']}"
    )


def test_fig_wifi_grid_is_configs_fig_wifi_toml() -> None:
    """The study runs what `codesign wifi capacity -c configs/fig_wifi.toml` runs."""
    settings = study_settings("fig_wifi", PaperConfig())
    from_file = load_config(CapacityConfig, ROOT / "configs" / "fig_wifi.toml")
    ours = CapacityConfig(**{**FIG_WIFI_GRID, "trials": settings["trials"], "seed": 0})
    assert from_file == ours
    assert study_command("fig_wifi", settings).startswith(
        "codesign wifi capacity -c configs/fig_wifi.toml --trials 20"
    )
    assert from_file.stack == "realistic" and from_file.stop_below == 0.5
    assert max(from_file.robots) == 48
    smoke = study_settings("fig_wifi", PaperConfig(smoke=True))
    assert study_command("fig_wifi", smoke) == (
        "codesign wifi capacity --stack realistic --robots 1,2 --channels paper "
        "--schedulers greedy --stop-below 0.5 --trials 1 --max-steps 40 --seed 0"
    )


def test_run_resumes_reruns_on_new_settings_and_records_the_manifest(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "paper"
    config = PaperConfig(only=("lqg",), smoke=True, workers=1)
    first = run_paper(config, out, command="codesign paper --only lqg --smoke")
    assert first.status == {"lqg": "ran"}
    # the stored table is the study's own function on the test seeds
    expected = run_lqg_demo(LqgDemoConfig(episodes=2, horizon=40, seed=SEED_SETS["test"]))
    stored = ResultsDir(out / "lqg").table("lqg")
    pd.testing.assert_frame_equal(stored, pd.DataFrame(expected["rows"]))
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest == first.manifest
    assert manifest["seeds"] == "test" and manifest["seed"] == SEED_SETS["test"]
    assert manifest["studies"]["lqg"]["status"] == "ran"
    assert manifest["studies"]["lqg"]["command"] == (
        "codesign demo --scenario lqg -n 2 --horizon 40 --seed 0"
    )
    assert manifest["studies"]["table_paper"] == {"status": "not selected"}
    assert manifest["studies_wall_time_s"] == manifest["studies"]["lqg"]["wall_time_s"] > 0
    assert set(manifest["provenance"]) >= {"commit", "versions", "checkpoints"}
    assert manifest["workers"] == 1 and PaperConfig().worker_count() == 2
    finished = read_study(out / "lqg")["finished"]  # type: ignore[index]

    lines: list[str] = []
    assert run_paper(config, out, log=lines.append).status == {"lqg": "reused"}
    assert read_study(out / "lqg")["finished"] == finished  # type: ignore[index]
    assert lines[0].startswith("lqg: complete, reused") and "commit" not in lines[0]
    with monkeypatch.context() as patch:  # the code moved on: reused, and said so
        patch.setattr(paper, "provenance", lambda *a: {"commit": "0" * 40})
        run_paper(config, out, log=lines.append)
    assert f"made at commit {manifest['provenance']['commit']}, now {'0' * 40}" in lines[-1]
    dev = PaperConfig(only=("lqg",), smoke=True, workers=1, seeds="dev")
    assert run_paper(dev, out).status == {"lqg": "ran"}  # new settings: rerun
    assert ResultsDir(out / "lqg").config("lqg")["seed"] == SEED_SETS["dev"]
    forced = run_paper(PaperConfig(only=("lqg",), smoke=True, seeds="dev", force=True), out)
    assert forced.status == {"lqg": "ran"}
    # a study not selected keeps its complete folder and shows in the manifest as kept
    kept = run_paper(PaperConfig(only=("figures",), workers=1), out)
    assert kept.manifest["studies"]["lqg"]["status"] == "kept"
    assert (out / "figures" / "lqg" / "report.md").is_file()
    assert not list(out.glob(".*.partial")) and not list(out.glob(".*.old"))


def test_an_interrupted_study_leaves_the_previous_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "paper"
    run_paper(PaperConfig(only=("lqg",), smoke=True, workers=1), out)
    before = read_study(out / "lqg")

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr("codesign_mb.studies.paper._run_lqg", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_paper(PaperConfig(only=("lqg",), smoke=True, seeds="dev", workers=1), out)
    assert read_study(out / "lqg") == before  # still complete, with the old settings
    assert ResultsDir(out / "lqg").config("lqg")["seed"] == SEED_SETS["test"]


def test_cli_smoke_runs_every_study_then_renders_readme(runner: CliRunner, tmp_path: Path) -> None:
    """`codesign paper --smoke`: every study on a few episodes (about 25 s on one core), the
    compact results, README's block; run again, every study is reused."""
    out, docs, readme = tmp_path / "paper", tmp_path / "docs", tmp_path / "README.md"
    readme.write_text(f"# x\n\nprose\n\n{BEGIN}\nold\n{END}\n\nmore prose\n")
    args = ["paper", "--smoke", "-o", str(out), "--readme", str(readme)]  # smoke: 1 worker
    args += ["--docs", str(docs)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / MANIFEST).read_text())
    assert {k: s["status"] for k, s in manifest["studies"].items()} == dict.fromkeys(STUDIES, "ran")
    assert all(f"{name}: " in result.stderr for name in STUDIES)
    assert manifest["workers"] == 1 and manifest["studies"]["fig_cn"]["cpu_time_s"] > 0
    for name in ("table_realistic", "table_variable", "table_paper"):
        summary = ResultsDir(out / name).table("tab_p")
        assert set(summary["kind"]) >= {"row", "blind", "oracle", "static", "random"}
        assert (out / "figures" / name / "report.md").is_file()
    assert sorted(p.stem for p in (docs / "results").iterdir()) == sorted([*STUDIES[:-1], "paper"])
    assert (docs / "figures" / "fig_wifi.png").stat().st_size > 5000
    text = readme.read_text()
    assert text.startswith("# x\n\nprose\n\n") and text.endswith(f"{END}\n\nmore prose\n")
    block = read_block(text)
    assert "`codesign demo --scenario lqg -n 2 --horizon 40 --seed 0`" in block
    for name in ("realistic", "variable"):
        assert (
            f"`codesign table --scenario {name} --pipeline model-based -n 1 --seed 0 "
            "--bound 'MPC + belt IMM, QoS planner (co-design)'`"
        ) in block
        assert "*clairvoyant schedule of: MPC + belt IMM, QoS planner (co-design)*" in block
    assert "![fig_pareto_paper](docs/figures/fig_pareto_paper.png)" in block
    check = runner.invoke(app, ["readme", "--readme", str(readme), "--docs", str(docs), "--check"])
    assert check.exit_code == 0, check.output
    again = runner.invoke(app, [*args, "--json"])
    assert again.exit_code == 0, again.output
    statuses = {k: v["status"] for k, v in json.loads(again.stdout)["studies"].items()}
    assert statuses == dict.fromkeys(STUDIES, "reused")
