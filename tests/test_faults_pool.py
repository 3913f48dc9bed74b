"""Fault injection (issue 35): a worker process killed in the middle of an episode, in the
local pool (``codesign table -j 2``) and on Ray (a sweep). Each run ends with the same
results as an undisturbed run; the killed worker's task is run again, and nothing twice.

This module is imported by the pool's spawned workers (the controller below is built there),
so it keeps its imports light."""

from __future__ import annotations

import json
import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from numpy.typing import NDArray

from codesign_mb.control.scripted import ToyPickController
from codesign_mb.core import registry
from codesign_mb.core.registry import Kind

TABLE = """
[table]
trials = 6

[table.plant]
name = "toy"
options = { horizon = 40 }

[[table.rows]]
name = "static"
controller = { kind = "killing_toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 0.6, latency_steps = 1 } }
"""
KILL_MARKER = "CODESIGN_TEST_KILL_MARKER"
"""The marker file of :class:`KillingToyPick`: an environment variable, inherited by the
pool's workers and not part of the records' keys (an option naming an existing file would be
keyed by its content)."""


def _kill_once(marker: str) -> None:
    """``SIGKILL`` this process unless ``marker`` exists (made here first: exactly one dies)."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)  # as the kernel's OOM killer would


class KillingToyPick(ToyPickController):
    """The toy pick, whose process is killed at its ``at_step``-th step (counted over its
    episodes: with the toy's 40-step horizon, in the middle of its third) unless the file
    ``$CODESIGN_TEST_KILL_MARKER`` exists; never when that variable is unset."""

    def __init__(self, at_step: int, **toy: float) -> None:
        super().__init__(**toy)
        self.at_step = at_step
        self.steps = 0

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        self.steps += 1
        marker = os.environ.get(KILL_MARKER)
        if self.steps == self.at_step and marker:
            _kill_once(marker)
        return super().act(observation)


def killing_toy_pick(env: Any, at_step: int = 100) -> KillingToyPick:
    """Factory of the ``killing_toy_pick`` controller kind (registered by the test only)."""
    c = env.unwrapped.config
    toy = {"max_speed_mps": c.max_speed_mps, "control_period_s": c.control_period_s}
    return KillingToyPick(at_step, **toy)


@pytest.fixture
def killing_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register ``killing_toy_pick`` in the driver (workers get its import path)."""
    kind = Kind(f"{__name__}:killing_toy_pick", takes_env=True)
    monkeypatch.setitem(registry._table("controller"), "killing_toy_pick", kind)
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    monkeypatch.delenv(KILL_MARKER, raising=False)


def _episodes(out: Path) -> pd.DataFrame:
    from codesign_mb.evaluation.evaluate import TIMING_COLUMNS

    frame = pd.read_parquet(out / "tab_p_episodes.parquet")
    timing = [c for c in frame if c in TIMING_COLUMNS or c.endswith("_cpu_ms")]
    return frame.drop(columns=timing)


def _rows(out: Path) -> dict[str, dict[str, Any]]:
    """Stored item -> row of every record line (asserting that no item is stored twice)."""
    from codesign_mb.evaluation.evaluate import TIMING_COLUMNS

    rows: dict[str, dict[str, Any]] = {}
    for path in sorted((out / ".records").glob("*.jsonl")):
        for line in path.read_text().splitlines():
            record = json.loads(line)
            key = f"{path.stem}/{record['item']}"
            assert key not in rows, f"{key} stored twice"
            row = record["row"]
            timing = {k for k in row if k in TIMING_COLUMNS or k.endswith("_cpu_ms")}
            rows[key] = {k: v for k, v in row.items() if k not in timing}
    return rows


def test_a_worker_killed_mid_episode_is_replaced_and_the_table_is_unchanged(
    killing_kind: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from typer.testing import CliRunner

    from codesign_mb.cli import app

    config = tmp_path / "table.toml"
    config.write_text(TABLE)
    runner = CliRunner()
    reference = tmp_path / "reference"
    args = ["table", "-c", str(config), "--no-references", "-j", "1", "-o", str(reference)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    marker = tmp_path / "killed"
    monkeypatch.setenv(KILL_MARKER, str(marker))  # now one worker is killed
    out = tmp_path / "out"
    args = ["table", "-c", str(config), "--no-references", "-j", "2", "-o", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    [note] = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert re.fullmatch(
        r"warning: a worker process died; rerunning [1-6] tasks in a new pool", note
    )
    killed = int(marker.read_text())
    assert killed != os.getpid()  # a worker was killed, not the driver
    pd.testing.assert_frame_equal(_episodes(out), _episodes(reference), check_exact=True)
    assert len(_episodes(out)) == 6
    # every episode stored exactly once, with the same row as the undisturbed run's
    assert _rows(out) == _rows(reference)


# -- Ray -----------------------------------------------------------------------------------------
@pytest.fixture
def ray_local() -> Iterator[Any]:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_a_ray_worker_killed_mid_trial_is_retried_and_the_sweep_is_unchanged(
    ray_local: Any, tmp_path: Path
) -> None:
    """Ray reruns a task whose worker process died (``iter_ray`` asks for
    ``RAY_TASK_RETRIES`` = 3, Ray's default): the sweep's rows equal the serial ones, the killed
    trial ran twice (in two processes), every other trial once. (About 15 s, most of it
    Ray's start.)"""
    from codesign_mb.studies.sweep import SweepConfig, execute_trial, plan_sweep, trial_key
    from codesign_mb.studies.sweep_ray import iter_ray

    cfg = SweepConfig(n_seeds=2, belt_speeds_mps=(0.2, 0.6), params={"horizon_steps": 20})
    pending = [(trial_key(trial, seed), trial, seed) for trial, seed in plan_sweep(cfg)]
    reference = {key: execute_trial(trial, seed) for key, trial, seed in pending}
    marker, attempts = str(tmp_path / "killed"), tmp_path / "attempts"
    attempts.mkdir()
    victim = pending[1][0]

    def killed_once(trial: Any, seed: int) -> dict[str, Any]:
        # Pickled by value (Ray's workers cannot import this test module): no module globals.
        key = trial_key(trial, seed)
        with open(attempts / key, "a") as fh:
            fh.write(f"{os.getpid()}\n")
        if key == victim and not os.path.exists(marker):
            with open(marker, "x") as fh:
                fh.write(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        return execute_trial(trial, seed)

    got = dict(iter_ray(killed_once, pending, 2, None))
    assert got == reference
    tries = {p.name: p.read_text().split() for p in attempts.iterdir()}
    assert len(tries[victim]) == 2 and tries[victim][0] == Path(marker).read_text()
    assert tries[victim][1] != tries[victim][0]  # run again, in another worker process
    assert all(len(t) == 1 for key, t in tries.items() if key != victim)
