"""Recording a trace as it goes (issue 31): the streamed recording is the in-memory one bit for
bit whatever the chunks, and both are what the lockstep cell draws when robots drive it through
its links; ``codesign wifi trace OUT.parquet`` writes as it records; JSON keeps its cap."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app
from codesign_mb.core.config import ConfigError
from codesign_mb.network.qos import QosRequest
from codesign_mb.studies import offline_lp
from codesign_mb.studies.offline_lp import write_trace
from codesign_mb.wifi.cell import SharedChannel, generate_trace, record_trace
from codesign_mb.wifi.presets import CHANNEL_PRESETS
from codesign_mb.wifi.sim import TRACE_CELLS_CAP, Trace
from codesign_mb.wifi.trace_parquet import TraceWriter

runner = CliRunner()

CASES = [  # cell, robots, steps, q, tau, seed
    ("paper", 5, 12, 0.3, 1, 1),
    ("better", 7, 9, 0.6, 2, 4),
    ("better", 3, 5, 1.0, 3, 7),
    ("paper", 12, 20, 0.2, 1, 3),
]


def _joined(chunks: list) -> Trace:
    """Chunks end to end, checking they are consecutive."""
    first = 0
    for c in chunks:
        assert c.first_tick == first
        first += c.ul_bpss.shape[1]
    return Trace(
        config=CHANNEL_PRESETS["paper"],
        horizon_ticks=first,
        ul_bpss=np.concatenate([c.ul_bpss for c in chunks], axis=1),
        dl_bpss=np.concatenate([c.dl_bpss for c in chunks], axis=1),
        frames=pd.concat([c.frames for c in chunks], ignore_index=True),
    )


def _same(a: Trace, b: Trace) -> None:
    assert a.horizon_ticks == b.horizon_ticks
    for x, y in ((a.ul_bpss, b.ul_bpss), (a.dl_bpss, b.dl_bpss)):
        assert x.shape == y.shape and x.tobytes() == np.ascontiguousarray(y).tobytes()
    pd.testing.assert_frame_equal(a.frames, b.frames, check_exact=True)


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}robots-q{c[3]}-tau{c[4]}")
@pytest.mark.parametrize("chunk_steps", [1, 2, 7, 1000])
def test_streamed_recording_is_the_in_memory_one_bit_for_bit(case, chunk_steps):
    cell, n, steps, q, tau, seed = case
    config = CHANNEL_PRESETS[cell]
    whole = generate_trace(config, n, steps=steps, reliability=q, latency_steps=tau, seed=seed)
    chunks = list(
        record_trace(
            config,
            n,
            steps=steps,
            reliability=q,
            latency_steps=tau,
            seed=seed,
            chunk_steps=chunk_steps,
        )
    )
    assert len(chunks) == -(-steps // chunk_steps) + 1  # the steps' chunks, then the tail
    _same(_joined(chunks), whole)
    period = config.traffic.period_ticks(config.mac.tick_us)
    for c in chunks[:-1]:  # a chunk holds its steps' ticks: memory bounded by chunk_steps
        assert c.ul_bpss.shape[1] <= chunk_steps * period


@pytest.mark.parametrize("case", CASES[:3], ids=lambda c: f"{c[0]}-{c[1]}robots")
def test_the_recording_is_what_the_cell_draws_when_robots_drive_it(case):
    """Independent of the recorder's loop: the robots step their links in ``step_order`` with
    static QoS on a cell that really schedules (greedy); the frames it admits and the channel
    it sees are the recording's (the schedule draws no randomness)."""
    cell, n, steps, q, tau, seed = case
    config = CHANNEL_PRESETS[cell]
    channel = SharedChannel(config, n, seed=seed, scheduler="greedy")
    for link in channel.links:
        link.reset(prior=[0.0])
    for _ in range(steps):
        for i in channel.step_order:
            channel.links[i].step([0.0], QosRequest(q, tau))
    driven = channel.trace()
    recorded = _joined(
        list(
            record_trace(
                config, n, steps=steps, reliability=q, latency_steps=tau, seed=seed, chunk_steps=3
            )
        )
    )
    pd.testing.assert_frame_equal(driven.frames, recorded.frames, check_exact=True)
    h = driven.horizon_ticks
    assert 0 < h < recorded.horizon_ticks
    assert driven.ul_bpss.tobytes() == np.ascontiguousarray(recorded.ul_bpss[:, :h]).tobytes()
    assert driven.dl_bpss.tobytes() == np.ascontiguousarray(recorded.dl_bpss[:, :h]).tobytes()


def test_wifi_trace_writes_parquet_as_it_records(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Row groups are on disk before the recording ends, the in-memory recorder is never
    called, and the file is the in-memory trace bit for bit."""
    monkeypatch.setattr(offline_lp, "CHUNK_STEPS", 10)
    monkeypatch.setattr(offline_lp, "join_chunks", None)  # would fail if called
    written_before: list[int] = []
    real = TraceWriter.add_ticks

    def add_ticks(self: TraceWriter, ul: np.ndarray, dl: np.ndarray) -> None:
        written_before.append(self._ticks)
        assert ul.shape[1] <= 10 * 40
        real(self, ul, dl)

    monkeypatch.setattr(TraceWriter, "add_ticks", add_ticks)
    out = tmp_path / "t.parquet"
    argv = ["wifi", "trace", str(out), "--robots", "4", "--steps", "60", "-q", "0.4"]
    r = runner.invoke(app, [*argv, "--seed", "5", "--json"])
    assert r.exit_code == 0, r.output
    assert len(written_before) == 7 and written_before[-1] >= 2000  # a row group of 2,000 ticks
    expected = generate_trace(CHANNEL_PRESETS["paper"], 4, steps=60, reliability=0.4, seed=5)
    _same(Trace.load(out), expected)


def test_write_trace_reports_what_it_wrote(tmp_path: Path):
    for suffix in (".parquet", ".json"):
        got = write_trace(tmp_path / f"t{suffix}", robots=3, steps=6, reliability=0.5, seed=1)
        trace = Trace.load(got.path)
        assert (got.n_stations, got.horizon_ticks) == (3, trace.horizon_ticks)
        assert got.frames == len(trace.frames)


def test_a_json_trace_over_the_cap_is_one_line_pointing_to_parquet(tmp_path: Path):
    out = tmp_path / "hour.json"
    argv = ["wifi", "trace", str(out), "--robots", "48", "--steps", "90000", "-q", "0.1"]
    r = runner.invoke(app, argv)
    assert r.exit_code == 2, r.output
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert str(TRACE_CELLS_CAP.value) in lines[0] and "hour.parquet" in lines[0]
    assert not out.exists()


def test_the_in_memory_recorder_keeps_its_cap():
    with pytest.raises(ConfigError, match="robots x ticks of the trace must be <= 4000000"):
        generate_trace(CHANNEL_PRESETS["paper"], 48, steps=90_000, reliability=0.1)
    with pytest.raises(ConfigError, match="chunk_steps must be >= 1"):
        next(record_trace(CHANNEL_PRESETS["paper"], 2, steps=3, chunk_steps=0))
