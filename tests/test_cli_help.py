"""Help that helps: every default shown, one meaning per short flag, README's CLI claims true."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.cli.demo import _LQG, _ROBOT, LQG_TABLE_NOTE

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()

NO_DEFAULT = {"--config", "--set", "--param", "--only", "--skip", "--readme", "--address"}
"""Options whose absence is their default (no file, no override): nothing to show."""

_RICH_TAG = re.compile(r"(?<!\\)\[[a-zA-Z#/@][^\[\]]*\]")
"""What rich takes for a markup tag, and so swallows from a help text: ``[default: x]``."""


def _commands() -> list[tuple[str, Any]]:
    """Every command (and group) of ``codesign``, by its path."""
    found = []

    def walk(command: Any, path: list[str]) -> None:
        found.append((" ".join(path), command))
        for name, sub in sorted(getattr(command, "commands", {}).items()):
            walk(sub, [*path, name])

    walk(typer.main.get_command(app), [])
    return found


COMMANDS = _commands()
LEAVES = [
    (p, c) for p, c in COMMANDS if (p and not getattr(c, "commands", None)) or p == "evaluate"
]


def _help(path: str) -> str:
    """``codesign PATH --help`` as a user reads it, box drawing and line breaks removed."""
    result = runner.invoke(app, [*path.split(), "--help"], env={"COLUMNS": "300"})
    assert result.exit_code == 0, result.output
    text = re.sub(r"[│╭╮╰╯─]", " ", result.stdout)
    return " ".join(text.split())


@pytest.mark.parametrize(("path", "command"), COMMANDS, ids=[p or "codesign" for p, _ in COMMANDS])
def test_no_help_text_is_swallowed_by_rich_markup(path: str, command: Any) -> None:
    texts = [command.help or ""] + [getattr(p, "help", None) or "" for p in command.params]
    for text in texts:
        assert not _RICH_TAG.search(text), f"{path}: escape the bracket in {text!r}"


@pytest.mark.parametrize(("path", "command"), LEAVES, ids=[p for p, _ in LEAVES])
def test_every_default_is_visible_in_help(path: str, command: Any) -> None:
    shown = _help(path)
    for param in command.params:
        if param.param_type_name != "option" or param.name == "help":
            continue
        written = re.findall(r"\\\[(default: [^\]]*)\]", param.help or "")
        for default in written:  # as written in the source: shown, not swallowed
            assert f"[{' '.join(default.split())}]" in shown, (path, default)
        flag_off = param.is_flag and not param.secondary_opts and not param.default
        if written or flag_off or set(param.opts) & NO_DEFAULT:
            continue
        assert param.default is not None and param.show_default is not False, (
            f"{path} {param.opts[0]}: its default is not shown; add \\[default: ...] to its help"
        )


def test_one_meaning_per_short_flag() -> None:
    meanings: dict[str, list[set[str]]] = {}
    for _, command in COMMANDS:
        for param in command.params:
            opts = [*getattr(param, "opts", []), *getattr(param, "secondary_opts", [])]
            longs = {o for o in opts if o.startswith("--")}
            for short in (o for o in opts if re.fullmatch(r"-[a-zA-Z]", o)):
                meanings.setdefault(short, []).append(longs)
    for short, longs in meanings.items():
        assert set.intersection(*longs), f"{short} means {longs}"
    assert all("--trials" in longs for longs in meanings["-n"])


def test_evaluate_help_shows_its_own_description() -> None:
    shown = _help("evaluate")
    assert "95% Wilson interval" in shown and "[evaluate.mpc] (MpcConfig)" in shown


def test_demo_help_shows_the_defaults_of_both_scenarios() -> None:
    from codesign_mb.studies.demo import LqgDemoConfig, RobotDemoConfig

    for shown, config in ((_ROBOT, RobotDemoConfig()), (_LQG, LqgDemoConfig())):
        for name, value in shown.items():
            actual = getattr(config, name)
            expected = ", ".join(f"{q:g}" for q in actual) if name == "reliabilities" else actual
            assert value == expected, (name, value, actual)
    assert "[default: robot 1, 0.3, 0.1; lqg 1, 0.9, 0.7, 0.5, 0.3]" in _help("demo")


def test_lqg_demo_table_is_explained_under_it() -> None:
    args = ["demo", "--scenario", "lqg", "-n", "1", "--horizon", "5", "-q", "1"]
    result = runner.invoke(app, args, env={"COLUMNS": "300"})
    assert result.exit_code == 0, result.output
    assert result.stdout.rstrip().endswith(LQG_TABLE_NOTE)


def _readme_exceptions(flag: str) -> set[str]:
    """The commands README says lack ``flag``: "... on every command but `a`, `b` and `c`"."""
    text = " ".join((ROOT / "README.md").read_text().split())
    match = re.search(
        re.escape(flag) + r"[^;]*? on every command but ((?:`[^`]+`(?:, | and )?)+)", text
    )
    assert match, f"README's sentence about {flag} is gone"
    return set(re.findall(r"`([^`]+)`", match.group(1)))


@pytest.mark.parametrize("flag", ["--json", "--seed", "(`-c`"])
def test_readme_says_which_commands_take_json_seed_and_config(flag: str) -> None:
    option = {"(`-c`": "--config"}.get(flag, flag)
    runnable = [(p, c) for p, c in COMMANDS if p and not getattr(c, "commands", None)]
    runnable += [("evaluate", dict(COMMANDS)["evaluate"])]
    lacking = {
        path
        for path, command in runnable
        if not any(option in getattr(p, "opts", []) for p in command.params)
    }
    assert lacking == _readme_exceptions(flag)


def test_train_steps_is_the_budget_of_stage_a_warm_up_too() -> None:
    from codesign_mb.cli.train import stage_config
    from codesign_mb.stages.stage_a import StageAConfig

    default = StageAConfig()
    cfg = stage_config("a", None, assignments=[], seed=None, steps=300, estimator=None)
    assert (cfg.total_steps, cfg.critic_warmup_steps) == (300, 300)
    cfg = stage_config(
        "a", None, assignments=["critic_warmup_steps=7"], seed=None, steps=300, estimator=None
    )
    assert cfg.critic_warmup_steps == 7  # what --set says wins
    big = default.total_steps * 10
    cfg = stage_config("a", None, assignments=[], seed=None, steps=big, estimator=None)
    assert cfg.critic_warmup_steps == default.critic_warmup_steps  # a cap, never a raise


def test_fig_wifi_curves_of_static_and_codesign_look_different() -> None:
    from codesign_mb.studies.fig_wifi_figures import curve_styles

    styles = curve_styles(["static", "codesign"], ["greedy", "convex"])
    looks = {
        key: (s["ls"], s["marker"], s["markerfacecolor"], s["color"]) for key, s in styles.items()
    }
    assert len(set(looks.values())) == len(looks)
    for scheduler in ("greedy", "convex"):
        static, codesign = styles[(scheduler, "static")], styles[(scheduler, "codesign")]
        assert static["marker"] != codesign["marker"] and static["color"] != codesign["color"]
        assert static["markerfacecolor"] != codesign["markerfacecolor"]  # filled vs hollow
    dodges = [s["dodge"] for s in styles.values()]
    assert len(set(dodges)) == len(dodges) and sum(dodges) == pytest.approx(0.0)


def test_sweep_n_is_its_trials_per_grid_point(tmp_path: Path) -> None:
    """README's sweep line: robot counts by --robots, replicates (trials) by -n."""
    import json

    def trials(*extra: str) -> int:
        args = ["sweep", "--robots", "1", "--robots", "2", "-v", "0.2", "--backend", "serial"]
        args += ["--param", "horizon_steps=5", "--fresh", "-o", str(tmp_path), "--json"]
        result = runner.invoke(app, [*args, *extra])
        assert result.exit_code == 0, result.output
        return json.loads(result.stdout)["n_trials"]

    assert trials("-n", "2") == trials("--seeds", "2") == 2 * trials("-n", "1")
