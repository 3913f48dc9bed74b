"""The shared CLI helpers: readable one-line errors (exit 2), strict config files, output."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import typer
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from codesign_mb.cli.common import (
    ConfigOption,
    JsonOption,
    SeedOption,
    cli_errors,
    comma_list,
    emit,
    explicit,
    load_config,
    track,
)
from codesign_mb.network import QosRequest


@dataclass(frozen=True)
class LinkCfg:
    reliability: float = 1.0
    latency_steps: int = 0

    def __post_init__(self) -> None:
        QosRequest(self.reliability, self.latency_steps)


@dataclass(frozen=True)
class DemoCfg:
    steps: int = 10
    link: LinkCfg = field(default_factory=LinkCfg)
    speeds: tuple[float, ...] = (0.2,)

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")


def _app() -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False)

    @app.command()
    @cli_errors
    def demo(
        config: ConfigOption = None,
        seed: SeedOption = 0,
        as_json: JsonOption = False,
        reliability: float | None = typer.Option(None, help="q in [0, 1]."),
        steps: int | None = typer.Option(None, help="Steps."),
    ) -> None:
        cfg = load_config(DemoCfg, config, {"link.reliability": reliability, "steps": steps})
        rows = [{"k": k, "seed": seed} for k in track(range(cfg.steps), description="demo")]
        emit({"steps": cfg.steps, "link": cfg.link, "rows": len(rows)}, as_json=as_json)

    @app.command()
    @cli_errors
    def defaults(
        ctx: typer.Context,
        config: ConfigOption = None,
        steps: int = typer.Option(DemoCfg.steps, help="Steps."),
        reliability: float = typer.Option(1.0, help="q in [0, 1]."),
    ) -> None:
        given = explicit(
            ctx,
            {"steps": steps, "reliability": reliability},
            rename={"reliability": "link.reliability"},
        )
        cfg = load_config(DemoCfg, config, given)
        emit({"steps": cfg.steps, "q": cfg.link.reliability}, as_json=True)

    @app.command()
    @cli_errors
    def crash() -> None:
        raise RuntimeError("a bug")

    @app.command()
    @cli_errors
    def typo() -> None:
        len(3)  # type: ignore[arg-type]

    return app


runner = CliRunner()


def test_validation_error_is_one_line_exit_2() -> None:
    result = runner.invoke(_app(), ["demo", "--reliability", "1.5"])
    assert result.exit_code == 2
    assert result.stderr == "error: link.reliability must be in [0, 1], got 1.5\n"
    assert result.stdout == ""
    assert "Traceback" not in result.output


def test_unknown_config_key_rejected(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("steps = 3\nstesp = 4\n")
    result = runner.invoke(_app(), ["demo", "--config", str(cfg)])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: unknown key 'stesp'")
    assert result.stderr.count("\n") == 1
    # Nested tables are strict too (YAML here).
    cfg = tmp_path / "c.yaml"
    cfg.write_text("link:\n  reliabilty: 0.5\n")
    with pytest.raises(ValueError, match="unknown key 'reliabilty'"):
        load_config(DemoCfg, cfg, {})


def test_missing_config_file_is_readable(tmp_path: Path) -> None:
    result = runner.invoke(_app(), ["demo", "--config", str(tmp_path / "nope.toml")])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: config file")
    assert "does not exist" in result.stderr


def test_config_file_then_cli_overrides(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("steps = 3\nspeeds = [0.2, 0.6]\n[link]\nreliability = 0.5\nlatency_steps = 2\n")
    loaded = load_config(DemoCfg, cfg, {"steps": None, "link.reliability": 0.9})
    assert loaded == DemoCfg(steps=3, link=LinkCfg(0.9, 2), speeds=(0.2, 0.6))
    result = runner.invoke(_app(), ["demo", "-c", str(cfg), "--steps", "4", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data == {"steps": 4, "link": {"reliability": 0.5, "latency_steps": 2}, "rows": 4}


def test_defaults_do_not_override_the_config_file(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("steps: 7\nlink:\n  reliability: 0.5\n")
    result = runner.invoke(_app(), ["defaults", "-c", str(cfg)])
    assert json.loads(result.stdout) == {"steps": 7, "q": 0.5}
    result = runner.invoke(_app(), ["defaults", "-c", str(cfg), "--steps", "10"])
    assert json.loads(result.stdout) == {"steps": 10, "q": 0.5}
    result = runner.invoke(_app(), ["defaults", "--reliability", "0.25"])
    assert json.loads(result.stdout) == {"steps": 10, "q": 0.25}
    assert explicit(None, {"a": 1, "b": None}) == {"a": 1}


def test_config_section(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[demo]\nsteps = 2\n[other]\nwhatever = 1\n")
    assert load_config(DemoCfg, cfg, {}, section="demo").steps == 2
    cfg.write_text("stesp = 3\n[demo]\nsteps = 2\n")
    with pytest.raises(ValueError, match="key 'stesp' outside any table"):
        load_config(DemoCfg, cfg, {}, section="demo")
    cfg.write_text("steps = 3\n")  # no [demo] table: the top level is the config
    assert load_config(DemoCfg, cfg, {}, section="demo").steps == 3


def test_bugs_are_one_line_with_a_pointer_to_debug(monkeypatch: pytest.MonkeyPatch) -> None:
    result = runner.invoke(_app(), ["crash"])
    assert result.exit_code == 1
    assert result.stderr.startswith("error: unexpected RuntimeError: ")
    assert "--debug" in result.stderr and result.stderr.count("\n") == 1
    monkeypatch.setenv("CODESIGN_DEBUG", "1")  # what `codesign --debug` sets
    result = runner.invoke(_app(), ["crash"])
    assert result.exit_code == 1 and isinstance(result.exception, RuntimeError)


def test_type_errors_are_bugs_not_user_errors() -> None:
    result = runner.invoke(_app(), ["typo"])
    assert result.exit_code == 1
    assert result.stderr.startswith("error: unexpected TypeError: ")


def test_cli_errors_keeps_signature_for_help() -> None:
    result = runner.invoke(_app(), ["demo", "--help"])
    assert result.exit_code == 0
    for option in ("--config", "--seed", "--json", "--reliability"):
        assert option in result.stdout


def test_emit_table_and_json(capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    emit([{"a": np.float64(1.5), "b": "x"}, {"a": float("nan"), "c": 2}], as_json=True)
    assert json.loads(capsys.readouterr().out) == [{"a": 1.5, "b": "x"}, {"a": None, "c": 2}]
    emit({"a": {"b": 1}}, as_json=False, title="t")
    out = capsys.readouterr().out
    assert "a.b" in out and "1" in out


def test_track_is_plain_iteration_without_tty() -> None:
    assert list(track(iter([1, 2, 3]), total=3, description="x")) == [1, 2, 3]
    assert list(track(range(2), disable=True)) == [0, 1]


@given(st.lists(st.integers(-(10**6), 10**6), max_size=8), st.sampled_from([",", ", ", " ,"]))
def test_comma_list_reads_back_what_was_joined(values: list[int], sep: str) -> None:
    """Any integers joined by commas (with blanks around them) parse back to themselves."""
    assert comma_list(sep.join(map(str, values)), "seeds", item=int) == tuple(values)


def test_comma_list_names_the_option_and_its_form_on_a_bad_value() -> None:
    with pytest.raises(ValueError, match=r"seeds must look like 0,1,2, got '0,x'"):
        comma_list("0,x", "seeds", item=int, example="0,1,2")
    assert comma_list(" su , ofdma,", "ns3") == ("su", "ofdma")
