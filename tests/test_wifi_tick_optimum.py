"""Allocators against the exact per-tick optimum (HiGHS MILP): the gap of the convex allocator's
rounded layout, the tick-optimal programme's exactness, RU-size-aware admission, the improved
greedy."""

from __future__ import annotations

import itertools
import math
from functools import cache

import numpy as np
import pytest

from codesign_mb.bench.allocators import GAP_SEED, gaps_to_tick_milp, random_tick
from codesign_mb.core import registry
from codesign_mb.wifi import (
    ChannelConfig,
    ConvexAllocator,
    ConvexAllocatorConfig,
    GreedyEdfAllocator,
    TickDemand,
    WifiConfig,
    generate_trace,
    make_allocator,
    replay,
    ru_plan,
)
from codesign_mb.wifi.admission import admit_lists, admit_ru_aware, must_serve_lists
from codesign_mb.wifi.allocators import AdmissionGreedyAllocator, RuPacker
from codesign_mb.wifi.tick_dp import TickDp, layout_value, size_values
from codesign_mb.wifi.tick_milp import solve_tick_milp
from codesign_mb.wifi.tick_optimal import TickOptimalAllocator, TickOptimalConfig

CELL = WifiConfig(channel=ChannelConfig(fixed_mcs=1, rician_k_db=math.inf))


@cache
def _gaps(count: int) -> dict[str, np.ndarray]:
    """Relative gap of each allocator's layout to the MILP optimum on ``count`` instances."""
    rng = np.random.default_rng(GAP_SEED)
    gaps: dict[str, list[float]] = {"convex": [], "tick_optimal": []}
    for index in range(count):
        d = random_tick(rng, index)
        n = d.n_stations
        allocs = {
            "convex": ConvexAllocator(ConvexAllocatorConfig(n_stations=n)),
            "tick_optimal": TickOptimalAllocator(TickOptimalConfig(n_stations=n)),
        }
        order, a, b, t_max, z_max = allocs["convex"].tick_objective(d)
        order2, *data2 = allocs["tick_optimal"].tick_objective(d)
        assert np.array_equal(order, order2)  # same admission, same objective
        for x, y in zip((a, b, t_max, z_max), data2, strict=True):
            assert np.array_equal(x, y)
        plan = allocs["convex"].plan
        ref = solve_tick_milp(plan, a, b, t_max, z_max)
        assert plan.is_valid_layout(ref.layout)
        assert layout_value(plan, ref.layout, a, b, t_max, z_max) == pytest.approx(ref.value)
        for name, alloc in allocs.items():
            layout = alloc.allocate(d)
            assert plan.is_valid_layout(layout)
            value = layout_value(plan, layout[order], a, b, t_max, z_max)
            assert value <= ref.value + 1e-9  # the MILP is the optimum
            gaps[name].append((ref.value - value) / ref.value if ref.value > 0 else 0.0)
    return {name: np.array(g) for name, g in gaps.items()}


def _check_gaps(gaps: dict[str, np.ndarray]) -> None:
    convex = gaps["convex"]
    assert np.median(convex) == 0.0
    assert np.percentile(convex, 90) <= 0.02
    assert np.all(gaps["tick_optimal"] <= 1e-9)  # the programme is exact


@pytest.mark.slow
def test_rounded_layout_within_2_percent_of_the_milp_on_100_instances():
    _check_gaps(_gaps(100))


def test_rounded_layout_near_the_milp_small():
    _check_gaps(_gaps(15))


def test_bench_reports_the_gaps_the_test_measures():
    report = gaps_to_tick_milp(6)
    gaps = _gaps(6)
    for name in ("convex", "tick_optimal"):
        assert report[name]["median"] == np.median(gaps[name])
        assert report[name]["max"] == gaps[name].max()


@pytest.mark.parametrize("bw", [20, 40, 80])
def test_programme_equals_the_milp(bw):
    """Random objective data, every bandwidth: the programme's value is HiGHS's optimum."""
    plan = ru_plan(bw)
    dp = TickDp(plan, RuPacker(plan))
    rng = np.random.default_rng(bw)
    for _ in range(8):
        m = int(rng.integers(1, 25))
        a, b = np.ones(m), 0.5 * 0.5 ** np.arange(m)
        t_max = rng.uniform(0, 0.4, m) * (rng.random(m) < 0.6)
        z_max = rng.uniform(0, 1, m)
        sizes, value = dp.solve(size_values(dp.frac_sd, a, b, t_max, z_max))
        layout = [-1] * m
        dp.place(list(range(m)), sizes, layout)
        assert plan.is_valid_layout(layout)
        assert layout_value(plan, np.array(layout), a, b, t_max, z_max) == pytest.approx(value)
        assert value == pytest.approx(solve_tick_milp(plan, a, b, t_max, z_max).value, abs=1e-9)


def _layout_counts(plan) -> set[tuple[int, ...]]:
    """Count vectors (per size) of every set of pairwise disjoint RUs, by enumeration."""
    units = sorted(plan.units, key=lambda u: u.index)
    out: set[tuple[int, ...]] = set()

    def walk(start: int, used: int, counts: list[int]) -> None:
        out.add(tuple(counts))
        for j in range(start, len(units)):
            u = units[j]
            if not used & u.unit_mask:
                k = plan.sizes.index(u.tones)
                counts[k] += 1
                walk(j + 1, used | u.unit_mask, counts)
                counts[k] -= 1

    walk(0, 0, [0] * len(plan.sizes))
    return out


@pytest.mark.parametrize("bw", [20, 40])
def test_fits_matches_every_layout_of_the_plan(bw):
    plan = ru_plan(bw)
    dp = TickDp(plan, RuPacker(plan))
    feasible = _layout_counts(plan)
    box = [range(plan.count(t) + 2) for t in plan.sizes]
    for counts in itertools.product(*box):
        assert dp.fits(counts) == (counts in feasible), counts


def test_admission_asks_only_for_shares_one_layout_serves():
    """RU-size-aware admission: on every instance the must-serve shares ``T`` of the admitted
    frames are served in full by one layout (the MILP maximising must-serve service)."""
    rng = np.random.default_rng(17)
    for index in range(30):
        d = random_tick(rng, index)
        alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=d.n_stations))
        order, a, _, t_max, _ = alloc.tick_objective(d)
        if order.size:
            zero = np.zeros_like(t_max)
            best = solve_tick_milp(alloc.plan, a, zero, t_max, zero).value
            assert best == pytest.approx(t_max.sum(), abs=1e-9)


def test_three_quarter_band_shares_do_not_all_fit():
    """Three frames due now, 0.3 of the band each (sum 0.9 <= c): each needs a 242-tone RU
    and only two exist, so one is rejected; the fluid test alone would admit all three."""
    e = np.full(3, 1.0)
    bits = np.full(3, 0.3 * 468 * 0.95)
    demand = TickDemand(bits, bits, np.ones(3), e)
    alloc = TickOptimalAllocator(TickOptimalConfig(n_stations=3))
    assert alloc.admitted(demand).tolist() == [0, 1]
    layout = alloc.allocate(demand)
    assert [alloc.plan.units[r].tones for r in layout[:2]] == [242, 242] and layout[2] == -1
    fluid = TickOptimalAllocator(TickOptimalConfig(n_stations=3, admission=False))
    assert fluid.admitted(demand).size == 3


def test_improved_greedy_leaves_no_spectrum_idle_and_serves_the_admitted():
    # station 0 needs a 26-tone RU per tick but has a large backlog; station 1 is hopeless
    e = np.full(3, 1.0)
    demand = TickDemand(
        backlog_bits=np.array([24.0 * 40 * 20, 468.0 * 50, 24.0 * 5]),
        head_bits=np.array([24.0 * 40, 468.0 * 50, 24.0 * 5]),
        slack_ticks=np.array([40.0, 2.0, 5.0]),
        bits_per_subcarrier=e,
    )
    paper = GreedyEdfAllocator(40)
    improved = AdmissionGreedyAllocator(40)
    p, q = paper.allocate(demand), improved.allocate(demand)
    assert paper.plan.units[p[1]].tones == 484  # the paper's greedy spends the band on it
    assert p[0] == -1 and p[2] == -1
    assert q[1] == -1 or improved.plan.units[q[1]].tones < 484  # rejected: only what is left
    assert q[0] >= 0 and q[2] >= 0
    # the spectrum left goes to the backlog, deadline order: station 2 (sooner) is served in
    # full, station 0 gets more than the 26-tone RU its head frame needs
    assert improved.plan.units[q[0]].tones > 26


@pytest.mark.parametrize("kind", ["greedy-admit", "tick-optimal"])
def test_new_kinds_are_registered_and_run_a_cell(kind):
    assert kind in registry.kinds("allocator")
    alloc = make_allocator(CELL, 8, kind)
    assert isinstance(alloc, AdmissionGreedyAllocator | TickOptimalAllocator)
    trace = generate_trace(CELL, 12, steps=4, seed=5)
    result = replay(trace, kind, record_layouts=True)
    assert all(trace.config.phy.plan.is_valid_layout(lay) for _, _, lay in result.layouts)
    greedy = replay(trace, "greedy")
    assert result.delivered >= 2 * greedy.delivered  # overload does not collapse them


def test_convex_builds_every_solver_model_up_front():
    alloc = ConvexAllocator(ConvexAllocatorConfig(n_stations=24))
    assert sorted(alloc._models) == alloc._buckets
    ref = ConvexAllocator(ConvexAllocatorConfig(n_stations=4, hot_path=False))
    assert ref._cvx is not None and ref.problem.is_dpp()


def _admission_reference(alloc, work, slack, ratio):
    """``admit_lists``, ``must_serve_lists`` and the RU-size check, in plain Python."""
    c = alloc.config.admission_capacity
    keep = admit_lists(work.tolist(), slack.tolist(), ratio.tolist())
    kept = [j for j, k in enumerate(keep) if k]

    def shares():
        return [c * x for x in must_serve_lists([work[j] for j in kept], [slack[j] for j in kept])]

    def counts(must):
        out = [0] * len(alloc.plan.sizes)
        for x in must:
            if x > 0:
                out[alloc._packer.smallest_size_for(x * alloc._full_sd)] += 1
        return out

    must = shares()
    while not alloc._dp.fits(counts(must)):
        drop = max((q for q, x in enumerate(must) if x > 0), key=lambda q: (ratio[kept[q]], q))
        del kept[drop]
        must = shares()
    out = np.zeros(len(work))
    out[kept] = must
    return np.isin(np.arange(len(work)), kept), out


@pytest.mark.parametrize("bw", [20, 40, 80])
def test_compiled_admission_equals_the_python_reference(bw):
    alloc = TickOptimalAllocator(TickOptimalConfig(bandwidth_mhz=bw, n_stations=30))
    rng = np.random.default_rng(bw)
    dropped = 0  # ticks where the RU-size check rejected a frame the fluid test admitted
    for _ in range(200):
        n = int(rng.integers(1, 30))
        slack = np.sort(rng.integers(1, 10, n)).astype(float)
        work = rng.uniform(0.01, 2.0, n) * rng.choice([0.1, 1.0], n)
        ratio = work / rng.choice([1.0, 3.0], n)
        keep, must = admit_ru_aware(
            work, slack, ratio, admission=True, capacity=0.95, **alloc._admission_args
        )
        ref_keep, ref_must = _admission_reference(alloc, work, slack, ratio)
        assert keep.tolist() == ref_keep.tolist()
        np.testing.assert_allclose(must, ref_must, atol=1e-12)
        dropped += sum(admit_lists(work.tolist(), slack.tolist(), ratio.tolist())) > keep.sum()
    assert dropped >= 10


@pytest.mark.parametrize("bw", [20, 40, 80])
def test_grow_keeps_the_layout_valid_and_never_shrinks_an_ru(bw):
    plan = ru_plan(bw)
    packer = RuPacker(plan)
    sd = [u.data_subcarriers for u in plan.units]
    rng = np.random.default_rng(bw)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        lay, used = [-1] * n, 0
        for i in range(n):  # a random valid start
            r = packer.place(int(rng.integers(0, len(plan.sizes) - 1)), used)
            if r >= 0 and rng.random() < 0.7:
                lay[i], used = r, used | packer.mask[r]
        before = list(lay)
        need = rng.uniform(0, 600, n).tolist()
        used = packer.grow(lay, used, need, list(range(n)))
        assert plan.is_valid_layout(lay)
        assert used == sum(packer.mask[r] for r in lay if r >= 0)
        for i in range(n):
            if before[i] >= 0:
                assert sd[lay[i]] >= sd[before[i]]
                # it grew as far as the spectrum left free allows (its own RU included)
                free = used & ~packer.mask[lay[i]]
                best = packer.place_at_most(packer.sizes_for(np.array([need[i]]))[0], free)
                assert sd[lay[i]] >= min(sd[best], need[i])
