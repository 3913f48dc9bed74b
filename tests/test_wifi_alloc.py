"""RU allocators: valid layouts, convex >= greedy, neither beats the LP, hot path == cvxpy."""

from __future__ import annotations

import math
from functools import cache
from itertools import combinations

import numpy as np
import pytest

from codesign_mb.wifi import (
    ChannelConfig,
    ConvexAllocator,
    ConvexAllocatorConfig,
    GreedyEdfAllocator,
    TickDemand,
    TrafficConfig,
    WifiConfig,
    generate_trace,
    offline_optimum,
    replay,
)
from codesign_mb.wifi.admission import admit_edf, must_serve
from codesign_mb.wifi.allocators import served_bits
from codesign_mb.wifi.engine import ChannelEngine, Frame

CELL = WifiConfig(channel=ChannelConfig(fixed_mcs=1, rician_k_db=math.inf))

# (name, config, robots, reliability, latency, seed): light, at capacity, overloaded, bursts
TRACES = {
    "light": (CELL, 4, 1.0, 1, 0),
    "full": (CELL, 7, 1.0, 1, 1),
    "overload": (CELL, 12, 1.0, 1, 2),
    "sync-burst": (
        WifiConfig(channel=CELL.channel, traffic=TrafficConfig(capture="synchronised")),
        8,
        1.0,
        1,
        3,
    ),
    "tau2": (CELL, 10, 1.0, 2, 4),
    "fading-q05": (
        WifiConfig(channel=ChannelConfig(distance_range_m=(5.0, 40.0))),
        16,
        0.5,
        1,
        5,
    ),
}


@cache
def _trace(name):
    config, robots, q, tau, seed = TRACES[name]
    return generate_trace(config, robots, steps=5, reliability=q, latency_steps=tau, seed=seed)


@cache
def _outcomes(name):
    trace = _trace(name)
    greedy = replay(trace, "greedy", record_layouts=True)
    convex = replay(trace, "convex", record_layouts=True)
    bound = offline_optimum(trace, solver="highs")
    return greedy, convex, bound


def _random_demand(rng, n):
    backlog = rng.uniform(0, 120_000, n) * (rng.random(n) < 0.8)
    head = np.minimum(backlog, rng.uniform(500, 110_000, n))
    slack = rng.integers(1, 40, n).astype(float)
    e = rng.choice([0.5, 1.0, 1.5, 3.0, 5.0], n) * 40
    return TickDemand(backlog, head, slack, e)


@pytest.mark.parametrize("name", sorted(TRACES))
def test_layouts_valid_and_convex_at_least_greedy_and_below_optimum(name):
    greedy, convex, bound = _outcomes(name)
    plan = ru_plan_of(name)
    for result in (greedy, convex):
        assert result.layouts
        for _, _, layout in result.layouts:
            assert plan.is_valid_layout(layout)
    assert convex.delivered >= greedy.delivered
    assert bound.status == "optimal"
    assert greedy.delivered <= bound.optimum + 1e-6
    assert convex.delivered <= bound.optimum + 1e-6


def ru_plan_of(name):
    return TRACES[name][0].phy.plan


def test_offline_solvers_agree():
    trace = _trace("overload")
    highs = offline_optimum(trace, solver="highs").optimum
    clarabel = offline_optimum(trace, solver="clarabel").optimum
    assert clarabel == pytest.approx(highs, rel=1e-5)


def test_offline_bound_is_tight_when_light():
    _, convex, bound = _outcomes("light")
    frames = _trace("light").frames
    deliverable = int(((frames.ul_ok == 1) & (frames.dl_ok == 1)).sum())
    assert bound.optimum == pytest.approx(deliverable)
    assert convex.delivered == deliverable


@pytest.mark.parametrize("bw", [20, 40, 80])
def test_random_demands_give_valid_layouts(bw):
    rng = np.random.default_rng(bw)
    greedy = GreedyEdfAllocator(bw)
    convex = ConvexAllocator(ConvexAllocatorConfig(bandwidth_mhz=bw, n_stations=30))
    for _ in range(30):
        d = _random_demand(rng, 30)
        for alloc in (greedy, convex):
            layout = alloc.allocate(d)
            assert layout.shape == (30,)
            assert alloc.plan.is_valid_layout(layout)
            assert np.all(layout[d.backlog_bits <= 0] == -1)


def test_greedy_gives_minimum_ru_in_deadline_order():
    # two stations, 1.5 bits per subcarrier: 24 subcarriers carry 36 bits per tick
    d = TickDemand(
        backlog_bits=np.array([36.0 * 10, 1e6]),
        head_bits=np.array([36.0 * 10, 1e6]),
        slack_ticks=np.array([10.0, 20.0]),
        bits_per_subcarrier=np.array([1.5, 1.5]),
    )
    layout = GreedyEdfAllocator(40).allocate(d)
    plan = GreedyEdfAllocator(40).plan
    assert plan.units[layout[0]].tones == 26  # just enough to finish in 10 ticks
    assert plan.units[layout[1]].tones == 242  # hopeless: the largest free RU (484 is not)
    assert served_bits(plan, layout, d)[0] * 10 >= 360


@pytest.mark.parametrize("n", [6, 24])
def test_hot_path_equals_cvxpy(n):
    rng = np.random.default_rng(n)
    tight = dict(n_stations=n, eps=1e-7, max_iter=100_000)
    hot = ConvexAllocator(ConvexAllocatorConfig(**tight))
    ref = ConvexAllocator(ConvexAllocatorConfig(**tight, hot_path=False, cvxpy_solver="CLARABEL"))
    assert ref.problem.is_dpp()
    same = 0
    for _ in range(10):
        d = _random_demand(rng, n)
        v, w = hot.solve_hot(d), ref.solve_cvxpy(d)
        k = hot._k
        # served subcarriers (t, z) are what the rounding uses: equal to solver tolerance
        np.testing.assert_allclose(v[n * k :], w[n * k :], atol=2e-3)
        q, _, _, _ = hot._qp_data(d)
        rho = hot.config.regularization
        assert 0.5 * rho * v @ v + q @ v == pytest.approx(0.5 * rho * w @ w + q @ w, abs=1e-5)
        same += bool(np.array_equal(hot.round(v, d), ref.round(w, d)))
    assert same >= 9


def test_replay_is_deterministic():
    trace = _trace("full")
    a = replay(trace, "convex").frames
    b = replay(trace, "convex").frames
    assert a.equals(b)


def test_allocator_config_errors_name_the_field():
    with pytest.raises(ValueError, match="n_stations"):
        ConvexAllocatorConfig(n_stations=0)
    with pytest.raises(ValueError, match="bandwidth_mhz"):
        ConvexAllocatorConfig(bandwidth_mhz=60)
    with pytest.raises(ValueError, match="n_stations=2"):
        ConvexAllocator(ConvexAllocatorConfig(n_stations=2)).allocate(
            _random_demand(np.random.default_rng(0), 3)
        )


def _edf_feasible(work, slack):
    return bool(np.all(np.cumsum(work) <= np.asarray(slack) + 1e-9))


def test_admit_edf_keeps_the_most_frames():
    """Moore-Hodgson: the admitted set is EDF-feasible and as large as any feasible subset."""
    rng = np.random.default_rng(0)
    for _ in range(150):
        n = int(rng.integers(1, 8))
        slack = np.sort(rng.integers(1, 12, n)).astype(float)
        work = rng.uniform(0.2, 5.0, n)
        keep = admit_edf(work, slack)
        assert _edf_feasible(work[keep], slack[keep])
        best = max(
            r
            for r in range(n + 1)
            for c in combinations(range(n), r)
            if _edf_feasible(work[list(c)], slack[list(c)])
        )
        assert keep.sum() == best


def test_admit_edf_weights_protect_valuable_frames():
    work, slack = [2.0, 2.0], [2.0, 3.0]  # only one fits
    assert admit_edf(work, slack).tolist() == [True, False]  # tie: drop the later deadline
    assert admit_edf(work, slack, np.array([1.0, 3.0])).tolist() == [False, True]
    assert admit_edf([3.0], [2.0]).tolist() == [False]  # cannot make it alone


def test_must_serve_keeps_the_admitted_set_feasible():
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(1, 7))
        slack = np.sort(rng.integers(1, 10, n)).astype(float)
        work = rng.uniform(0.1, 4.0, n)
        keep = admit_edf(work, slack)
        work, slack = work[keep], slack[keep]
        must = must_serve(work, slack)
        assert np.all(must >= -1e-12) and np.all(must <= work + 1e-12)
        assert must.sum() <= 1.0 + 1e-9
        later = slack > 1  # serve `must` now: the rest still fits from the next tick on
        assert _edf_feasible((work - must)[later], slack[later] - 1)
        assert np.allclose(must[~later], work[~later])  # due now: all of it


def test_uplink_ppdu_counts_only_the_scheduled_stations():
    """Trigger and multi-STA BlockAck address the stations given an RU, not every queued one."""

    class FirstOnly:
        plan = GreedyEdfAllocator(40).plan

        def allocate(self, demand):
            layout = np.full(demand.n_stations, -1)
            layout[0] = len(self.plan.units) - 1  # the 484-tone RU
            return layout

    engine = ChannelEngine(CELL, 6, FirstOnly(), GreedyEdfAllocator(40))
    frames = [Frame(i, 0, 0, 40, 400_000, 528) for i in range(6)]
    for f in frames:
        engine.add(f)
    engine.run_tick(np.ones(6), np.ones(6))
    mac, phy = CELL.mac, CELL.phy
    # tick 0: a beacon, then a BSRP poll of the 6 stations (52-tone RUs, 7 symbols of QoS Null)
    bsrp = mac.bsrp_exchange_us(6, mac.data_symbols(38, 48, 1.0), phy)
    # the UL TB PPDU gets what the beacon (with its own access) and the poll leave of the tick
    n_sym = mac.ul_data_symbols(1, mac.beacon_us + bsrp, phy)
    assert n_sym > mac.ul_data_symbols(6, mac.beacon_us + bsrp, phy)
    # SERVICE + tail bits, and the dynamic fragment of the MPDU the A-MPDU ends in (38 B)
    assert frames[0].ul_bits - frames[0].ul_left == pytest.approx(468 * n_sym - 22 - 8 * 38)
    assert all(f.ul_left == f.ul_bits for f in frames[1:])
    ul = mac.ul_overhead_us(1, phy) + n_sym * phy.ul_symbol_us
    expected = mac.beacon_us + bsrp + mac.channel_access_us + ul
    assert engine.busy_us == pytest.approx(expected)
    assert mac.tick_us - phy.ul_symbol_us < engine.busy_us <= mac.tick_us


def test_admission_control_keeps_convex_near_the_optimum_under_overload():
    _, convex, bound = _outcomes("overload")
    assert convex.delivered >= 0.8 * bound.optimum
    _, convex, bound = _outcomes("tau2")
    assert convex.delivered >= 0.95 * bound.optimum


def test_convex_admits_the_valuable_frame_when_only_one_fits():
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=2, admission_capacity=1.0))
    e = np.array([1.0, 1.0])
    bits = np.array([468.0 * 3, 468.0 * 3])  # three ticks of the whole band each
    demand = TickDemand(bits, bits, np.array([3.0, 4.0]), e)
    assert alloc.admitted(demand).tolist() == [0]  # tie: the earlier deadline stays
    layout = alloc.allocate(demand)
    assert alloc.plan.units[layout[0]].tones == 484 and layout[1] == -1
    valued = TickDemand(bits, bits, np.array([3.0, 4.0]), e, weights=np.array([1.0, 5.0]))
    assert alloc.admitted(valued).tolist() == [1]
    layout = alloc.allocate(valued)
    assert alloc.plan.units[layout[1]].tones == 484 and layout[0] == -1
