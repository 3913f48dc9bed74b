"""Fault injection (issues 18 and 35): a full results disk, a failing MPC solver, an
allocator solver returning non-finite values, corrupt checkpoints and records, a results
write killed half-way. Each run completes with the fault counted in its results, or stops
with one clear line, with every finished result intact, and a rerun gives the undisturbed
run's results. (A worker killed mid-episode, locally and on Ray: ``test_faults_pool.py``, and
``test_evaluate.py``, ``test_core.py``; the driver killed: ``test_resume.py``.)"""

from __future__ import annotations

import errno
import json
import os
import signal
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.core.records import RecordStore
from codesign_mb.core.registry import models_dir
from codesign_mb.evaluation import evaluate as evaluate_module
from codesign_mb.evaluation.evaluate import TIMING_COLUMNS

TABLE = """
[table]
trials = 10

[table.plant]
name = "toy"
options = { horizon = 40 }

[[table.rows]]
name = "static"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 1.0, latency_steps = 1 } }

[[table.rows]]
name = "30%"
controller = { kind = "toy_pick" }
estimator = { kind = "none" }
qos = { kind = "static", options = { reliability = 0.3, latency_steps = 1 } }
"""


def _episodes(out: Path) -> pd.DataFrame:
    frame = pd.read_parquet(out / "tab_p_episodes.parquet")
    return frame.drop(columns=[c for c in frame if c in TIMING_COLUMNS or c.endswith("_cpu_ms")])


def _lines(records: Path) -> list[str]:
    return [line for p in sorted(records.glob("*.jsonl")) for line in p.read_text().splitlines()]


def _stored(records: Path) -> dict[str, dict[str, Any]]:
    """``<group>/<item>`` -> stored row (timings dropped) of every record line."""
    rows = {}
    for path in sorted(records.glob("*.jsonl")):
        for line in path.read_text().splitlines():
            record = json.loads(line)
            row = {k: v for k, v in record["row"].items() if not k.endswith("_cpu_ms")}
            rows[f"{path.stem}/{record['item']}"] = {
                k: v for k, v in row.items() if k not in TIMING_COLUMNS
            }
    return rows


def _count_runs(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls: list[int] = []
    run = evaluate_module._Runner.run

    def counted(self: Any, episode: int, seed: int) -> dict[str, Any]:
        calls.append(episode)
        return run(self, episode, seed)

    monkeypatch.setattr(evaluate_module._Runner, "run", counted)
    return calls


# -- a full disk ------------------------------------------------------------------------------
def test_a_full_disk_stops_the_table_with_one_line_and_keeps_what_finished(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tmp_path / "table.toml"
    config.write_text(TABLE)
    reference = tmp_path / "reference"
    assert runner.invoke(app, ["table", "-c", str(config), "-o", str(reference)]).exit_code == 0
    out = tmp_path / "out"
    args = ["table", "-c", str(config), "-o", str(out)]
    append = RecordStore._append
    written = [0]

    def fills_up(self: RecordStore, path: Path, data: bytes) -> None:
        if written[0] == 7:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written[0] += 1
        append(self, path, data)

    with monkeypatch.context() as full:
        full.setattr(RecordStore, "_append", fills_up)
        result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"error: cannot store a finished episode in {out / '.records'}/"
        f"{next((out / '.records').glob('*.jsonl')).name}: No space left on device; "
        f"7 finished episodes stored before it kept in {out / '.records'}, rerun the same "
        "command to resume"
    ]
    assert len(_lines(out / ".records")) == 7 and not (out / "tab_p.parquet").exists()
    kept = _stored(out / ".records")  # the finished episodes, whole, as the undisturbed run's
    assert len(kept) == 7 and kept.items() <= _stored(reference / ".records").items()

    # The disk fills up again, now while the tables are written: the episodes are all kept.
    to_parquet = pd.DataFrame.to_parquet

    def no_space(self: pd.DataFrame, path: Any, *args: Any, **kwargs: Any) -> Any:
        if "episode" in self.columns:  # tab_p_episodes, into an open temporary file
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return to_parquet(self, path, *args, **kwargs)

    calls = _count_runs(monkeypatch)
    with monkeypatch.context() as full:
        full.setattr(pd.DataFrame, "to_parquet", no_space)
        result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.stderr.splitlines()[-1] == (
        f"error: No space left on device: {out / 'tab_p_episodes.parquet'}"
    )
    assert len(calls) == 20 - 7
    assert not list(out.glob(".tab_p_episodes*"))  # no temporary file left behind
    assert _stored(out / ".records") == _stored(reference / ".records")  # all 20 kept
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert len(calls) == 20 - 7  # nothing recomputed
    pd.testing.assert_frame_equal(_episodes(out), _episodes(reference), check_exact=True)


# -- solvers that fail -------------------------------------------------------------------------
def test_a_failing_mpc_solver_is_counted_and_the_run_completes(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from codesign_mb.control.daqp_workspace import DaqpWorkspace

    solve = DaqpWorkspace.solve
    calls = [0]

    def every_third_fails(
        self: DaqpWorkspace, *, matrix_changed: bool = False
    ) -> tuple[np.ndarray, int]:
        calls[0] += 1
        x, flag = solve(self, matrix_changed=matrix_changed)
        return (np.full_like(x, np.nan), 1) if calls[0] % 3 == 0 else (x, flag)  # "solved"

    monkeypatch.setattr(DaqpWorkspace, "solve", every_third_fails)
    out = tmp_path / "out"
    args = ["evaluate", "-n", "2", "--max-steps", "15", "-j", "1", "-o", str(out), "--json"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert calls[0] == 30 and summary["mpc_failures"] == 10  # one in three, each counted
    table = pd.read_parquet(out / "evaluate.parquet")
    assert table["mpc_failures"].sum() == 10 and (table["steps"] == 15).all()


def test_non_finite_allocator_solutions_are_counted_as_fallbacks(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from codesign_mb.wifi.convex_qp import OsqpQp

    calls = [0]

    def non_finite(self: OsqpQp) -> tuple[np.ndarray, int, str]:
        calls[0] += 1
        return np.full(self.nv, np.nan), 1, "solved"  # OSQP says solved, returns NaN

    monkeypatch.setattr(OsqpQp, "_run", non_finite)
    out = tmp_path / "out"
    args = ["wifi", "capacity", "--stack", "toy", "--schedulers", "convex", "--channels"]
    args += ["paper", "--robots", "8", "--trials", "1", "--max-steps", "20", "-o", str(out)]
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    trials = pd.read_parquet(out / "fig_wifi.parquet")
    assert calls[0] > 0 and trials["allocator_fallbacks"].sum() == calls[0]
    curves = json.loads(result.stdout)
    assert sum(c["allocator_fallbacks"] for c in curves) == calls[0]


# -- corrupt checkpoints and records ----------------------------------------------------------
def _truncated(source: Path, target: Path, keep: int) -> Path:
    target.write_bytes(source.read_bytes()[:keep])
    return target


def test_corrupt_checkpoints_are_reported_by_name(tmp_path: Path) -> None:
    from codesign_mb.adaptation.learned import LearnedQosPolicy
    from codesign_mb.control.sac import SacController
    from codesign_mb.estimation.learned import load_estimator

    shipped = models_dir() / "checkpoints"
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"garbage")
    truncated_pt = _truncated(shipped / "stage_b" / "mlp.pt", tmp_path / "mlp.pt", 2000)
    truncated_zip = _truncated(shipped / "stage_a" / "model.zip", tmp_path / "model.zip", 3000)
    no_data = tmp_path / "no_data.zip"  # a whole zip without SB3's "data" entry
    with (
        zipfile.ZipFile(shipped / "stage_a" / "model.zip") as src,
        zipfile.ZipFile(no_data, "w") as dst,
    ):
        for name in src.namelist():
            if name != "data":
                dst.writestr(name, src.read(name))
    policy = tmp_path / "qos"
    policy.mkdir()
    (policy / "model.zip").write_bytes((shipped / "stage_c_mpc" / "model.zip").read_bytes())
    (policy / "qos_policy.json").write_text('{"interface": ')
    cases = [
        (load_estimator, garbage, "UnpicklingError", "codesign train b"),
        (load_estimator, truncated_pt, "RuntimeError", "codesign train b"),
        (SacController.load, truncated_zip, "wasn't a zip-file", "codesign train a"),
        (SacController.load, no_data, "No data found", "codesign train a"),
        (LearnedQosPolicy.load, policy, "JSONDecodeError", "codesign train c"),
    ]
    for load, path, why, remedy in cases:
        with pytest.raises(ValueError) as caught:
            load(path)
        message = str(caught.value)
        named = policy / "qos_policy.json" if path == policy else path
        assert message.startswith(f"checkpoint {str(named)!r} is corrupt: "), message
        assert why in message and remedy in message and "\n" not in message


def test_a_corrupt_checkpoint_stops_the_table_with_one_line(
    runner: CliRunner, tmp_path: Path
) -> None:
    garbage = tmp_path / "mlp.pt"
    garbage.write_bytes(b"\x80\x02garbage")
    config = tmp_path / "table.toml"
    config.write_text(
        TABLE.split("[[table.rows]]")[0]
        + f"""
[[table.rows]]
name = "mlp"
controller = {{ kind = "toy_pick" }}
estimator = {{ kind = "mlp", checkpoint = "{garbage}" }}
qos = {{ kind = "static", options = {{ reliability = 1.0, latency_steps = 1 }} }}
"""
    )
    result = runner.invoke(app, ["table", "-c", str(config), "-o", str(tmp_path / "out")])
    assert result.exit_code == 2
    [line] = result.stderr.splitlines()
    assert line.startswith(f"error: checkpoint {str(garbage)!r} is corrupt: ")
    assert "train it again with `codesign train b`" in line


def test_a_corrupt_sweep_trial_is_recomputed_with_a_warning(tmp_path: Path) -> None:
    from codesign_mb.studies.sweep import SweepConfig, run_sweep

    cfg = SweepConfig(n_seeds=2, belt_speeds_mps=(0.2,), params={"horizon_steps": 20})
    first = run_sweep(cfg, tmp_path, backend="serial")
    path = tmp_path / ".records" / "sweep_sweep.jsonl"
    lines = path.read_text().splitlines()
    lines[1] = '{"item": "' + json.loads(lines[1])["item"] + '", "row": '  # torn
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(RuntimeWarning, match=f"record file {path} line 2 is corrupt"):
        again = run_sweep(cfg, tmp_path, backend="serial")
    assert (again.computed, again.reused) == (1, first.n_trials - 1)
    pd.testing.assert_frame_equal(again.table, first.table)


def test_corrupt_bookkeeping_files_are_named_and_not_fatal(tmp_path: Path) -> None:
    """A garbage ``training.json`` beside a checkpoint, or ``study.json`` of a paper study:
    a warning naming the file; the cost counts as unknown, the study as not complete."""
    from codesign_mb.core.registry import ComponentSpec
    from codesign_mb.studies.paper import read_study
    from codesign_mb.studies.table_cost import training_cost
    from codesign_mb.studies.table_rows import TableRow

    (tmp_path / "mlp.pt").write_bytes(b"weights")
    (tmp_path / "training.json").write_text("[1, 2")
    row = TableRow(
        "mlp",
        ComponentSpec("toy_pick"),
        ComponentSpec("mlp", checkpoint=str(tmp_path / "mlp.pt")),
        ComponentSpec("static"),
    )
    with pytest.warns(RuntimeWarning, match=f"{tmp_path / 'training.json'} is corrupt"):
        cost = training_cost(row)
    assert cost.unknown == (str(tmp_path / "mlp.pt"),) and cost.env_steps == 0
    study = tmp_path / "lqg"
    study.mkdir()
    (study / "study.json").write_text("null")
    with pytest.warns(RuntimeWarning, match=f"{study / 'study.json'} is corrupt"):
        assert read_study(study) is None


# -- a results write interrupted --------------------------------------------------------------
_KILLED_WRITE = r"""
import contextlib, os, signal, sys
from pathlib import Path

import pandas as pd

from codesign_mb.core import results

out, victim = Path(sys.argv[1]), sys.argv[2]
atomic_write = results.atomic_write


class HalfThenKilled:
    # The file being written: its first write puts half its bytes on disk, then SIGKILL.
    def __init__(self, fh):
        self.fh = fh

    def write(self, data):
        self.fh.write(data[: max(1, len(data) // 2)])
        self.fh.flush()
        os.fsync(self.fh.fileno())
        os.kill(os.getpid(), signal.SIGKILL)

    def __getattr__(self, name):
        return getattr(self.fh, name)


@contextlib.contextmanager
def killed_during(path, mode="wb"):
    with atomic_write(path, mode) as fh:
        yield HalfThenKilled(fh) if Path(path).name == victim else fh


results.atomic_write = killed_during
table = pd.DataFrame({"x": range(2000), "y": [0.5 * i for i in range(2000)]})
results.write_results(out, table=table, config={"version": 2}, name="t")
"""


def test_a_killed_results_write_leaves_whole_files_and_no_mixed_table(tmp_path: Path) -> None:
    """The writer is killed (``SIGKILL``) with half of a file written, in each of the three
    files of a table (written in order parquet, csv, json): every file on disk is the old whole
    one or the new whole one; the folder lists no table (the old metadata is removed first, so
    never new rows under the old config); the half file, a temporary, is not taken for a
    result; the rerun writes the new table whole."""
    import subprocess
    import sys

    from codesign_mb.core.results import ResultsDir, write_results

    old = pd.DataFrame({"x": range(3), "y": [1.0, 2.0, 3.0]})
    new = pd.DataFrame({"x": range(2000), "y": [0.5 * i for i in range(2000)]})
    read = {"t.parquet": pd.read_parquet, "t.csv": pd.read_csv}
    for killed_in, replaced in (("t.parquet", ()), ("t.csv", ("t.parquet",)),
                                ("t.json", ("t.parquet", "t.csv"))):  # fmt: skip
        out = tmp_path / killed_in
        write_results(out, table=old, config={"version": 1}, name="t")
        assert ResultsDir(out).names == ["t"]
        script = [sys.executable, "-c", _KILLED_WRITE, str(out), killed_in]
        killed = subprocess.run(script, capture_output=True, text=True, timeout=120)
        assert killed.returncode == -signal.SIGKILL, killed.stderr
        for name, reader in read.items():
            pd.testing.assert_frame_equal(reader(out / name), new if name in replaced else old)
        assert not (out / "t.json").exists() and ResultsDir(out).names == []
        [stray] = [p for p in out.iterdir() if p.name not in ("t.parquet", "t.csv")]
        assert stray.name.startswith(f".{killed_in}.") and stray.suffix == ".tmp"  # half
        assert stray.stat().st_size > 0
        assert [p.name for p in out.glob("*.parquet")] == ["t.parquet"]
        assert [p.name for p in out.glob("*.json")] == []
        write_results(out, table=new, config={"version": 2}, name="t")  # the rerun
        assert ResultsDir(out).names == ["t"] and ResultsDir(out).config("t") == {"version": 2}
        for name, reader in read.items():
            pd.testing.assert_frame_equal(reader(out / name), new)


# -- a corrupt record of an evaluation run ----------------------------------------------------
def test_corrupt_episode_records_are_named_recomputed_and_the_table_is_unchanged(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two episode records of ``codesign evaluate`` damaged: one garbled past parsing (bytes
    that are not even UTF-8), one changed so that it still parses (a success turned into a
    failure, caught by its checksum). The rerun names both, recomputes only those two
    episodes and writes the table of the undisturbed run."""
    out = tmp_path / "out"
    args = ["evaluate", "-n", "4", "--max-steps", "15", "-j", "1", "--controller", "scripted"]
    args += ["--estimator", "none", "-o", str(out)]
    assert runner.invoke(app, args).exit_code == 0
    reference = pd.read_parquet(out / "evaluate.parquet")
    [path] = (out / ".records").glob("*.jsonl")
    lines = path.read_bytes().splitlines(keepends=True)
    lines[1] = lines[1][:40] + b"\xff\xfe\x00garbled" + lines[1][60:]
    assert b'"lifted": false' in lines[2]
    lines[2] = lines[2].replace(b'"lifted": false', b'"lifted": true ')  # parses
    path.write_bytes(b"".join(lines))
    calls = _count_runs(monkeypatch)
    with pytest.warns(RuntimeWarning) as caught:
        result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    warned = [str(w.message) for w in caught if "is corrupt" in str(w.message)]
    assert len(warned) == 2, warned
    for line, number, why in zip(warned, (2, 3), ("utf-8", "checksum does not match"), strict=True):
        assert f"record file {path} line {number} is corrupt (" in line, line
        assert why in line and line.endswith("its episode is computed again")
    assert sorted(calls) == [1, 2]  # only those two
    again = pd.read_parquet(out / "evaluate.parquet")
    timing = [c for c in reference if c in TIMING_COLUMNS or c.endswith("_cpu_ms")]
    pd.testing.assert_frame_equal(
        again.drop(columns=timing), reference.drop(columns=timing), check_exact=True
    )
