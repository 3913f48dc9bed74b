"""Property: no config file, instance file or command line ends in a traceback or a hang.

Hypothesis writes config files, TOML or YAML, for every command that takes ``-c``: the keys
of the command's config section with valid values (the defaults, tiny run sizes) or invalid
ones (NaN, infinity, huge, negative, the wrong type, empty lists, tables for numbers, unknown
keys, a broken syntax), and instance files for ``codesign solve`` (a recorded trace with one
entry broken, or any JSON). Every run must exit 0 with a JSON result, or exit 2 with one line
``error: ...`` that names the field (or the file and line of a syntax error); never exit 1
(a traceback behind ``--debug``), never run past its time cap (Hypothesis' deadline).

Hypothesis also writes command lines for every command (:data:`OPTION_COMMANDS`): one to
three of its options, each a value it takes or one it must refuse (NaN, infinity, negative,
huge, not a number, an unknown choice, a path that cannot be read or written). A run with an
invalid value must exit 2 with one line ``error: ...`` (accepting it is a failure); a valid
one exits 0 with its JSON result (or 2 with one line, e.g. a value valid alone but not with
another).

The default suite runs 13 x 40 config files, 100 instance files and 18 x 25 command lines
(1,070 cases, about 100 s on one core); ``-m slow`` runs 150 command lines a command more
(``test_options_many_cases``: 2,700).

Valid files run tiny settings (one episode of a few steps), so that the suite stays within a
few minutes; the commands whose every run is long (``train``, ``table``, ``paper``, ``tune``, and
``render``, which needs OpenGL) get files with at least one invalid entry, and must refuse
them before any work. ``derandomize=True``: the same examples on every machine.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import typing
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from codesign_mb.bench.suite import BenchConfig
from codesign_mb.cli import app
from codesign_mb.control.mpc_config import MpcConfig
from codesign_mb.core.config import to_mapping
from codesign_mb.evaluation.evaluate import EvaluateConfig
from codesign_mb.plants.conveyor_config import ConveyorConfig
from codesign_mb.stages.stage_a import StageAConfig
from codesign_mb.studies.demo import LqgDemoConfig, RobotDemoConfig
from codesign_mb.studies.fig_cn import FigCnConfig
from codesign_mb.studies.fig_wifi import CapacityConfig
from codesign_mb.studies.paper_studies import PaperConfig
from codesign_mb.studies.render import RenderConfig
from codesign_mb.studies.report_sections import ReportConfig
from codesign_mb.studies.sweep import SweepConfig
from codesign_mb.studies.table import TableConfig
from codesign_mb.studies.tune import TuneConfig

runner = CliRunner()

CASE_SECONDS = 60
"""The time cap of one run (Hypothesis' deadline): valid runs take seconds, errors much less."""

PROPERTY = settings(
    max_examples=40,
    deadline=timedelta(seconds=CASE_SECONDS),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

INVALID: list[Any] = [
    math.nan,
    math.inf,
    -math.inf,
    1e30,
    10**15,
    -1,
    -2.5,
    "",
    "x?",
    True,
    [],
    [math.nan],
    {"zz": 1},
    None,
]
"""Values every typed field refuses, or that break its range (TOML has no None: dropped)."""


@dataclasses.dataclass(frozen=True)
class Command:
    """How the property runs one command: its argv, config section and schema."""

    argv: Callable[[Path, Path], list[str]]
    section: str
    schema: type
    tiny: dict[str, Any]
    """Valid values of the fields that set a run's size (kept small: a run of seconds)."""
    nested: dict[str, type] = dataclasses.field(default_factory=dict)
    """Table fields whose keys are another config's (fuzzed with that config's fields)."""
    runs: bool = True
    """False: every valid run is long, so the property gives it invalid files only."""
    options: tuple[str, ...] = ()
    """Fields the command line sets (over the file): not fuzzed."""


def _out(tmp: Path) -> list[str]:
    return ["-o", str(tmp / "out"), "--json"]


def _tiny_results(folder: Path) -> Path:
    """A real results folder: a small Fig. 4 table, as ``codesign evaluate fig-cn`` writes it."""
    import pandas as pd

    from codesign_mb.core.results import write_results

    table = pd.DataFrame(
        {
            "estimator": ["predictor"] * 4 + ["none"] * 4,
            "belt_speed_mps": [0.2] * 8,
            "latency_steps": [0, 0, 1, 1] * 2,
            "success": [True, True, True, False, True, False, False, False],
        }
    )
    write_results(folder, table=table, config={"trials": 2}, name="fig_cn")
    return folder


COMMANDS: dict[str, Command] = {
    "evaluate": Command(
        lambda c, t: ["evaluate", "-c", str(c), *_out(t)],
        "evaluate",
        EvaluateConfig,
        {"trials": 1, "max_steps": 3, "workers": 1},
        {"env": ConveyorConfig, "mpc": MpcConfig},
    ),
    "fig-cn": Command(
        lambda c, t: ["evaluate", "fig-cn", "-c", str(c), *_out(t)],
        "fig_cn",
        FigCnConfig,
        {
            "trials": 1,
            "max_steps": 3,
            "workers": 1,
            "delays": [0],
            "belt_speeds_mps": [0.2],
            "reliabilities": [],
            "estimators": ["none"],
        },
        {"env": ConveyorConfig, "mpc": MpcConfig},
    ),
    "demo lqg": Command(
        lambda c, t: ["demo", "--scenario", "lqg", "-c", str(c), "--json"],
        "demo",
        LqgDemoConfig,
        {"episodes": 1, "horizon": 5, "reliabilities": [1.0, 0.5]},
    ),
    "demo robot": Command(
        lambda c, t: ["demo", "-c", str(c), "--json"],
        "robot_demo",
        RobotDemoConfig,
        {"episodes": 1, "reliabilities": [1.0], "estimators": ["none"], "workers": 1},
    ),
    "bench": Command(
        lambda c, t: ["bench", "env", "-c", str(c), "--json"],
        "bench",
        BenchConfig,
        {"repeats": 1},
    ),
    "sweep": Command(
        lambda c, t: ["sweep", "-c", str(c), "--backend", "serial", *_out(t)],
        "sweep",
        SweepConfig,
        {
            "scenario": "linear",
            "n_seeds": 1,
            "belt_speeds_mps": [0.2],
            "robot_counts": [1],
            "pipelines": [],
            "params": {"horizon_steps": 5},
        },
    ),
    "report": Command(
        lambda c, t: ["report", str(_tiny_results(t / "results")), "-c", str(c), *_out(t)],
        "report",
        ReportConfig,
        {"dpi": 30},
    ),
    "wifi capacity": Command(
        lambda c, t: ["wifi", "capacity", "-c", str(c), *_out(t)],
        "capacity",
        CapacityConfig,
        {
            "stack": "toy",
            "robots": [1],
            "robots_by_channel": {},
            "channels": ["paper"],
            "schedulers": ["greedy"],
            "trials": 1,
            "max_steps": 5,
            "workers": 1,
            "pipelines": {},
            "scenario": "",
        },
    ),
    "train": Command(
        lambda c, t: ["train", "a", "-c", str(c), "--out", str(t / "o"), "--work-dir", str(t)],
        "a",
        StageAConfig,
        {},
        runs=False,
    ),
    "table": Command(
        lambda c, t: ["table", "-c", str(c), *_out(t)], "table", TableConfig, {}, runs=False
    ),
    "paper": Command(
        lambda c, t: ["paper", "-c", str(c), *_out(t)], "paper", PaperConfig, {}, runs=False
    ),
    "tune": Command(
        lambda c, t: ["tune", "-c", str(c), *_out(t)], "tune", TuneConfig, {}, runs=False
    ),
    "render": Command(
        lambda c, t: ["render", "-c", str(c), "-o", str(t / "r.gif"), "--json"],
        "render",
        RenderConfig,
        {},
        runs=False,
        options=("out",),
    ),
}


def _plain(value: Any) -> Any:
    """A default as a config file holds it: dataclasses as tables, tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = to_mapping(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def _default(schema: type, name: str) -> Any:
    field = {f.name: f for f in dataclasses.fields(schema)}[name]
    if field.default is not dataclasses.MISSING:
        return _plain(field.default)
    return _plain(field.default_factory())  # type: ignore[misc]


@st.composite
def valid_value(draw: st.DrawFn, command: Command, schema: type, name: str) -> Any:
    """A value the schema accepts: a tiny size, the default, or a float near the default."""
    if schema is command.schema and name in command.tiny:
        return command.tiny[name]
    default = _default(schema, name)
    if isinstance(default, float) and not isinstance(default, bool) and math.isfinite(default):
        return draw(st.sampled_from([default, default * 0.5, default * 1.5]))
    return default


@st.composite
def config_table(draw: st.DrawFn, command: Command, schema: type, broken: bool) -> dict:
    """A table for ``schema``: some fields given; with ``broken``, at least one entry wrong
    (surely wrong, NaN or an unknown key, for a command that must not run)."""
    names = [f.name for f in dataclasses.fields(schema)]
    if schema is command.schema:
        names = [n for n in names if n not in command.options]
    table: dict[str, Any] = {}
    for name in names:
        if (schema is command.schema and name in command.tiny) or draw(st.booleans()):
            table[name] = draw(valid_value(command, schema, name))
    if not broken:
        return table
    hints = typing.get_type_hints(schema)
    typed = [n for n in names if hints.get(n) is not Any]
    how = draw(st.sampled_from(["value", "value", "nested", "unknown"]))
    if how == "nested" and schema is command.schema and command.nested:
        name = draw(st.sampled_from(sorted(command.nested)))
        table[name] = draw(config_table(command, command.nested[name], True))
    elif how == "unknown" or not typed:
        table[draw(st.sampled_from(["trails", "sed", "x_unknown"]))] = 1
    else:
        invalid = INVALID if command.runs else [math.nan]
        for name in draw(st.lists(st.sampled_from(typed), min_size=1, max_size=2, unique=True)):
            table[name] = draw(st.sampled_from(invalid))
    return table


def _toml(value: Any) -> str:
    """``value`` in TOML (inline tables and arrays; NaN and infinity as TOML spells them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else "inf" if value > 0 else "-inf"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value if v is not None) + "]"
    items = (f"{json.dumps(str(k))} = {_toml(v)}" for k, v in value.items() if v is not None)
    return "{" + ", ".join(items) + "}"


def write_config(path: Path, section: str, table: dict, *, under_section: bool) -> None:
    if path.suffix == ".toml":
        lines = [f"[{section}]"] if under_section else []
        lines += [f"{json.dumps(k)} = {_toml(v)}" for k, v in table.items() if v is not None]
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_text(yaml.safe_dump({section: table} if under_section else table))


@st.composite
def config_file(draw: st.DrawFn, command: Command) -> tuple[str, dict, str]:
    """``(suffix, table, how)``: how is valid, value (an entry broken) or syntax."""
    hows = ["valid", "value", "value", "syntax"] if command.runs else ["value", "value", "syntax"]
    how = draw(st.sampled_from(hows))
    table = draw(config_table(command, command.schema, how == "value"))
    return draw(st.sampled_from([".toml", ".yaml"])), table, how


def check_run(result: Any, *, must_fail: bool, names: list[str]) -> None:
    """Exit 0 with a JSON result, or exit 2 with one line naming one of ``names``."""
    assert "Traceback" not in result.output
    if result.exit_code == 0 and not must_fail:
        json.loads(result.stdout)
        return
    assert result.exit_code == 2, (result.exit_code, result.output[-2000:])
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-2000:]
    assert any(name in lines[0] for name in names), (names, lines[0])


def _keys(table: Any) -> list[str]:
    """Every key of a (nested) table: what an error about it names."""
    if not isinstance(table, dict):
        return []
    return [str(k) for k in table] + [k for v in table.values() for k in _keys(v)]


@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", COMMANDS)
@PROPERTY
@given(data=st.data())
def test_config_files_give_a_result_or_one_line(name: str, data: st.DataObject) -> None:
    command = COMMANDS[name]
    suffix, table, how = data.draw(config_file(command), label="config")
    under_section = data.draw(st.booleans(), label="under_section")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"config{suffix}"
        write_config(path, command.section, table, under_section=under_section)
        if how == "syntax":  # an unclosed list at the end: a parse error in any file
            with path.open("a") as fh:
                fh.write("broken = [1, 2\n" if suffix == ".toml" else "broken: [1, 2\n")
        result = runner.invoke(app, command.argv(path, Path(tmp)))
        names = [*_keys(table), command.section, str(path)]
        event(f"{how} file: exit code {result.exit_code}")
        must_fail = how == "syntax" or not command.runs  # a wrong value may be valid too
        check_run(result, must_fail=must_fail, names=names)
        if how == "syntax":
            assert str(path) in result.stderr and "line" in result.stderr


def _json_values() -> st.SearchStrategy[Any]:
    scalars = st.one_of(
        st.none(), st.booleans(), st.integers(-(10**20), 10**20), st.floats(), st.text(max_size=4)
    )
    return st.recursive(
        scalars,
        lambda inner: (
            st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
        ),
        max_leaves=8,
    )


@pytest.fixture(scope="module")
def recorded_trace(tmp_path_factory: pytest.TempPathFactory) -> dict:
    path = tmp_path_factory.mktemp("trace") / "trace.json"
    result = runner.invoke(app, ["wifi", "trace", str(path), "--robots", "2", "--steps", "2"])
    assert result.exit_code == 0, result.output
    return json.loads(path.read_text())


@st.composite
def instance(draw: st.DrawFn, trace: dict) -> Any:
    """A recorded trace with one entry broken (or none), or any JSON value."""
    kind = draw(st.sampled_from(["trace", "entry", "entry", "column", "key", "json"]))
    data = json.loads(json.dumps(trace))
    if kind == "json":
        return draw(_json_values())
    if kind == "entry":
        key = draw(st.sampled_from(sorted(data)))
        data[key] = draw(st.sampled_from(INVALID) | _json_values())
    elif kind == "column":
        column = draw(st.sampled_from(sorted(data["frames"])))
        value = draw(st.sampled_from([*INVALID, 0, 1, 2, 10**9]))
        data["frames"][column][draw(st.integers(0, len(data["frames"][column]) - 1))] = value
    elif kind == "key":
        key = draw(st.sampled_from(sorted(data)))
        if draw(st.booleans()):
            del data[key]
        else:
            data["x_" + key] = 1
    return data


@pytest.mark.timeout(600)
@settings(PROPERTY, max_examples=100)
@given(data=st.data())
def test_instance_files_give_a_result_or_one_line(
    recorded_trace: dict, data: st.DataObject
) -> None:
    case = data.draw(instance(recorded_trace), label="instance")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "instance.json"
        path.write_text(json.dumps(case))  # NaN and infinity as JSON's NaN, Infinity
        result = runner.invoke(app, ["solve", str(path), "--json"])
        check_run(result, must_fail=False, names=[str(path)])
        if result.exit_code == 0:
            assert json.loads(result.stdout)["optimum_frames"] >= 0


# -- command-line options ---------------------------------------------------------------------
HUGE = str(10**15)
"""Above every cap (steps, episodes, seeds, workers, ...)."""

NOT_INT = ["nan", "inf", "1.5", "x", ""]
NOT_FLOAT = ["nan", "inf", "-inf", "x", ""]
COUNT_BAD = ["0", "-1", HUGE, *NOT_INT]
"""Refused by every option counting something (>= 1)."""
SEED_BAD = ["-1", HUGE, *NOT_INT]
FRACTION_BAD = ["-0.1", "1.5", *NOT_FLOAT]
SPEED_BAD = ["-0.2", "1e9", *NOT_FLOAT]
OUT_DIR_BAD = ["/proc/codesign", "{file}", "{file}/sub"]
"""An output folder that cannot be made: under /proc, a file, a folder under a file."""


@dataclasses.dataclass(frozen=True)
class Opt:
    """One option of a command: values it takes and values it must refuse (exit 2)."""

    flag: str
    """``--name``, or a ``{placeholder}`` of the base argv (a positional argument)."""
    valid: tuple[str, ...]
    invalid: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class OptionCommand:
    """A command's base argv (a tiny valid run, or a long one) and its fuzzed options."""

    argv: tuple[str, ...]
    options: tuple[Opt, ...]
    runs: bool = True
    """False: a valid run is long, so every case has at least one invalid option."""
    json: bool = True
    """A valid run prints JSON (``--json``)."""


def opt(flag: str, valid: list[str], invalid: list[str]) -> Opt:
    return Opt(flag, tuple(valid), tuple(invalid))


_OUT = opt("-o", ["{tmp}/out2"], OUT_DIR_BAD)
_SEED = opt("--seed", ["0", "7"], SEED_BAD)

OPTION_COMMANDS: dict[str, OptionCommand] = {
    "demo lqg": OptionCommand(
        ("demo", "--scenario", "lqg", "-n", "1", "--horizon", "4", "-q", "1", "--json"),
        (
            opt("-q", ["0.5", "0"], FRACTION_BAD),
            opt("--latency", ["0", "2"], ["-1", "1001", *NOT_INT]),
            opt("-n", ["2"], COUNT_BAD),
            opt("--horizon", ["3", "6"], COUNT_BAD),
            opt("--plant", ["scalar", "double_integrator", "pendulum"], ["bogus", ""]),
            opt("-c", [], ["{tmp}/nope.toml", "{tmp}"]),
            _SEED,
        ),
    ),
    "demo robot": OptionCommand(
        ("demo", "--scenario", "robot", "-n", "1", "--json"),
        (
            opt("-q", ["1"], FRACTION_BAD),
            opt("--latency", ["0", "1"], ["-1", "1001", *NOT_INT]),
            opt("-n", ["1"], COUNT_BAD),
            opt("--horizon", [], ["5"]),
            opt("--plant", [], ["scalar"]),
            opt("--scenario", [], ["bogus", ""]),
            _SEED,
        ),
        runs=False,
    ),
    "bench": OptionCommand(
        ("bench", "env", "--repeats", "1", "--json"),
        (opt("--repeats", ["1"], COUNT_BAD), _SEED, opt("-c", [], ["{tmp}/nope.toml"])),
    ),
    "sweep": OptionCommand(
        (
            "sweep",
            "--backend",
            "serial",
            "--scenario",
            "linear",
            "-n",
            "1",
            "--robots",
            "1",
            "--belt-speed",
            "0.2",
            "--param",
            "horizon_steps=5",
            "-o",
            "{tmp}/out",
            "--json",
        ),
        (
            opt("-n", ["2"], COUNT_BAD),
            opt("--robots", ["2"], ["0", "-1", "257", *NOT_INT]),
            opt("--belt-speed", ["0.6", "0"], ["-0.2", *NOT_FLOAT]),
            opt("--pipeline", ["none", "predictor"], ["bogus", ""]),
            opt(
                "--param",
                ["reliability=0.5", "latency_steps=1"],
                ["x", "bogus=1", "horizon_steps=nan", "reliability=2", "horizon_steps=-3"],
            ),
            opt("--name", ["s2"], ["a/b", "", ".x"]),
            opt("--backend", ["serial"], ["bogus", ""]),
            opt("--workers", ["1"], ["0", "-1", "100000", *NOT_INT]),
            opt("--address", [], ["auto"]),
            opt("--scenario", ["linear"], ["bogus", ""]),
            _SEED,
            _OUT,
        ),
    ),
    "report": OptionCommand(
        ("report", "{results}", "-o", "{tmp}/out", "--json"),
        (
            opt("{results}", [], ["{tmp}/nope", "{file}", "{tmp}/empty"]),
            opt("--dpi", ["30", "40"], ["5", "19", "1201", *NOT_INT]),
            opt("--confidence", ["0.9", "0.5"], ["0", "1", "1.5", "-0.1", *NOT_FLOAT]),
            opt("--metric", ["success_rate"], [""]),
            opt("-o", ["{tmp}/out2"], ["{file}", "{file}/sub", "/proc/codesign"]),
            _SEED,
        ),
    ),
    "solve": OptionCommand(
        ("solve", "{trace}", "--json"),
        (
            opt("{trace}", [], ["{tmp}/nope.json", "{file}", "{tmp}"]),
            opt("--solver", ["auto", "highs", "clarabel"], ["bogus", ""]),
            opt("-j", ["1"], ["0", "-1", *NOT_INT]),
            opt("--backend", ["local"], ["bogus", ""]),
        ),
    ),
    "wifi phy-table": OptionCommand(
        ("wifi", "phy-table", "--json"),
        (
            opt("-b", ["20", "40", "80"], ["30", "0", "-1", "160", *NOT_INT]),
            opt("--gi", ["0.8", "1.6", "3.2"], ["0.5", "-1", *NOT_FLOAT]),
            opt("--ul-gi", ["1.6", "3.2"], ["0.8", *NOT_FLOAT]),
            opt("--streams", ["1", "2"], ["0", "3", *NOT_INT]),
        ),
    ),
    "wifi trace": OptionCommand(
        ("wifi", "trace", "{tmp}/t.json", "--robots", "2", "--steps", "2", "--json"),
        (
            opt("--robots", ["1", "3"], ["0", "-1", "257", *NOT_INT]),
            opt("--steps", ["1", "3"], COUNT_BAD),
            opt("-q", ["0.5", "1"], FRACTION_BAD),
            opt("--latency", ["1", "2"], ["-1", "1001", *NOT_INT]),
            opt("--channel", ["paper", "better"], ["bogus", ""]),
            _SEED,
        ),
    ),
    "wifi capacity": OptionCommand(
        (
            "wifi",
            "capacity",
            "--stack",
            "toy",
            "--robots",
            "1",
            "--channels",
            "paper",
            "--schedulers",
            "greedy",
            "-n",
            "1",
            "--max-steps",
            "5",
            "-j",
            "1",
            "-o",
            "{tmp}/out",
            "--json",
        ),
        (
            opt("--robots", ["2", "1,2", "1..2"], ["0", "x", "3..1", "", ",", "1..1000000000"]),
            opt("--channels", ["better", "paper,better"], ["bogus", "", ","]),
            opt("--schedulers", ["convex", "greedy,convex"], ["bogus", "", ","]),
            opt("--stack", ["toy"], ["bogus", ""]),
            opt("-n", ["2"], COUNT_BAD),
            opt("--stop-below", ["0", "0.5"], ["-0.1", "2", *NOT_FLOAT]),
            opt("--max-steps", ["3"], COUNT_BAD),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            _SEED,
            _OUT,
        ),
    ),
    "wifi crosscheck": OptionCommand(
        (
            "wifi",
            "crosscheck",
            "--ns3",
            "none",
            "--mcs",
            "7",
            "--captures",
            "staggered",
            "--schedulers",
            "greedy",
            "--periods",
            "2",
            "--max-stations",
            "20",
            "--json",
        ),
        (
            opt("--mcs", ["5", "3,7"], ["12", "-1", "x", "", ","]),
            opt("--captures", ["synchronised"], ["bogus", ","]),
            opt("--schedulers", ["greedy-admit"], ["bogus", ","]),
            opt("--ns3", ["none", ""], ["bogus"]),
            opt("--max-stations", ["10", "30"], ["0", "201", "-1", *NOT_INT]),
            opt("--periods", ["1", "3"], ["0", "-1", "1001", HUGE, *NOT_INT]),
            opt("--out", ["{tmp}/cc.json"], ["{tmp}", "/proc/codesign.json", "{file}/x.json"]),
            opt("--ns3-from", ["{recorded}"], ["{tmp}/nope.json", "{file}", "{tmp}", "{trace}"]),
        ),
    ),
    "evaluate": OptionCommand(
        ("evaluate", "-n", "1", "--max-steps", "3", "-j", "1", "-o", "{tmp}/out", "--json"),
        (
            opt("--controller", ["mpc", "scripted"], ["bogus", ""]),
            opt("--estimator", ["predictor", "none"], ["bogus", ""]),
            opt("--qos", ["static"], ["bogus", ""]),
            opt("-q", ["0.5", "1"], FRACTION_BAD),
            opt("--delay", ["0", "2"], ["-1", "1001", *NOT_INT]),
            opt("--belt-speed", ["0.2", "0.4"], SPEED_BAD),
            opt("--scenario", ["paper", "constant-0.2"], ["bogus"]),
            opt("-n", ["1"], COUNT_BAD),
            opt("--max-steps", ["2"], COUNT_BAD),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            opt("--name", ["e2"], ["a/b", ""]),
            opt("-c", [], ["{tmp}/nope.toml", "{tmp}"]),
            _SEED,
            _OUT,
        ),
    ),
    "fig-cn": OptionCommand(
        ("evaluate", "fig-cn", "-c", "{tiny_fig_cn}", "-o", "{tmp}/out", "--json"),
        (
            opt("-n", ["1"], COUNT_BAD),
            opt("--delay", ["1"], ["-1", "1001", *NOT_INT]),
            opt("--belt-speed", ["0.4"], SPEED_BAD),
            opt("-q", ["0.5"], FRACTION_BAD),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            _SEED,
            _OUT,
        ),
    ),
    "train": OptionCommand(
        ("train", "a", "--out", "{tmp}/o", "--work-dir", "{tmp}/w"),
        (
            opt("--steps", ["10"], COUNT_BAD),
            opt("--seed", ["1"], SEED_BAD),
            opt("--scenario", ["realistic"], ["bogus", ""]),
            opt("--set", ["total_steps=10"], ["x", "bogus=1", "total_steps=nan", "sac=3"]),
            opt("-c", [], ["{tmp}/nope.toml", "{tmp}"]),
        ),
        runs=False,
    ),
    "table": OptionCommand(
        ("table", "-o", "{tmp}/out"),
        (
            opt("--pipeline", ["model-based"], ["bogus", ""]),
            opt("--plant", ["0.2"], ["bogus", ""]),
            opt("--scenario", ["realistic"], ["bogus"]),
            opt("-n", ["2"], COUNT_BAD),
            opt("--seed", ["1"], SEED_BAD),
            opt("--seeds", ["0,1"], [",", "x", "-1", ""]),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            opt("--on-missing", ["skip", "error"], ["bogus", ""]),
            _OUT,
        ),
        runs=False,
    ),
    "tune": OptionCommand(
        ("tune", "-o", "{tmp}/out"),
        (
            opt("--target", ["0.9"], FRACTION_BAD),
            opt("-n", ["2"], COUNT_BAD),
            opt("--iterations", ["3"], COUNT_BAD),
            opt("--low", ["0.01"], ["0", "-1", "2", *NOT_FLOAT]),
            opt("--high", ["0.5"], ["0", "-1", *NOT_FLOAT]),
            opt("--seed-set", ["dev"], ["test", "bogus", ""]),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            opt("--scenario", ["realistic"], ["bogus"]),
            _OUT,
        ),
        runs=False,
    ),
    "paper": OptionCommand(
        ("paper", "-o", "{tmp}/out", "--docs", "{tmp}/docs"),
        (
            opt("-n", ["2"], COUNT_BAD),
            opt("--realistic-trials", ["2"], COUNT_BAD),
            opt("--fig-cn-trials", ["2"], COUNT_BAD),
            opt("--wifi-trials", ["2"], COUNT_BAD),
            opt("-j", ["1"], ["0", "100000", *NOT_INT]),
            opt("--only", ["lqg"], ["bogus", ""]),
            opt("--skip", ["lqg"], ["bogus", ""]),
            _OUT,
        ),
        runs=False,
    ),
    "render": OptionCommand(
        ("render", "-o", "{tmp}/r.gif", "--json"),
        (
            opt("--steps", ["2"], ["-1", HUGE, *NOT_INT]),
            opt("--fps", ["10"], ["0", "-1", "1001", *NOT_INT]),
            opt("--belt-speed", ["0.6"], SPEED_BAD),
            opt("--profile", ["variable"], ["bogus", ""]),
            opt("--object", ["cylinder"], ["bogus", ""]),
            opt("--camera", ["edge"], ["bogus", ""]),
            opt("-o", [], ["/proc/x.gif", "{tmp}/r.txt", "{tmp}"]),
            _SEED,
        ),
        runs=False,
    ),
    "calibrate-perception": OptionCommand(
        ("calibrate-perception", "-o", "{tmp}/c.json", "--json"),
        (
            opt("--episodes", ["1"], COUNT_BAD),
            opt("--sweep-frames", ["10"], COUNT_BAD),
            opt("--object", ["cylinder"], ["bogus", ""]),
            opt("--seed-set", ["dev"], ["test", "bogus", ""]),
            opt("-o", [], ["/proc/x.json", "{tmp}"]),
        ),
        runs=False,
    ),
}
"""Every command and its options (``readme``, which rewrites README.md, aside)."""

_TINY_FIG_CN = (
    "[fig_cn]\ntrials = 1\nmax_steps = 3\nworkers = 1\ndelays = [0]\nbelt_speeds_mps = [0.2]\n"
    'reliabilities = []\nestimators = ["none"]\n'
)


@pytest.fixture(scope="module")
def option_assets(tmp_path_factory: pytest.TempPathFactory, recorded_trace: dict) -> dict:
    """Inputs the options name: a results folder, a trace, a recorded ns-3 run, a file."""
    root = tmp_path_factory.mktemp("assets")
    (root / "trace.json").write_text(json.dumps(recorded_trace))
    (root / "fig_cn.toml").write_text(_TINY_FIG_CN)
    (root / "file").write_text("not a folder\n")
    recorded = Path(__file__).parents[1] / "docs" / "results" / "wifi_crosscheck.json"
    return {
        "results": str(_tiny_results(root / "results")),
        "trace": str(root / "trace.json"),
        "tiny_fig_cn": str(root / "fig_cn.toml"),
        "file": str(root / "file"),
        "recorded": str(recorded),
    }


@st.composite
def option_case(draw: st.DrawFn, command: OptionCommand) -> tuple[list[tuple[str, str]], bool]:
    """``([(flag, value)], any_invalid)``: one to three options, each valid or invalid."""
    options = draw(
        st.lists(
            st.sampled_from(command.options), min_size=1, max_size=3, unique_by=lambda o: o.flag
        )
    )
    chosen, bad = [], False
    for i, opt in enumerate(options):
        must_break = not command.runs and i == 0
        invalid = must_break or not opt.valid or draw(st.booleans())
        invalid = invalid and bool(opt.invalid)
        if not invalid and not opt.valid:
            continue
        value = draw(st.sampled_from(opt.invalid if invalid else opt.valid))
        chosen.append((opt.flag, value))
        bad = bad or invalid
    if not command.runs and not bad:  # a long command: never a valid run
        opt = next(o for o in command.options if o.invalid)
        chosen.append((opt.flag, opt.invalid[0]))
        bad = True
    return chosen, bad


def _option_argv(command: OptionCommand, chosen: list[tuple[str, str]], paths: dict) -> list[str]:
    argv = list(command.argv)
    for flag, value in chosen:
        if flag.startswith("{"):  # a positional argument of the base argv
            argv = [value if a == flag else a for a in argv]
        else:
            argv += [flag, value]
    return [a.format(**paths) for a in argv]


def run_option_case(name: str, data: st.DataObject, assets: dict) -> None:
    command = OPTION_COMMANDS[name]
    chosen, bad = data.draw(option_case(command), label="options")
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "empty").mkdir()
        argv = _option_argv(command, chosen, {**assets, "tmp": tmp})
        result = runner.invoke(app, argv)
        event(f"{'invalid' if bad else 'valid'} options: exit code {result.exit_code}")
        assert "Traceback" not in result.output, argv
        if result.exit_code == 0 and not bad:
            if command.json:
                json.loads(result.stdout)
            return
        assert result.exit_code == 2, (argv, result.exit_code, result.output[-2000:])
        lines = result.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), (argv, result.stderr[-2000:])


OPTIONS_PROPERTY = settings(PROPERTY, max_examples=25)


@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", OPTION_COMMANDS)
@OPTIONS_PROPERTY
@given(data=st.data())
def test_options_give_a_result_or_one_line(
    name: str, data: st.DataObject, option_assets: dict
) -> None:
    """Every command's options, valid or not (NaN, infinity, negative, huge, not a number,
    unknown choices, paths that cannot be read or written): exit 0 with a result, or exit 2
    with one line ``error: ...``; an invalid value is always refused (exit 2)."""
    run_option_case(name, data, option_assets)


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("name", OPTION_COMMANDS)
@settings(PROPERTY, max_examples=150)
@given(data=st.data())
def test_options_many_cases(name: str, data: st.DataObject, option_assets: dict) -> None:
    """The options property with 150 cases a command (2,700 in all): ``-m slow``."""
    run_option_case(name, data, option_assets)
