"""The offline allocation LP on a stored instance, and the online allocators' gap to it.

What ``codesign solve`` prints: the optimum of :func:`~codesign_mb.wifi.offline.offline_optimum`
(the most frames any scheduler delivers in time on the trace) and, optionally, what the greedy
and convex allocators deliver when replayed on the same trace.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from codesign_mb.wifi.offline import offline_optimum
from codesign_mb.wifi.sim import Trace, replay

__all__ = ["solve_instance"]


def solve_instance(path: str | Path, *, solver: str = "highs", compare: bool = False) -> dict:
    """Solve the instance at ``path``; with ``compare``, the allocators' frames and gaps."""
    trace = Trace.load(path)
    result = offline_optimum(trace, solver=solver)
    record: dict[str, Any] = {
        "instance": str(path),
        "optimum_frames": result.optimum,
        "solver": result.solver,
        "solve_time_s": result.solve_time_s,
        "status": result.status,
        "frames_admitted": result.n_frames_admitted,
        "frames_deliverable": result.n_frames,
        "variables": result.n_variables,
        "constraints": result.n_constraints,
    }
    if compare:
        for name in ("greedy", "convex"):
            replayed = replay(trace, name)
            delivered = replayed.delivered
            record[f"{name}_frames"] = delivered
            record[f"{name}_solver_fallbacks"] = replayed.fallbacks.total
            record[f"{name}_gap"] = (
                (result.optimum - delivered) / result.optimum if result.optimum > 0 else 0.0
            )
    return record
