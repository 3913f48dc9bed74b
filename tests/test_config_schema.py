"""The config dataclass is the schema: types from its annotations, ranges and caps from its
``__post_init__``, checked by ``from_mapping`` with one line naming the field and the value."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import pytest

from codesign_mb.core.config import (
    Cap,
    ConfigError,
    FloatOrInf,
    check_range,
    from_mapping,
    load_config_file,
    to_mapping,
)
from codesign_mb.core.registry import ComponentSpec, factory


@dataclass(frozen=True)
class Link:
    reliability: float = 1.0
    latency_steps: int = 0

    def __post_init__(self) -> None:
        check_range("reliability", self.reliability, ge=0.0, le=1.0)


@dataclass(frozen=True)
class Run:
    trials: int = 10
    speeds: tuple[float, ...] = (0.2,)
    corner: tuple[float, float] = (0.0, 0.0)
    name: str = "run"
    verbose: bool = False
    workers: int | None = None
    fading_db: FloatOrInf = 6.0
    link: Link = field(default_factory=Link)
    options: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_range("trials", self.trials, ge=1, cap=Cap(1000, "trials of a test run"))
        if self.name == "boom":
            raise TypeError("a TypeError of the schema's own checks")


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"trials": "3"}, "trials must be an integer, got '3'"),
        ({"trials": 2.5}, "trials must be an integer, got 2.5"),
        ({"trials": True}, "trials must be an integer, got True"),
        ({"trials": math.nan}, "trials must be an integer, got nan"),
        ({"trials": 1e30}, "trials must be an integer below 2**63, got 1e+30"),
        ({"trials": 5000}, "trials must be <= 1000 (the cap on trials of a test run), got 5000"),
        ({"trials": 0}, "trials must be >= 1, got 0"),
        ({"speeds": [0.2, math.inf]}, "speeds[1] must be a finite number, got inf"),
        ({"speeds": "0.2"}, "speeds must be a list, got '0.2'"),
        ({"corner": [1.0]}, "corner must hold 2 values, got [1.0]"),
        ({"name": 3}, "name must be a string, got 3"),
        ({"verbose": 1}, "verbose must be true or false, got 1"),
        ({"workers": "two"}, "workers must be an integer, got 'two'"),
        ({"fading_db": math.nan}, "fading_db must be a finite number, got nan"),
        ({"link": 3}, "link must be a table, got 3"),
        ({"link": {"reliability": 1.5}}, "link.reliability must be <= 1.0, got 1.5"),
        ({"link": {"reliabilty": 0.5}}, "unknown key 'reliabilty' in link"),
        ({"options": {"a": "x"}}, "options.a must be an integer, got 'x'"),
        ({"name": "boom"}, "a TypeError of the schema's own checks"),
        ({"trails": 3}, "unknown key 'trails'; expected one of corner, fading_db, link"),
    ],
)
def test_schema_rejects_with_one_line_naming_field_and_value(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as raised:
        from_mapping(Run, data)
    assert str(raised.value).startswith(message)
    assert isinstance(raised.value, ValueError)  # a user error: exit code 2 at the CLI


def test_schema_normalises_what_it_accepts() -> None:
    run = from_mapping(
        Run,
        {"trials": 1e2, "speeds": [1, 0.5], "fading_db": math.inf, "link": {"reliability": 1}},
    )
    assert run.trials == 100 and isinstance(run.trials, int)
    assert run.speeds == (1.0, 0.5) and all(isinstance(v, float) for v in run.speeds)
    assert run.fading_db == math.inf and run.link == Link(1.0, 0)
    assert from_mapping(Run, {"workers": None}).workers is None


def _cli_configs() -> list[type]:
    from codesign_mb.bench.suite import BenchConfig
    from codesign_mb.evaluation.evaluate import EvaluateConfig
    from codesign_mb.stages.stage_a import StageAConfig
    from codesign_mb.stages.stage_b import StageBConfig
    from codesign_mb.stages.stage_c import StageCConfig
    from codesign_mb.stages.stage_d import StageDConfig
    from codesign_mb.studies.demo import LqgDemoConfig, RobotDemoConfig
    from codesign_mb.studies.fig_cn import FigCnConfig
    from codesign_mb.studies.fig_wifi import CapacityConfig
    from codesign_mb.studies.paper_studies import PaperConfig
    from codesign_mb.studies.render import RenderConfig
    from codesign_mb.studies.report_sections import ReportConfig
    from codesign_mb.studies.sweep import SweepConfig
    from codesign_mb.studies.table import TableConfig
    from codesign_mb.wifi.config import WifiConfig

    return [
        BenchConfig,
        EvaluateConfig,
        StageAConfig,
        StageBConfig,
        StageCConfig,
        StageDConfig,
        LqgDemoConfig,
        RobotDemoConfig,
        FigCnConfig,
        CapacityConfig,
        PaperConfig,
        RenderConfig,
        ReportConfig,
        SweepConfig,
        TableConfig,
        WifiConfig,
    ]


@pytest.mark.parametrize("cls", _cli_configs(), ids=lambda c: c.__name__)
def test_every_config_accepts_its_own_defaults(cls: type) -> None:
    """The typed schema and the defaults agree: a config written out reads back equal."""
    config = cls()
    assert from_mapping(cls, to_mapping(config)) == config
    assert dataclasses.is_dataclass(config)


def test_check_range_on_lists_and_caps() -> None:
    check_range("robots", (1, 2, 256), ge=1, cap=Cap(256, "robots"))
    with pytest.raises(ConfigError, match=r"robots must be <= 256 \(the cap on robots\), got 300"):
        check_range("robots", [1, 300], cap=Cap(256, "robots"))
    with pytest.raises(ConfigError, match="x must be > 0, got 0"):
        check_range("x", 0, gt=0)
    check_range("optional", None, ge=1)


@pytest.mark.parametrize(
    ("suffix", "text", "message"),
    [
        (".yaml", "a: [1, 2\n", r"is not valid YAML: .* \(at line 2, column 1\)"),
        (".yaml", "a: 1\n  b: 2\n", r"is not valid YAML: .*line 2"),
        (".toml", "a = 1\nb = = 2\n", r"is not valid TOML: .*line 2"),
        (".toml", "a = [1,\n", r"is not valid TOML: .*\(at the end, line 2\)"),
        (".yaml", "- 1\n- 2\n", "must hold a mapping at the top level"),
    ],
)
def test_a_syntax_error_names_the_file_and_line(
    tmp_path, suffix: str, text: str, message: str
) -> None:
    path = tmp_path / f"c{suffix}"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as raised:
        load_config_file(path)
    assert str(path) in str(raised.value)


def test_component_options_are_checked_against_the_factory_signature() -> None:
    factory("qos", ComponentSpec("static", options={"reliability": 0.5, "latency_steps": 2}))
    with pytest.raises(ConfigError, match="unknown option 'q' of qos kind 'static'"):
        factory("qos", ComponentSpec("static", options={"q": 0.5}))
    with pytest.raises(ConfigError, match=r"options\.reliability of qos kind .static. must be"):
        factory("qos", ComponentSpec("static", options={"reliability": "high"}))
    # A classmethod forwarding **overrides: its class's constructor is the schema.
    with pytest.raises(ConfigError, match="unknown option 'acel_std' of estimator kind"):
        factory("estimator", ComponentSpec("predictor", options={"acel_std": 1.0}))
    factory("estimator", ComponentSpec("predictor", options={"accel_std": 1.0}))
