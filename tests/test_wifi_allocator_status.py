"""Solver failures of the convex allocator: checked, fallen back from, counted, reported."""

from __future__ import annotations

import math

import cvxpy as cp
import numpy as np
import pytest

from codesign_mb.network import QosRequest
from codesign_mb.wifi import (
    ChannelConfig,
    ConvexAllocator,
    ConvexAllocatorConfig,
    SharedChannel,
    TickDemand,
    TrafficConfig,
    WifiConfig,
    generate_trace,
    replay,
)
from codesign_mb.wifi.convex_qp import OsqpQp

CELL = WifiConfig(
    channel=ChannelConfig(fixed_mcs=1, rician_k_db=math.inf),
    traffic=TrafficConfig(capture="synchronised"),
)


def _demands(n: int, count: int, seed: int) -> list[TickDemand]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        backlog = rng.uniform(2_000, 120_000, n)
        head = np.minimum(backlog, rng.uniform(500, 110_000, n))
        slack = rng.integers(1, 40, n).astype(float)
        e = rng.choice([0.5, 1.0, 1.5, 3.0, 5.0], n) * 40
        out.append(TickDemand(backlog, head, slack, e))
    return out


def _fail_with(status_val: int, status: str, x: float):
    """An ``OsqpQp._run`` that reports ``status`` and an iterate of all ``x``."""

    def run(self: OsqpQp) -> tuple[np.ndarray, int, str]:
        return np.full(self.nv, x), status_val, status

    return run


@pytest.mark.parametrize(
    ("status_val", "status", "x", "reason"),
    [
        (11, "unsolved", 0.0, "osqp status 'unsolved'"),  # failed status, finite iterate
        (1, "solved", math.nan, "non-finite"),  # "solved" but not finite
    ],
)
def test_osqp_failure_falls_back_counted_and_feasible(monkeypatch, status_val, status, x, reason):
    monkeypatch.setattr(OsqpQp, "_run", _fail_with(status_val, status, x))
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=12))
    solved = 0
    for d in _demands(12, 20, seed=3):
        layout = alloc.allocate(d)
        assert alloc.plan.is_valid_layout(layout)
        assert np.all(layout[d.backlog_bits <= 0] == -1)
        # the explicit fallback: the tick rounded from zero relaxed service
        assert np.array_equal(layout, alloc.round(np.zeros(12 * alloc._k + 24), d))
        solved += alloc.admitted(d).size >= 2  # one admitted station needs no solve
    assert solved > 0
    assert alloc.fallbacks == solved
    assert reason in (alloc.last_fallback_reason or "")


def test_osqp_failure_does_not_poison_later_solves():
    """A non-finite OSQP solution is reported, and the workspace solves the next tick again."""
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=4))
    model = OsqpQp(4, alloc._shape, eps=1e-2, max_iter=200)
    a, b = np.array([1.0, 1.0]), np.array([0.5, 0.25])
    t_max, z_max = np.array([0.3, 0.3]), np.array([0.2, 0.2])
    reference = model.solve(a, b, t_max, z_max)
    assert reference is not None and model.last_status == "solved"
    reference = reference.copy()
    assert model.solve(np.array([math.nan, 1.0]), b, t_max, z_max) is None  # a real failure
    assert "non-finite" in model.last_status
    again = model.solve(a, b, t_max, z_max)
    assert again is not None and model.last_status == "solved"
    np.testing.assert_allclose(again, reference, atol=1e-3)


def test_healthy_solves_count_no_fallback():
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=12))
    for d in _demands(12, 20, seed=4):
        alloc.allocate(d)
    assert alloc.fallbacks == 0 and alloc.last_fallback_reason is None


def test_cvxpy_failure_falls_back_counted(monkeypatch):
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=6, hot_path=False))
    d = _demands(6, 1, seed=5)[0]
    healthy = alloc.allocate(d)
    assert alloc.fallbacks == 0

    def raise_solver_error(*args: object, **kwargs: object) -> None:
        raise cp.error.SolverError("forced")

    monkeypatch.setattr(alloc.problem, "solve", raise_solver_error)
    layout = alloc.allocate(d)
    assert alloc.fallbacks == 1 and "SolverError" in (alloc.last_fallback_reason or "")
    assert alloc.plan.is_valid_layout(layout)
    assert np.array_equal(layout, alloc.round(np.zeros(6 * alloc._k + 12), d))
    monkeypatch.undo()
    assert np.array_equal(alloc.allocate(d), healthy)  # solved again, cold-started
    assert alloc.fallbacks == 1


def test_fallbacks_reach_replay_results(monkeypatch):
    trace = generate_trace(CELL, 8, steps=3, seed=0)
    healthy = replay(trace, "convex", record_layouts=True)
    assert healthy.fallbacks.total == 0
    monkeypatch.setattr(OsqpQp, "_run", _fail_with(11, "unsolved", 0.0))
    failed = replay(trace, "convex", record_layouts=True)
    assert failed.fallbacks.ul > 0
    assert failed.fallbacks.total == failed.fallbacks.ul + failed.fallbacks.dl
    assert "unsolved" in (failed.fallbacks.ul_reason or "")
    assert failed.layouts
    assert all(trace.config.phy.plan.is_valid_layout(lay) for _, _, lay in failed.layouts)
    assert replay(trace, "greedy").fallbacks.total == 0


def test_fallbacks_reach_the_shared_channel(monkeypatch):
    monkeypatch.setattr(OsqpQp, "_run", _fail_with(11, "unsolved", 0.0))
    channels = {}
    for scheduler in ("convex", "greedy"):
        channel = SharedChannel(CELL, 8, seed=0, scheduler=scheduler)
        for link in channel.links:
            link.reset(prior=[0.0])
        for t in range(4):
            for i in channel.step_order:
                channel.links[i].step([float(t)], QosRequest(1.0, 1))
        channels[scheduler] = channel
    convex = channels["convex"].fallbacks
    assert convex.total > 0 and "unsolved" in (convex.ul_reason or "")
    assert channels["greedy"].fallbacks.total == 0
    channels["convex"].reset(seed=1)  # a new episode counts from zero
    assert channels["convex"].fallbacks.total == 0
