"""The RU allocators by kind (role ``allocator`` of :mod:`codesign_mb.core.registry`).

================ =========================================================================
kind             what
================ =========================================================================
``greedy``       :class:`~codesign_mb.wifi.allocators.GreedyEdfAllocator` (the paper's, sec. 5)
``greedy-admit`` :class:`~codesign_mb.wifi.allocators.AdmissionGreedyAllocator` (improved greedy)
``convex``       :class:`~codesign_mb.wifi.convex.ConvexAllocator` (OSQP hot path)
``convex-cvxpy`` the same allocator solved through its cvxpy model
``tick-optimal`` :class:`~codesign_mb.wifi.tick_optimal.TickOptimalAllocator` (exact per tick)
================ =========================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.wifi import allocators, config, tick_optimal  # noqa: F401

register(
    "allocator",
    {
        "greedy": Kind("codesign_mb.wifi.config:greedy_allocator"),
        "convex": Kind("codesign_mb.wifi.config:convex_allocator"),
        "convex-cvxpy": Kind("codesign_mb.wifi.config:convex_cvxpy_allocator"),
        "greedy-admit": Kind("codesign_mb.wifi.allocators:admission_greedy_allocator"),
        "tick-optimal": Kind("codesign_mb.wifi.tick_optimal:tick_optimal_allocator"),
    },
)
