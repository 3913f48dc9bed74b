"""``codesign bench``: the suite by name, readable errors, ``all`` fails when one fails."""

from __future__ import annotations

import json
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.bench import suite
from codesign_mb.cli import bench as bench_cli


def fake_bench(*, repeats: int, seed: int) -> dict[str, Any]:
    return {"solve_s_median": 0.001 * repeats, "seed_seen": seed}


def broken_bench(*, repeats: int, seed: int) -> dict[str, Any]:
    raise RuntimeError("solver diverged")


@pytest.fixture
def app(monkeypatch: pytest.MonkeyPatch) -> typer.Typer:
    monkeypatch.setattr(
        suite,
        "BENCHMARKS",
        {"fake": f"{__name__}:fake_bench", "broken": f"{__name__}:broken_bench"},
    )
    app = typer.Typer(pretty_exceptions_enable=False)
    bench_cli.register(app)

    @app.callback()
    def _root() -> None:
        pass

    return app


def test_bench_runs_registered_function(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "fake", "--repeats", "3", "--seed", "5", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["benchmark"] == "fake" and data["repeats"] == 3 and data["seed_seen"] == 5
    assert data["solve_s_median"] == pytest.approx(0.003) and data["wall_s"] >= 0


def test_unknown_benchmark_is_a_readable_error(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "nope"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: unknown benchmark 'nope'")


def test_bench_all_fails_when_one_fails(app: typer.Typer) -> None:
    result = CliRunner().invoke(app, ["bench", "all", "--json", "--repeats", "1"])
    assert result.exit_code == 1, result.output
    data = json.loads(result.stdout)
    assert [d["benchmark"] for d in data] == ["fake", "broken"]
    assert data[0]["repeats"] == 1 and "error" not in data[0]
    assert data[1]["error"] == "RuntimeError: solver diverged"
    assert "1 benchmark(s) failed: broken: RuntimeError: solver diverged" in result.stderr


def test_bench_config_file(app: typer.Typer, tmp_path: Any) -> None:
    cfg = tmp_path / "b.toml"
    cfg.write_text("[bench]\nrepeats = 4\n")
    result = CliRunner().invoke(app, ["bench", "fake", "-c", str(cfg), "--json"])
    assert json.loads(result.stdout)["repeats"] == 4
    cfg.write_text("[bench]\nrepeat = 4\n")
    result = CliRunner().invoke(app, ["bench", "fake", "-c", str(cfg)])
    assert result.exit_code == 2 and result.stderr.startswith("error: unknown key 'repeat'")
    result = CliRunner().invoke(app, ["bench", "fake", "--repeats", "0"])
    assert result.stderr == "error: repeats must be >= 1, got 0\n"


def test_every_registered_benchmark_resolves() -> None:
    from codesign_mb.core.registry import resolve

    assert set(suite.BENCHMARKS) == {"env", "loop", "mpc", "allocators", "estimator", "offline-lp"}
    for target in suite.BENCHMARKS.values():
        assert callable(resolve(target))
