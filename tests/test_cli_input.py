"""Issue 18's corpus: every bad input a user typed gives one line naming it, exit code 2.

Each case is a command that ended in a traceback, ran until killed, or was accepted and
produced nonsense on the commit the issue was filed against. Each now stops before any work
with one line ``error: ...`` on stderr that names the field (and the file, when the file's
value is at fault) and the value; where the input is valid, the result is the one asked for.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.core.config import LATENCY_STEPS_CAP, ROBOTS_CAP
from codesign_mb.core.results import write_results

runner = CliRunner()

CONFIG_COMMANDS = {
    "demo": ["demo"],
    "bench": ["bench", "env"],
    "sweep": ["sweep"],
    "report": ["report", "{tmp}"],
    "render": ["render"],
    "train": ["train", "a"],
    "table": ["table"],
    "paper": ["paper"],
    "wifi capacity": ["wifi", "capacity"],
    "evaluate": ["evaluate"],
    "evaluate fig-cn": ["evaluate", "fig-cn"],
    "tune": ["tune"],
}
"""Every command that takes a config file (-c), as a user types it."""


def one_line_error(result, *needles: str) -> str:
    """The command stopped on bad input: exit 2, one line ``error: ...`` holding ``needles``."""
    assert result.exit_code == 2, (result.exit_code, result.output)
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _run(args: list[str], tmp_path: Path):
    """Run ``args`` with its outputs under ``tmp_path`` (nothing written elsewhere)."""
    out: list[str] = []
    if args[0] in ("evaluate", "sweep", "table", "paper", "report", "tune") or args[:2] == [
        "wifi",
        "capacity",
    ]:
        out = ["-o", str(tmp_path / "out")]
    elif args[0] == "render":
        out = ["-o", str(tmp_path / "out.gif")]
    elif args[0] == "train":
        out = ["--out", str(tmp_path / "out"), "--work-dir", str(tmp_path / "work")]
    return runner.invoke(app, [*(a.format(tmp=tmp_path) for a in args), *out])


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
@pytest.mark.parametrize(
    ("suffix", "text", "where"),
    [
        (".yaml", "trials: [1, 2\n", "line 2"),
        (".toml", "seed = 1\nx = = 2\n", "line 2"),
        (".toml", "trials = [1, 2\n", "line 2"),
    ],
)
def test_malformed_config_names_the_file_and_line(
    command: str, suffix: str, text: str, where: str, tmp_path: Path
) -> None:
    config = tmp_path / f"bad{suffix}"
    config.write_text(text)
    result = _run([*CONFIG_COMMANDS[command], "-c", str(config)], tmp_path)
    one_line_error(result, str(config), where, "not valid")


def _trace(tmp_path: Path) -> dict:
    path = tmp_path / "trace.json"
    result = runner.invoke(app, ["wifi", "trace", str(path), "--robots", "2", "--steps", "2"])
    assert result.exit_code == 0, result.output
    return json.loads(path.read_text())


def _frames(data: dict, column: str, value: object) -> dict:
    data["frames"][column][0] = value
    return data


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        (lambda d: [], "must be a JSON object, got []"),
        (lambda d: None, "must be a JSON object, got None"),
        (lambda d: 3, "must be a JSON object, got 3"),
        (lambda d: {k: v for k, v in d.items() if k != "horizon_ticks"}, "'horizon_ticks'"),
        (lambda d: {k: v for k, v in d.items() if k != "ul_bpss"}, "'ul_bpss'"),
        (lambda d: _frames(d, "ul_bits", -5), "frames.ul_bits must be >= 0, got -5"),
        (lambda d: _frames(d, "ul_ok", 2), "frames.ul_ok must be 0 or 1, got 2"),
        (lambda d: _frames(d, "deadline_tick", 10**6), "frames.deadline_tick must be <= "),
        (lambda d: {**d, "horizon_ticks": d["horizon_ticks"] + 0.5}, "horizon_ticks must be an"),
        (lambda d: {**d, "ul_bpss": [[float("nan")]]}, "ul_bpss must be finite"),
        (lambda d: {**d, "extra": 1}, "unknown key 'extra'"),
    ],
)
def test_solve_rejects_a_malformed_instance(change, needle: str, tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(change(_trace(tmp_path))))
    one_line_error(runner.invoke(app, ["solve", str(path)]), needle, str(path))


def test_solve_still_solves_a_recorded_trace(tmp_path: Path) -> None:
    _trace(tmp_path)
    result = runner.invoke(app, ["solve", str(tmp_path / "trace.json"), "--json"])
    assert result.exit_code == 0, result.output
    # 2 robots, 2 steps, q = 1 on the paper cell: every frame gets through in time.
    assert json.loads(result.stdout)["optimum_frames"] == pytest.approx(4.0)


def _config(tmp_path: Path, text: str, suffix: str = ".toml") -> str:
    path = tmp_path / f"c{suffix}"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["wifi", "capacity", "--channels", ""], ["channels must name at least one"]),
        (["wifi", "capacity", "--schedulers", ","], ["schedulers must name at least one"]),
        (
            ["wifi", "capacity", "--robots", "1..1000000000"],
            [f"robots must be <= {ROBOTS_CAP.value}", "1000000000"],
        ),
        (
            ["wifi", "trace", "{tmp}/t.json", "--latency", "100000"],
            [f"latency_steps must be <= {LATENCY_STEPS_CAP.value}", "100000"],
        ),
        (["evaluate", "--delay", "1000000"], ["latency_steps must be <= ", "1000000"]),
        (["demo", "--latency", "1000000"], ["latency_steps must be <= ", "1000000"]),
        (["train", "a", "--set", "sac=3"], ["sac must be a table, got 3"]),
        (["train", "a", "--set", "total_steps=NaN"], ["total_steps must be an integer, got nan"]),
        (["train", "c", "--set", "env.j_max=NaN"], ["env.j_max must be a finite number, got nan"]),
        (["bench", "env", "--repeats", "0"], ["repeats must be >= 1, got 0"]),
        (
            ["calibrate-perception", "--sweep-frames", "1000000000", "-o", "{tmp}/c.json"],
            ["sweep_frames must be <= ", "1000000000"],
        ),
        (
            ["calibrate-perception", "--episodes", "-1", "-o", "{tmp}/c.json"],
            ["episodes must be >= 1, got -1"],
        ),
        (["sweep", "--workers", "100000"], ["workers must be <= 256"]),
    ],
)
def test_bad_option_is_one_line(args: list[str], needles: list[str], tmp_path: Path) -> None:
    one_line_error(_run(args, tmp_path), *needles)


@pytest.mark.parametrize(
    ("args", "text", "needles"),
    [
        (["evaluate"], "[evaluate]\nlatency_steps = inf\n", ["latency_steps", "got inf"]),
        (["evaluate"], "[evaluate]\nlatency_steps = 1e30\n", ["latency_steps", "1e+30"]),
        (["evaluate"], "[evaluate.mpc]\nhorizon = nan\n", ["mpc.horizon", "got nan"]),
        (["evaluate"], "[evaluate.predictor]\nacel_std = 1.0\n", ["unknown option 'acel_std'"]),
        (["sweep"], "[sweep]\nn_seeds = 1e30\n", ["n_seeds", "1e+30"]),
        (["sweep"], "[sweep]\nn_seeds = 1000000\n", ["n_seeds must be <= 100000", "1000000"]),
        (["bench", "env"], "[bench]\nrepeats = 1e30\n", ["repeats", "1e+30"]),
        (["wifi", "capacity"], "[capacity]\nchannels = []\n", ["channels must name"]),
        (["wifi", "capacity"], "[capacity]\ntrials = 'many'\n", ["trials must be an integer"]),
        (["demo"], "[demo]\nlatency_steps = 3\n", ["no [robot_demo] table", "[demo]"]),
        (["train", "c"], "[c.env]\nj_max = nan\n", ["env.j_max must be a finite number"]),
        (["train", "a"], "[a]\ntotal_steps = nan\n", ["total_steps must be an integer"]),
        (["report", "{tmp}"], "[report]\ndpi = 1000000\n", ["dpi must be <= 1200"]),
        (["table"], "[table]\ntrials = -3\n", ["trials must be >= 1, got -3"]),
        (["paper"], "[paper]\nworkers = 1e9\n", ["workers must be <= 256"]),
    ],
)
def test_bad_config_value_names_file_field_and_value(
    args: list[str], text: str, needles: list[str], tmp_path: Path
) -> None:
    path = _config(tmp_path, text)
    one_line_error(_run([*args, "-c", path], tmp_path), *needles, path)


def test_a_command_line_value_is_not_blamed_on_the_file(tmp_path: Path) -> None:
    path = _config(tmp_path, "[evaluate]\ntrials = 2\n")
    line = one_line_error(_run(["evaluate", "-c", path, "--delay", "5000"], tmp_path))
    assert "latency_steps" in line and path not in line


@pytest.mark.parametrize("body", ["[]", '{"rows": 1}', "not json"])
@pytest.mark.parametrize("name", ["tab_p", "fig_cn", "fig_wifi", "fig_lat"])
def test_report_on_a_corrupt_table_names_its_file(name: str, body: str, tmp_path: Path) -> None:
    import pandas as pd

    results = tmp_path / "results"
    write_results(results, table=pd.DataFrame({"a": [1]}), config={"k": 1}, name=name)
    (results / f"{name}.json").write_text(body)
    one_line_error(runner.invoke(app, ["report", str(results)]), f"{name}.json")


def test_lqg_demo_reads_its_latency_from_the_config_file(tmp_path: Path) -> None:
    """Once ignored (always 0): the [demo] table's latency reaches the run."""
    path = _config(tmp_path, "[demo]\nlatency_steps = 3\nhorizon = 5\nepisodes = 1\n")
    result = runner.invoke(app, ["demo", "--scenario", "lqg", "-c", path, "-q", "1", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["latency_steps"] == 3 and data["horizon"] == 5
    # tau = 3 and every packet delivered: the held measurement is 3 steps old once the first
    # arrives (step 3), and the initial hold counts 1, 2, 3 before it: mean age of 5 steps.
    assert data["rows"][0]["mean_age"] == pytest.approx((1 + 2 + 3 + 3 + 3) / 5)


# -- issue 35: the examples, and what the command-line fuzzer found ----------------------------
def _fig_cn_results(tmp_path: Path, change=None) -> Path:
    """A real (tiny) results folder: Fig. 4's table as ``evaluate fig-cn`` writes it."""
    import pandas as pd

    table = pd.DataFrame(
        {
            "estimator": ["predictor", "predictor", "none", "none"],
            "belt_speed_mps": [0.2] * 4,
            "latency_steps": [0, 1, 0, 1],
            "trials": [2] * 4,
            "successes": [2, 1, 1, 0],
            "success_rate": [1.0, 0.5, 0.5, 0.0],
        }
    )
    results = tmp_path / "results"
    write_results(results, table=change(table) if change else table, config={}, name="fig_cn")
    return results


def test_report_renders_the_tiny_results_folder(tmp_path: Path) -> None:
    result = runner.invoke(app, ["report", str(_fig_cn_results(tmp_path)), "--json"])
    assert result.exit_code == 0, result.output
    assert set(json.loads(result.stdout)["figures"]) == {"fig_cn"}


@pytest.mark.parametrize(
    ("change", "needles"),
    [
        (lambda t: t.assign(success_rate="high"), ["success_rate must be a number in [0, 1]"]),
        (lambda t: t.assign(latency_steps=[0.0, float("nan"), 0.0, 1.0]), ["row 1", "got nan"]),
        (lambda t: t.assign(latency_steps=-1), ["latency_steps must be an integer >= 0"]),
        (lambda t: t.assign(belt_speed_mps=float("nan")), ["belt_speed_mps", "got nan"]),
        (lambda t: t.assign(successes=3), ["successes must be <= trials", "3 > 2"]),
    ],
)
def test_report_refuses_a_column_it_cannot_draw(change, needles, tmp_path: Path) -> None:
    results = _fig_cn_results(tmp_path, change)
    one_line_error(
        runner.invoke(app, ["report", str(results)]), str(results / "fig_cn.parquet"), *needles
    )
    assert not (results / "report").exists()  # checked before anything is written


def test_report_refuses_a_folder_without_results(tmp_path: Path) -> None:
    (tmp_path / "metadata.json").write_text('"str"')
    line = one_line_error(runner.invoke(app, ["report", str(tmp_path)]), "not a results folder")
    assert "metadata.json" in line
    results = _fig_cn_results(tmp_path)
    (results / "fig_cn.json").write_text('"str"')  # a table whose metadata is a string
    one_line_error(runner.invoke(app, ["report", str(results)]), "fig_cn.json", "got str")


def test_crosscheck_reads_a_recorded_ns3_run_without_ns3(tmp_path: Path) -> None:
    recorded = Path(__file__).parents[1] / "docs" / "results" / "wifi_crosscheck.json"
    grid = ["--mcs", "7", "--captures", "staggered", "--schedulers", "greedy"]
    result = runner.invoke(
        app, ["wifi", "crosscheck", *grid, "--ns3-from", str(recorded), "--json"]
    )
    assert result.exit_code == 0, result.output
    row = json.loads(result.stdout)["rows"][0]
    assert row["ns3_best"] == max(row[f"ns3_{a}"] for a in ("su", "su-rts", "ofdma")) > 0
    trace = tmp_path / "trace.json"
    _trace(tmp_path)  # valid JSON, but a trace, not an ns-3 run
    for path, needle in [
        (trace, "must be a JSON object with a list 'rows'"),
        (tmp_path / "nope.json", "cannot be read"),
    ]:
        result = runner.invoke(app, ["wifi", "crosscheck", *grid, "--ns3-from", str(path)])
        one_line_error(result, str(path), needle)
    result = runner.invoke(app, ["wifi", "crosscheck", "--mcs", "5", "--ns3-from", str(recorded)])
    one_line_error(result, "ns-3 is not installed", "no ns-3 result for su at MCS 5")


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        ("belt_speeds_mps = [nan]", ["belt_speeds_mps[0] must be a finite number, got nan"]),
        ("delays = [-1]", ["delays must be integers >= 0, got -1"]),
        ("delays = []", ["delays must not be empty"]),
        ("belt_speeds_mps = []", ["belt_speeds_mps must not be empty"]),
        ("estimators = []", ["estimators must not be empty"]),
    ],
)
def test_fig_cn_config_refuses(text: str, needles: list[str], tmp_path: Path) -> None:
    path = _config(tmp_path, f"[fig_cn]\n{text}\n")
    one_line_error(_run(["evaluate", "fig-cn", "-c", path], tmp_path), *needles, path)


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["evaluate", "--trials", "nan"], ["'--trials'", "codesign evaluate --help"]),
        (["evaluate", "--bogus", "1"], ["No such option: --bogus"]),
        (["wifi", "nope"], ["No such command 'nope'", "codesign wifi --help"]),
        (["solve"], ["Missing argument"]),
        (["wifi", "crosscheck", "--ns3", "none", "--periods", "100000000"], ["periods must be <="]),
        (["wifi", "crosscheck", "--ns3", "none", "--mcs", ","], ["mcs must name at least one"]),
        (["wifi", "crosscheck", "--ns3", "none", "--out", "/proc/x.json"], ["out: cannot write"]),
        (["evaluate", "-o", "/proc/codesign"], ["--out: cannot write into '/proc/codesign'"]),
        (["evaluate", "fig-cn", "-o", "/proc/codesign"], ["--out: cannot write into"]),
        (["sweep", "-o", "/proc/codesign"], ["--out: cannot write into"]),
        (["table", "-o", "/proc/codesign"], ["--out: cannot write into"]),
        (["tune", "-o", "/proc/codesign"], ["--out: cannot write into"]),
        (["wifi", "capacity", "-o", "/proc/codesign"], ["--out: cannot write into"]),
        (["table", "--seeds", ","], ["seeds must name at least one seed"]),
        (
            ["calibrate-perception", "--seed-set", "test", "-o", "{tmp}/c.json"],
            ["refusing to calibrate on the 'test' seed set"],
        ),
        (
            ["demo", "--scenario", "robot", "--horizon", "5"],
            ["--horizon applies to --scenario lqg"],
        ),
        (["train", "a", "--seed", "-1"], ["seed must be >= 0, got -1"]),
        (["report", "{tmp}", "--seed", "1000000000000000"], ["seed must be <= 4294967295"]),
        (["wifi", "capacity", "--seed", "1000000000000000"], ["seed must be <= 4294967295"]),
        (["render", "--seed", "1000000000000000", "-o", "{tmp}/r.gif"], ["seed must be <= "]),
    ],
)
def test_command_line_is_refused_before_any_work(
    args: list[str], needles: list[str], tmp_path: Path
) -> None:
    """Found by the command-line fuzzer (and the issue's usage errors): each was accepted and
    ran (some until killed), failed after work began, or printed click's boxed usage text."""
    args = [a.format(tmp=tmp_path) for a in args]
    one_line_error(runner.invoke(app, args), *needles)
