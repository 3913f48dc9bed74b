"""Work is never lost (issue 18): finished episodes are kept as they finish, an interrupted
``codesign table`` resumes to the same table bit for bit with no episode computed twice, and
killing the driver ends its workers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from typer.testing import CliRunner

import codesign_mb.cli.table as cli_table
from codesign_mb.cli import app
from codesign_mb.core.records import RecordStore, digest
from codesign_mb.evaluation import evaluate as evaluate_module
from codesign_mb.evaluation.evaluate import TIMING_COLUMNS

TRIALS = 40
TOY_TABLE = f"""
[table]
trials = {TRIALS}
references = true

[table.plant]
name = "toy"
options = {{ horizon = 40 }}

[[table.rows]]
name = "scripted, static QoS"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "none" }}
qos = {{ kind = "static", options = {{ reliability = 1.0, latency_steps = 1 }} }}

[[table.rows]]
name = "scripted, age rule"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "none" }}
qos.kind = "age_rule"
qos.options = {{ low = 0.3, high = 1.0, max_age_steps = 2, latency_steps = 1 }}
"""
# Cells: the two rows, blind, oracle (static equals the first row: run once) and, in a second
# pass at the age rule's measured reliability, random: 5 x 40 distinct episodes.
DISTINCT_EPISODES = 5 * TRIALS
_TIMING = {*TIMING_COLUMNS, "cpu_ms_per_step", "eval_wall_time_s"}


def _timeless(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` without the columns that measure time (they vary from run to run)."""
    return frame.drop(columns=[c for c in frame if c in _TIMING or c.endswith("_cpu_ms")])


def _tables(out: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    return (
        _timeless(pd.read_parquet(out / "tab_p.parquet")),
        _timeless(pd.read_parquet(out / "tab_p_episodes.parquet")),
    )


def _count_episodes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Record every episode run in this process (``-j 1``): ``(episode, seed)`` per call."""
    calls: list[tuple[int, int]] = []
    run = evaluate_module._Runner.run

    def counted(self: Any, episode: int, seed: int) -> dict[str, Any]:
        calls.append((episode, seed))
        return run(self, episode, seed)

    monkeypatch.setattr(evaluate_module._Runner, "run", counted)
    return calls


def _stored_items(records: Path) -> list[tuple[str, str]]:
    """Every stored line, as (file, item)."""
    return [
        (path.name, json.loads(line)["item"])
        for path in sorted(records.glob("*.jsonl"))
        for line in path.read_text().splitlines()
    ]


@pytest.fixture(scope="module")
def toy_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("config") / "table.toml"
    path.write_text(TOY_TABLE)
    return path


@pytest.fixture(scope="module")
def reference(toy_config: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """An uninterrupted run: its tables and how many episodes it computed."""
    out = tmp_path_factory.mktemp("reference") / "out"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CODESIGN_NO_PROGRESS", "1")
        calls = _count_episodes(patch)
        result = CliRunner().invoke(app, ["table", "-c", str(toy_config), "-o", str(out)])
    assert result.exit_code == 0, result.output
    summary, episodes = _tables(out)
    return {"summary": summary, "episodes": episodes, "computed": len(calls), "out": out}


def _interrupting_track(after: int) -> Any:
    """A progress wrapper raising ``KeyboardInterrupt`` (Ctrl-C) once ``after`` episodes
    reached it, counted over every pass of the table."""
    seen = [0]

    def track(stream: Any, **_: Any) -> Iterator[Any]:
        for item in stream:
            if seen[0] == after:
                raise KeyboardInterrupt
            seen[0] += 1
            yield item

    return track


def test_an_interrupted_table_resumes_to_the_same_table(
    toy_config: Path, reference: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    assert reference["computed"] == DISTINCT_EPISODES  # every distinct episode once
    calls = _count_episodes(monkeypatch)
    out = tmp_path / "out"
    args = ["table", "-c", str(toy_config), "-o", str(out)]
    with monkeypatch.context() as ctrl_c:
        ctrl_c.setattr(cli_table, "track", _interrupting_track(after=57))
        first = CliRunner().invoke(app, args)
    assert first.exit_code == 130
    # the 58th episode was stored as it finished, before Ctrl-C reached the progress bar
    assert len(calls) == 58
    assert first.stderr.splitlines() == [
        f"interrupted: 58 finished episodes kept in {out / '.records'}; rerun the same "
        "command to resume"
    ]
    assert not (out / "tab_p.parquet").exists()
    assert len(_stored_items(out / ".records")) == 58

    second = CliRunner().invoke(app, args)
    assert second.exit_code == 0, second.output
    assert "resumed: 58 episodes reused" in second.stderr
    assert len(calls) == DISTINCT_EPISODES  # 58 + 142: none computed twice
    stored = _stored_items(out / ".records")
    assert len(stored) == len(set(stored)) == DISTINCT_EPISODES
    summary, episodes = _tables(out)
    pd.testing.assert_frame_equal(summary, reference["summary"], check_exact=True)
    pd.testing.assert_frame_equal(episodes, reference["episodes"], check_exact=True)
    meta = json.loads((out / "tab_p.json").read_text())["extra"]
    assert (meta["episodes_computed"], meta["episodes_reused"]) == (142, 58)

    # A finished run is not recomputed; --fresh recomputes every episode, to the same table.
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and len(calls) == DISTINCT_EPISODES
    fresh = CliRunner().invoke(app, [*args, "--fresh"])
    assert fresh.exit_code == 0 and len(calls) == 2 * DISTINCT_EPISODES
    pd.testing.assert_frame_equal(_tables(out)[0], reference["summary"], check_exact=True)


def test_a_corrupt_episode_record_is_recomputed_with_a_warning(
    toy_config: Path, reference: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A torn last line (a killed write) and a garbage line: named, recomputed, same table."""
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    out = tmp_path / "out"
    records = out / ".records"
    records.mkdir(parents=True)
    for path in reference["out"].joinpath(".records").glob("*.jsonl"):
        (records / path.name).write_bytes(path.read_bytes())
    damaged = sorted(records.glob("*.jsonl"))[0]
    lines = damaged.read_bytes().splitlines(keepends=True)
    lines[3] = b"garbage\n"
    damaged.write_bytes(b"".join(lines)[:-40])  # and the last line torn
    calls = _count_episodes(monkeypatch)
    result = CliRunner().invoke(app, ["table", "-c", str(toy_config), "-o", str(out)])
    assert result.exit_code == 0, result.output
    warned = [line for line in result.stderr.splitlines() if "is corrupt" in line]
    assert warned == [
        f"warning: record file {damaged} line {n} is corrupt ({why}); its episode is computed again"
        for n, why in ((4, "Expecting value: line 1 column 1 (char 0)"), (TRIALS, _torn(lines)))
    ]
    assert len(calls) == 2  # only those two
    summary, episodes = _tables(out)
    pd.testing.assert_frame_equal(summary, reference["summary"], check_exact=True)
    pd.testing.assert_frame_equal(episodes, reference["episodes"], check_exact=True)


def _torn(lines: list[bytes]) -> str:
    try:
        json.loads(lines[-1][:-40])
    except ValueError as exc:
        return str(exc)
    raise AssertionError("the torn line parses")


def test_records_round_trip_exactly_and_keys_follow_the_content(tmp_path: Path) -> None:
    store = RecordStore(tmp_path)
    row = {"a": 0.1 + 0.2, "nan": float("nan"), "inf": -float("inf"), "none": None, "b": True}
    stored = store.add("g", "0:1", row)
    got = RecordStore(tmp_path).take("g", ["0:1", "1:2"])
    assert list(got) == ["0:1"] and got["0:1"] == stored
    assert (
        stored["a"] == row["a"] and stored["inf"] == row["inf"] and stored["nan"] != stored["nan"]
    )
    assert RecordStore(tmp_path, fresh=True).take("g", ["0:1"]) == {}
    # a checkpoint counts by its content: retrained at the same path, another key
    weights = tmp_path / "model.zip"
    weights.write_bytes(b"one")
    before = digest({"checkpoint": str(weights)})
    weights.write_bytes(b"two!")
    assert digest({"checkpoint": str(weights)}) != before


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == pid and state != "Z":
            found.append(int(entry.name))
    return found


def _all_gone(pids: set[int], within_s: float = 5.0) -> bool:
    """Whether every process of ``pids`` has exited within ``within_s`` (a worker or the
    resource tracker, reparented when its driver died, needs a few milliseconds to see it)."""
    deadline = time.monotonic() + within_s
    while any(map(_alive, pids)):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


_DRIVER = """
import time
from codesign_mb.evaluation import pool
if __name__ == "__main__":
    for _ in pool.imap(time.sleep, [(120,)] * 4, workers=2):
        pass
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_killing_the_driver_ends_its_workers(tmp_path: Path) -> None:
    script = tmp_path / "driver.py"
    script.write_text(_DRIVER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    driver = subprocess.Popen([sys.executable, str(script)], env=env)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(workers) < 2:
            time.sleep(0.2)
            workers = [
                pid
                for pid in _children(driver.pid)
                if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
            ]
        assert len(workers) == 2, "the pool did not start"
        time.sleep(2.0)  # the workers are in their task (a 120 s sleep)
        driver.send_signal(signal.SIGKILL)
        driver.wait(timeout=10)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(map(_alive, workers)):
            time.sleep(0.1)
        assert not any(map(_alive, workers)), "a worker outlived its driver"
    finally:
        if driver.poll() is None:
            driver.kill()
        for pid in workers:  # only if the test failed: leave no sleeping orphan behind
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


BLIND_TABLE = """
[table]
trials = 8
references = false

[table.plant]
name = "toy"
options = { horizon = 1000 }

[[table.rows]]
name = "blind"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 0.0, latency_steps = 1 } }
"""
# q = 0: the toy pick never succeeds, so every episode runs its 1000 steps (~0.2 s).


@pytest.mark.slow  # ~25 s: a driver and its workers import the package (the in-process
# interruption above is the default suite's)
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_on_a_parallel_table_keeps_what_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGINT to the process group, as a terminal's Ctrl-C: one line, exit 130, workers gone,
    the finished episodes kept and reused by the rerun."""
    config, out = tmp_path / "blind.toml", tmp_path / "out"
    config.write_text(BLIND_TABLE)
    args = ["table", "-c", str(config), "-o", str(out)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "CODESIGN_NO_PROGRESS": "1"}
    main = "import sys; from codesign_mb.cli import main; sys.argv[0] = 'codesign'; main()"
    command = [sys.executable, "-c", main, *args, "-j", "2"]
    driver = subprocess.Popen(
        command, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(_stored_items(out / ".records")) < 2:
            assert driver.poll() is None, driver.communicate()
            workers.update(_children(driver.pid))
            time.sleep(0.05)
        os.killpg(driver.pid, signal.SIGINT)
        _, stderr = driver.communicate(timeout=60)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    kept = len(_stored_items(out / ".records"))
    assert 2 <= kept < 8
    assert driver.returncode == 130
    assert stderr.splitlines() == [
        f"interrupted: {kept} finished episodes kept in {out / '.records'}; rerun the same "
        "command to resume"
    ]
    assert workers and _all_gone(workers)
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    calls = _count_episodes(monkeypatch)
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert f"resumed: {kept} episodes reused" in result.stderr
    assert len(calls) == 8 - kept
    episodes = pd.read_parquet(out / "tab_p_episodes.parquet")
    assert episodes["episode"].tolist() == list(range(8))


def test_an_interrupted_paper_study_resumes_from_its_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``codesign paper``: the study in progress keeps its finished episodes in its partial
    folder, and the rerun continues it (here a toy table stands in for a table study)."""
    from codesign_mb.core.registry import ComponentSpec, PlantSpec
    from codesign_mb.studies import paper
    from codesign_mb.studies.paper_studies import PaperConfig
    from codesign_mb.studies.table import TableConfig
    from codesign_mb.studies.table_figures import run_table_study
    from codesign_mb.studies.table_rows import TableRow

    row = TableRow(
        "scripted", ComponentSpec("toy_pick"), ComponentSpec("none"), ComponentSpec("static")
    )
    toy = TableConfig(plant=PlantSpec("toy", {"horizon": 40}), rows=(row,), trials=10)

    def toy_table(name: str, settings: Any, out: Path, workers: int, progress: Any) -> dict:
        run_table_study(toy, out, progress=progress)
        return {}

    monkeypatch.setattr(paper, "_run_table", toy_table)
    calls = _count_episodes(monkeypatch)
    out = tmp_path / "paper"
    config = PaperConfig(only=("table_realistic",), workers=1)
    partial = out / ".table_realistic.partial" / ".records"
    with pytest.raises(KeyboardInterrupt) as caught:
        paper.run_paper(config, out, progress=_interrupting_track(after=4))
    assert str(caught.value) == (
        f"complete studies kept in {out}: none; 5 finished episodes kept in {partial}; rerun "
        "the same command to resume"
    )
    assert len(calls) == 5 and len(_stored_items(partial)) == 5
    assert paper.run_paper(config, out).status == {"table_realistic": "ran"}
    assert len(calls) == 10  # the other 5 only
    assert pd.read_parquet(out / "table_realistic" / "tab_p_episodes.parquet")[
        "episode"
    ].tolist() == list(range(10))
    assert not list(out.glob(".*.partial")) and not (out / "table_realistic" / ".records").exists()


def test_capacity_trials_resume_to_the_same_table(tmp_path: Path) -> None:
    """``wifi capacity`` keeps each trial as it finishes; a rerun computes only the rest."""
    from codesign_mb.core.records import RECORDS_DIR
    from codesign_mb.studies import fig_wifi
    from codesign_mb.studies.fig_wifi import CapacityConfig, run_capacity
    from codesign_mb.studies.fig_wifi_figures import run_capacity_study

    cfg = CapacityConfig(
        robots=(1, 2),
        channels=("paper",),
        schedulers=("greedy",),
        stack="toy",
        trials=2,
        max_steps=20,
    )
    whole = run_capacity(cfg)  # no store: the rows as computed
    run = fig_wifi.run_point
    calls: list[int] = []

    def counted(config: Any, **point: Any) -> dict[str, Any]:
        calls.append(point["trial"])
        return run(config, **point)

    out = tmp_path / "out"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fig_wifi, "run_point", counted)
        with pytest.raises(KeyboardInterrupt, match="3 finished trials kept in"):
            run_capacity_study(cfg, out, progress=_interrupting_track(after=2))
        store = RecordStore(out / RECORDS_DIR, what="trial")
        resumed = run_capacity(cfg, store=store)
    assert len(calls) == len(cfg.points()) == 8  # 3 + 5: none twice
    assert (store.reused, store.computed) == (3, 5)
    pd.testing.assert_frame_equal(resumed, whole, check_exact=True)


def test_an_evaluation_is_not_recomputed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    calls = _count_episodes(monkeypatch)
    args = ["evaluate", "--controller", "scripted", "--estimator", "none", "-n", "3"]
    args += ["--max-steps", "10", "-j", "1", "-o", str(tmp_path), "--json"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    table = pd.read_parquet(tmp_path / "evaluate.parquet")
    second = CliRunner().invoke(app, [*args, "-q", "1.0"])  # the same settings, given
    assert second.exit_code == 0, second.output
    assert len(calls) == 3 and "resumed: 3 episodes reused" in second.stderr
    again = pd.read_parquet(tmp_path / "evaluate.parquet")
    pd.testing.assert_frame_equal(again, table, check_exact=True)  # timing columns too: kept
    more = CliRunner().invoke(app, [*args, "-n", "5"])  # seeds are prefix-stable: 2 more
    assert more.exit_code == 0 and len(calls) == 5
    changed = CliRunner().invoke(app, [*args, "-q", "0.5"])
    assert changed.exit_code == 0 and len(calls) == 8  # another setting: other episodes
