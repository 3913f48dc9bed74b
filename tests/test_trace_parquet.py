"""Parquet traces: the same trace as JSON bit for bit, read by window, solved by window to the
in-memory optimum bit for bit, and a broken file is one line through the CLI."""

from __future__ import annotations

import json
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.studies.offline_lp import solve_instance
from codesign_mb.wifi.cell import generate_trace
from codesign_mb.wifi.offline_windows import solve_windows
from codesign_mb.wifi.presets import CHANNEL_PRESETS
from codesign_mb.wifi.sim import Trace
from codesign_mb.wifi.trace_parquet import ParquetTrace, TraceWriter, save_parquet

INSTANCES = sorted(Path(__file__).parent.parent.joinpath("solvers", "instances").glob("*.json"))
runner = CliRunner()


def _same(a: Trace, b: Trace) -> None:
    """Bit for bit: channel bytes, frame table (values, dtypes, order), config, horizon."""
    assert a.horizon_ticks == b.horizon_ticks and a.config == b.config
    for x, y in ((a.ul_bpss, b.ul_bpss), (a.dl_bpss, b.dl_bpss)):
        assert x.shape == y.shape and x.tobytes() == np.ascontiguousarray(y).tobytes()
    pd.testing.assert_frame_equal(a.frames, b.frames, check_exact=True)


@pytest.fixture(scope="module")
def windowed() -> Trace:
    """12 robots asking for 20 % of their packets: cut into several windows."""
    return generate_trace(CHANNEL_PRESETS["paper"], 12, steps=20, reliability=0.2, seed=3)


def test_parquet_round_trip_is_bit_exact(tmp_path: Path):
    trace = generate_trace(CHANNEL_PRESETS["better"], 5, steps=12, reliability=0.3, seed=1)
    path = tmp_path / "t.parquet"
    save_parquet(trace, path, ticks_per_group=37)  # groups that do not divide the horizon
    _same(trace, Trace.load(path))
    groups = pq.ParquetFile(path).metadata.num_row_groups
    assert groups == math.ceil(trace.horizon_ticks / 37) + 1  # ticks in blocks, frames apart


@pytest.mark.parametrize("path", INSTANCES, ids=lambda p: p.stem)
def test_json_to_parquet_to_json_is_the_same_file(path: Path, tmp_path: Path):
    original = Trace.load(path)
    original.save(tmp_path / "t.parquet")  # the suffix picks the format
    back = Trace.load(tmp_path / "t.parquet")
    _same(original, back)
    back.save(tmp_path / "t.json")
    assert (tmp_path / "t.json").read_text() == json.dumps(original.to_json()) + "\n"


def test_channel_reads_only_the_row_groups_of_its_ticks(
    windowed: Trace, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    path = tmp_path / "t.parquet"
    save_parquet(windowed, path, ticks_per_group=50)
    source = ParquetTrace.open(path)
    asked: list[list[int]] = []
    real = pq.ParquetFile.read_row_groups
    monkeypatch.setattr(
        pq.ParquetFile,
        "read_row_groups",
        lambda self, groups, **kw: asked.append(list(groups)) or real(self, groups, **kw),
    )
    rng = np.random.default_rng(0)
    for _ in range(20):
        lo = int(rng.integers(0, windowed.horizon_ticks - 1))
        hi = int(rng.integers(lo + 1, min(lo + 130, windowed.horizon_ticks) + 1))
        ul, dl = source.channel(lo, hi)
        assert ul.tobytes() == np.ascontiguousarray(windowed.ul_bpss[:, lo:hi]).tobytes()
        assert dl.tobytes() == np.ascontiguousarray(windowed.dl_bpss[:, lo:hi]).tobytes()
        wanted = [source.header.channel_groups[g] for g in range(lo // 50, (hi - 1) // 50 + 1)]
        assert asked.pop() == wanted


def test_streamed_solve_is_the_in_memory_solve_bit_for_bit(
    windowed: Trace, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    path = tmp_path / "t.parquet"
    save_parquet(windowed, path, ticks_per_group=64)
    source = ParquetTrace.open(path)
    ranges: list[tuple[int, int]] = []
    real = ParquetTrace.channel
    monkeypatch.setattr(
        ParquetTrace, "channel", lambda self, a, b: ranges.append((a, b)) or real(self, a, b)
    )
    alone = solve_windows(windowed, solver="highs", min_ticks=1)
    streamed = solve_windows(source, solver="highs", min_ticks=1)
    assert len(alone.windows) > 3
    assert streamed.optimum == alone.optimum
    for column in ("first_tick", "end_tick", "frames", "variables", "constraints", "optimum"):
        assert streamed.windows[column].tolist() == alone.windows[column].tolist()
    assert streamed.stations["frames"].tolist() == alone.stations["frames"].tolist()
    # each window read alone, none the whole horizon
    assert ranges == list(zip(alone.windows["first_tick"], alone.windows["end_tick"], strict=True))


def test_a_journal_is_keyed_by_the_trace_not_its_format(windowed: Trace, tmp_path: Path):
    path, journal = tmp_path / "t.parquet", tmp_path / "w.jsonl"
    save_parquet(windowed, path)
    alone = solve_windows(windowed, solver="highs", min_ticks=1, journal=journal)
    resumed = solve_windows(ParquetTrace.open(path), solver="highs", min_ticks=1, journal=journal)
    assert resumed.windows["resumed"].all() and resumed.optimum == alone.optimum


def test_solve_instance_of_parquet_equals_the_json_path(windowed: Trace, tmp_path: Path):
    windowed.save(tmp_path / "t.json")
    Trace.load(tmp_path / "t.json").save(tmp_path / "t.parquet")  # the same (rounded) trace
    a = solve_instance(tmp_path / "t.json", solver="highs")
    b = solve_instance(tmp_path / "t.parquet", solver="highs")
    keys = ("optimum_frames", "per_window", "per_robot", "variables", "frames_admitted")
    assert {k: a[k] for k in keys} == {k: b[k] for k in keys}


def test_a_pickled_source_leaves_its_frames_behind(windowed: Trace, tmp_path: Path):
    path = tmp_path / "t.parquet"
    save_parquet(windowed, path)
    source = ParquetTrace.open(path)
    copy = pickle.loads(pickle.dumps(source))
    assert copy.frames is None and len(pickle.dumps(source)) < 10_000
    assert copy.channel(5, 77)[0].tobytes() == source.channel(5, 77)[0].tobytes()


def test_wifi_trace_records_parquet_that_solve_reads(tmp_path: Path):
    out = tmp_path / "t.parquet"
    argv = ["wifi", "trace", str(out), "--robots", "3", "--steps", "4", "-q", "0.5"]
    r = runner.invoke(app, [*argv, "--seed", "2", "--json"])
    assert r.exit_code == 0, r.output
    expected = generate_trace(CHANNEL_PRESETS["paper"], 3, steps=4, reliability=0.5, seed=2)
    _same(expected, Trace.load(out))
    r = runner.invoke(app, ["solve", str(out), "--solver", "highs", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["optimum_frames"] == solve_windows(expected, solver="highs").optimum


def _write(path: Path, trace: Trace, *, ul: Any = None, frames: Any = None) -> None:
    """``trace`` written with its channel or frames replaced (the writer checks no value)."""
    with TraceWriter(path, trace.config, trace.n_stations, trace.horizon_ticks) as writer:
        writer.add_ticks(trace.ul_bpss if ul is None else ul, trace.dl_bpss)
        writer.add_frames(trace.frames if frames is None else frames)


def _rewrite_header(path: Path, **changes: Any) -> None:
    """Rewrite the file, its row groups as they are, with the header's fields changed."""
    pf = pq.ParquetFile(path)
    header = {**json.loads(pf.metadata.metadata[b"codesign"]), **changes}
    tables = [pf.read_row_group(i) for i in range(pf.metadata.num_row_groups)]
    with pq.ParquetWriter(path, pf.schema_arrow) as writer:
        for table in tables:
            writer.write_table(table)
        writer.add_key_value_metadata({"codesign": json.dumps(header)})


def _broken(kind: str, trace: Trace, path: Path) -> None:
    f = trace.frames
    if kind == "not parquet":
        path.write_bytes(b"PAR1 this is not a Parquet file")
    elif kind == "truncated":
        save_parquet(trace, path)
        path.write_bytes(path.read_bytes()[:-100])
    elif kind == "no header":
        f.to_parquet(path)
    elif kind == "nan":
        ul = trace.ul_bpss.copy()
        ul[1, 7] = np.nan
        _write(path, trace, ul=ul)
    elif kind == "negative":
        _write(path, trace, ul=-trace.ul_bpss)
    elif kind == "station":
        _write(path, trace, frames=f.assign(station=f["station"].where(f.index != 2, 99)))
    elif kind == "deadline":
        _write(path, trace, frames=f.assign(deadline_tick=f["capture_tick"]))
    elif kind == "horizon":
        _write(path, trace, frames=f.assign(deadline_tick=f["deadline_tick"] + 10**6))
    elif kind == "format":
        save_parquet(trace, path)
        _rewrite_header(path, format="codesign-wifi-trace/1")
    else:  # a header announcing one tick more than the row groups hold
        save_parquet(trace, path)
        _rewrite_header(path, horizon_ticks=trace.horizon_ticks + 1)


BROKEN = {
    "not parquet": "not a readable Parquet trace",
    "truncated": "not a readable Parquet trace",
    "no header": "metadata 'codesign'",
    "nan": "ul_bpss must be finite, got nan at station 1, tick 7",
    "negative": "ul_bpss must be >= 0",
    "station": "frames.station must be <= 2, got 99",
    "deadline": "frames.deadline_tick - capture_tick",
    "horizon": "frames.deadline_tick must be <= 160",
    "format": "format must be 'codesign-wifi-trace-parquet/1'",
    "groups": "row group",
}


@pytest.mark.parametrize("kind", sorted(BROKEN))
@pytest.mark.parametrize("how", ["streamed", "whole"])
def test_a_broken_parquet_file_is_one_line_exit_2(kind: str, how: str, tmp_path: Path):
    trace = generate_trace(CHANNEL_PRESETS["paper"], 3, steps=3, seed=0)
    path = tmp_path / "broken.parquet"
    _broken(kind, trace, path)
    extra = ["--compare"] if how == "whole" else []
    result = runner.invoke(app, ["solve", str(path), "--json", *extra])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert BROKEN[kind] in lines[0] and str(path) in lines[0], lines[0]
