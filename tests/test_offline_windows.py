"""[lp] by windows and on the sparse hot path: the same optimum as the monolithic LP and as the
readable cvxpy model, on the shipped instances and on random small traces."""

from __future__ import annotations

import functools
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from codesign_mb.evaluation.pool import imap
from codesign_mb.wifi.cell import generate_trace
from codesign_mb.wifi.offline import build_offline_lp, offline_optimum
from codesign_mb.wifi.offline_reference import reference_optimum
from codesign_mb.wifi.offline_windows import solve_windows, split_windows
from codesign_mb.wifi.presets import CHANNEL_PRESETS
from codesign_mb.wifi.sim import Trace

INSTANCES = sorted(Path(__file__).parent.parent.joinpath("solvers", "instances").glob("*.json"))


def _random_trace(i: int) -> Trace:
    """Trace ``i`` of a seeded family: 2-8 robots, 3-12 steps, q in [0.05, 1], tau 1-2."""
    rng = np.random.default_rng(1000 + i)
    return generate_trace(
        CHANNEL_PRESETS[["paper", "better"][i % 2]],
        int(rng.integers(2, 9)),
        steps=int(rng.integers(3, 13)),
        reliability=float(rng.uniform(0.05, 1.0)),
        latency_steps=int(rng.integers(1, 3)),
        seed=i,
    )


def _close(a: float, b: float, rel: float = 1e-6) -> bool:
    return abs(a - b) <= rel * max(1.0, abs(a), abs(b))


def test_windows_partition_the_frames_and_no_frame_crosses_a_cut():
    for i in range(12):
        trace = _random_trace(i)
        windows = split_windows(trace, min_ticks=1)
        assert windows[0].first_tick == 0 and windows[-1].end_tick == trace.horizon_ticks
        for a, b in itertools.pairwise(windows):
            assert a.end_tick == b.first_tick
        rows = np.concatenate([w.frame_rows for w in windows])
        f = trace.frames
        kept = np.flatnonzero(((f["ul_ok"] != 0) & (f["dl_ok"] != 0)).to_numpy())
        assert sorted(rows.tolist()) == kept.tolist()  # each frame in exactly one window
        for w in windows:
            life = f.iloc[w.frame_rows]
            assert (life["capture_tick"] >= w.first_tick).all()
            assert (np.minimum(life["deadline_tick"], trace.horizon_ticks) <= w.end_tick).all()


def test_decomposed_optimum_is_the_monolithic_one_on_60_random_traces():
    split = 0
    for i in range(60):
        trace = _random_trace(i)
        whole = offline_optimum(trace, solver="highs").optimum
        result = solve_windows(trace, solver="highs", min_ticks=1)
        split += len(result.windows) > 1
        assert _close(result.optimum, whole), (i, result.optimum, whole)
        assert _close(float(result.stations["frames"].sum()), whole)
    assert split >= 30  # most of the family is cut at least once: the test tests a split


@pytest.mark.parametrize("path", INSTANCES, ids=lambda p: p.stem)
def test_decomposed_optimum_is_the_monolithic_one_on_the_shipped_instances(path: Path):
    trace = Trace.load(path)
    whole = offline_optimum(trace, solver="highs").optimum
    assert _close(solve_windows(trace, solver="highs", min_ticks=1).optimum, whole)
    assert _close(offline_optimum(trace, solver="clarabel").optimum, whole)


def test_a_pool_gives_the_same_windows_bit_for_bit():
    trace = generate_trace(CHANNEL_PRESETS["paper"], 12, steps=20, reliability=0.2, seed=3)
    alone = solve_windows(trace, solver="highs", min_ticks=1)
    pooled = solve_windows(
        trace, solver="highs", min_ticks=1, mapper=functools.partial(imap, workers=2)
    )
    assert len(alone.windows) > 3
    assert alone.windows["optimum"].tolist() == pooled.windows["optimum"].tolist()
    assert alone.optimum == pooled.optimum


def test_a_killed_solve_resumes_from_its_journal(tmp_path: Path):
    trace = generate_trace(CHANNEL_PRESETS["paper"], 10, steps=20, reliability=0.2, seed=4)
    journal = tmp_path / "windows.jsonl"
    first = solve_windows(trace, solver="highs", min_ticks=1, journal=journal)
    lines = journal.read_text().splitlines()
    assert len(lines) == len(first.windows) > 3
    # a kill: the last windows never written, one line cut in the middle
    journal.write_text("\n".join(lines[:2]) + "\n" + lines[2][: len(lines[2]) // 2] + "\n")
    again = solve_windows(trace, solver="highs", min_ticks=1, journal=journal)
    assert again.windows["resumed"].tolist()[:2] == [True, True]
    assert not again.windows["resumed"].iloc[2:].any()
    assert again.optimum == first.optimum
    # another trace never reads this one's windows
    other = generate_trace(CHANNEL_PRESETS["paper"], 10, steps=20, reliability=0.2, seed=5)
    assert (
        not solve_windows(other, solver="highs", min_ticks=1, journal=journal)
        .windows["resumed"]
        .any()
    )
    assert all("key" in json.loads(line) for line in journal.read_text().splitlines()[:2])


@pytest.mark.parametrize("i", [0, 1, 2])
def test_sparse_assembly_has_the_readable_models_optimum(i: int):
    trace = _random_trace(100 + i)
    assert _close(offline_optimum(trace, solver="highs").optimum, reference_optimum(trace))


@pytest.mark.slow
@pytest.mark.parametrize("path", INSTANCES, ids=lambda p: p.stem)
def test_sparse_assembly_has_the_readable_models_optimum_on_the_instances(path: Path):
    trace = Trace.load(path)
    assert _close(offline_optimum(trace, solver="highs").optimum, reference_optimum(trace))


def test_only_the_bounds_the_chains_do_not_imply_are_kept_for_the_interior_point():
    lp = build_offline_lp(_random_trace(7))
    assert lp.bounded is not None and np.unique(lp.bounded).size < lp.n_variables / 3


@pytest.mark.slow
def test_ray_gives_the_same_windows_bit_for_bit(tmp_path: Path):
    from codesign_mb.studies.offline_lp import solve_instance

    trace = generate_trace(CHANNEL_PRESETS["paper"], 12, steps=20, reliability=0.2, seed=3)
    path = tmp_path / "t.json"
    trace.save(path)
    local = solve_instance(path, workers=1)
    ray = solve_instance(path, workers=2, backend="ray")
    assert local["windows"] > 1
    assert ray["per_window"] == local["per_window"]
    assert ray["optimum_frames"] == local["optimum_frames"]
