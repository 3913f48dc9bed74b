"""``codesign train`` and ``codesign table`` on the toy plant: files, defaults, resume, errors."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app

TOY_A = """
[a]
total_steps = 200
chunk_steps = 100
eval_episodes = 1
final_eval_episodes = 1
demo_episodes = 1
bc_epochs = 2
critic_warmup_steps = 20
curriculum = []

[a.estimator]
kind = "none"

[a.plant]
name = "toy"
options = { horizon = 40 }

[a.demo]
kind = "toy_pick"

[a.sac]
net_arch = [32, 32]
buffer_size = 5000
batch_size = 32
learning_starts = 50
"""

TOY_TABLE = """
[table]
trials = 3
timeline_row = "scripted, static QoS"

[table.plant]
name = "toy"
options = { horizon = 40 }

[[table.rows]]
name = "scripted, static QoS"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 1.0, latency_steps = 1 } }

[[table.rows]]
name = "scripted, 30% QoS"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 0.3, latency_steps = 1 } }
"""


def test_train_a_writes_checkpoint_then_resumes(runner: CliRunner, tmp_path: Path) -> None:
    config = tmp_path / "toy.toml"
    config.write_text(TOY_A)
    out, work = tmp_path / "out", tmp_path / "work"
    args = ["train", "a", "-c", str(config), "--out", str(out), "--work-dir", str(work)]
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["env_steps"] == 200
    meta = json.loads((out / "training.json").read_text())
    assert meta["command"].startswith("codesign ") or meta["command"]
    assert (out / "model.zip").is_file() and (out / "curve.json").is_file()
    # an "interrupted" run of 200 steps resumed to 300: the step count continues
    result = runner.invoke(app, [*args, "--resume", "--steps", "300", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["env_steps"] == 300
    curve = json.loads((out / "curve.json").read_text())
    assert [p["steps"] for p in curve] == [0, 100, 200, 300]


def test_train_writes_under_runs_by_default(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without --out, the checkpoint goes to the working directory's runs/, and nothing under
    the package's models/checkpoints/ changes (no file written, touched or added)."""
    from codesign_mb.core.registry import models_dir

    config = tmp_path / "toy.toml"
    config.write_text(TOY_A.replace("total_steps = 200", "total_steps = 100"))
    monkeypatch.chdir(tmp_path)
    shipped = models_dir() / "checkpoints"
    before = _snapshot(shipped)
    result = runner.invoke(app, ["train", "a", "-c", str(config), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["env_steps"] == 100
    out = tmp_path / "runs" / "checkpoints" / "stage_a"
    assert (out / "model.zip").is_file() and (out / "training.json").is_file()
    assert (tmp_path / "runs" / "train" / "stage_a" / "state.json").is_file()
    assert _snapshot(shipped) == before


def _snapshot(folder: Path) -> dict[str, tuple[int, bytes]]:
    """Every file under ``folder``: modification time (ns) and content."""
    return {
        str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_train_refuses_the_package_models_folder_without_overwrite(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """--out (or --work-dir) inside models/ needs --overwrite; checked before any training."""
    from codesign_mb.core import registry

    models = tmp_path / "package" / "models"  # stands in for the installed package's
    (models / "checkpoints" / "stage_a").mkdir(parents=True)
    monkeypatch.setattr(registry, "models_dir", lambda: models.resolve())
    monkeypatch.chdir(tmp_path)
    (tmp_path / "link").symlink_to(models / "checkpoints")
    config = tmp_path / "toy.toml"
    config.write_text(TOY_A)
    for extra in (
        ["--out", str(models / "checkpoints" / "stage_a")],
        ["--out", "link/stage_a"],  # the same folder through a symlink
        ["--out", "runs/a", "--work-dir", str(models / "work")],
    ):
        result = runner.invoke(app, ["train", "a", "-c", str(config), *extra])
        assert result.exit_code == 2, result.output
        [line] = result.stderr.splitlines()
        assert "inside the installed package's models folder" in line and "--overwrite" in line
    assert not any(models.rglob("*.json")) and not (tmp_path / "runs").exists()
    config.write_text(TOY_A.replace("total_steps = 200", "total_steps = 100"))
    out = models / "checkpoints" / "stage_a"
    result = runner.invoke(app, ["train", "a", "-c", str(config), "--out", str(out), "--overwrite"])
    assert result.exit_code == 0, result.output
    assert (out / "model.zip").is_file()


def test_train_rejects_bad_input(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(app, ["train", "x"])
    assert result.exit_code == 2
    assert "stage must be one of" in result.output
    result = runner.invoke(app, ["train", "b", "--steps", "3"])
    assert result.exit_code == 2
    assert "--steps does not apply" in result.output
    result = runner.invoke(app, ["train", "a", "--set", "total_step=3"])
    assert result.exit_code == 2
    assert "unknown key 'total_step'" in result.output
    result = runner.invoke(app, ["train", "a", "--set", "plant.name=mars"])
    assert result.exit_code == 2
    assert "plant.name must be one of" in result.output


def test_table_writes_tab_p_and_fig_lat(runner: CliRunner, tmp_path: Path) -> None:
    config = tmp_path / "table.toml"
    config.write_text(TOY_TABLE)
    out = tmp_path / "results"
    result = runner.invoke(app, ["table", "-c", str(config), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    assert [r["row"] for r in rows] == ["scripted, static QoS", "scripted, 30% QoS"]
    assert rows[0]["mean_requested_reliability"] == pytest.approx(1.0)
    assert rows[1]["mean_requested_reliability"] == pytest.approx(0.3)
    assert 0.0 <= rows[0]["success_ci_low"] <= rows[0]["success_rate"] <= 1.0
    table = pd.read_csv(out / "tab_p.csv")
    assert len(table) == 2
    assert (table["plant"] == "toy").all() and (table["status"] == "ok").all()  # [table.plant]
    episodes = pd.read_csv(out / "tab_p_episodes.csv")
    assert len(episodes) == 6
    assert (out / "fig_lat.png").stat().st_size > 1000
    timeline = pd.read_csv(out / "fig_lat.csv")
    assert timeline["success"].astype(bool).any()


def test_table_rejects_unknown_pipeline(runner: CliRunner) -> None:
    result = runner.invoke(app, ["table", "--pipeline", "nope"])
    assert result.exit_code == 2
    assert "pipeline must be one of" in result.output
