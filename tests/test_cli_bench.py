"""``codesign bench``: lazy registry, readable errors for parts not written yet."""

from __future__ import annotations

import json
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.cli import bench as bench_cli


def fake_bench(*, repeats: int, seed: int) -> dict[str, Any]:
    return {"solve_s_median": 0.001 * repeats, "seed_seen": seed}


@pytest.fixture
def app(monkeypatch: pytest.MonkeyPatch) -> typer.Typer:
    monkeypatch.setattr(
        bench_cli,
        "BENCHMARKS",
        {
            "fake": f"{__name__}:fake_bench",
            "later": "codesign_mb.not_written_yet.bench:bench_later",
        },
    )
    app = typer.Typer(pretty_exceptions_enable=False)
    bench_cli.register(app)

    @app.callback()
    def _root() -> None:
        pass

    return app


def test_bench_runs_registered_function(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "fake", "-n", "3", "--seed", "5", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["benchmark"] == "fake" and data["repeats"] == 3 and data["seed_seen"] == 5
    assert data["solve_s_median"] == pytest.approx(0.003) and data["wall_s"] >= 0


def test_missing_part_is_a_readable_error(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "later"])
    assert result.exit_code == 2
    assert result.stderr == (
        "error: benchmark 'later' is not available: module 'codesign_mb.not_written_yet.bench' "
        "does not exist yet\n"
    )
    result = CliRunner().invoke(app, ["bench", "nope"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: unknown benchmark 'nope'")


def test_bench_all_skips_missing(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "all", "--json", "-n", "1"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert [d["benchmark"] for d in data] == ["fake", "later"]
    assert "skipped" in data[1]


def test_bench_config_file(app: typer.Typer, tmp_path: Any) -> None:
    cfg = tmp_path / "b.toml"
    cfg.write_text("[bench]\nrepeats = 4\n")
    result = CliRunner().invoke(app, ["bench", "fake", "-c", str(cfg), "--json"])
    assert json.loads(result.stdout)["repeats"] == 4
    cfg.write_text("[bench]\nrepeat = 4\n")
    result = CliRunner().invoke(app, ["bench", "fake", "-c", str(cfg)])
    assert result.exit_code == 2 and result.stderr.startswith("error: unknown key 'repeat'")
    result = CliRunner().invoke(app, ["bench", "fake", "-n", "0"])
    assert result.stderr == "error: repeats must be >= 1, got 0\n"


def test_registry_points_at_the_agreed_functions() -> None:
    assert bench_cli.BENCHMARKS == {
        "env": "codesign_mb.bench.env:bench_env",
        "mpc": "codesign_mb.bench.mpc:bench_mpc",
        "allocators": "codesign_mb.bench.allocators:bench_allocators",
    }
