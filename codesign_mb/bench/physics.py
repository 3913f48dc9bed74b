"""The bare-physics ceiling of the benchmarks: record an episode's actuator commands, replay them.

MuJoCo is deterministic, so replaying the ``ctrl`` of every substep of an episode by bare
``mj_step`` calls reproduces its trajectory and contacts: the time of the physics alone, which
the env and closed-loop benchmarks divide by (a ratio that does not depend on the host's speed).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import mujoco
import numpy as np

__all__ = ["recording_controls", "replay_physics"]


@contextmanager
def recording_controls(plant: Any, controls: list[np.ndarray]) -> Iterator[None]:
    """Within the block, the plant runs its Python inner loop and keeps each substep's ``ctrl``.

    The Python loop applies the same torques as the compiled one (``tests/test_robot.py``);
    the compiled path is restored on exit.
    """
    sim = plant.sim
    bare_step = sim._mj_step2  # the second half of each physics step, after the torques
    ctrl = sim.data.ctrl

    def recording_step() -> None:
        controls.append(ctrl.copy())
        bare_step()

    sim.compiled, sim._mj_step2 = False, recording_step
    try:
        yield
    finally:
        sim._mj_step2, sim.compiled = bare_step, True


def replay_physics(plant: Any, seed: int, controls: np.ndarray) -> tuple[float, float]:
    """Bare ``mj_step`` calls on the recorded ``ctrl`` of the episode ``seed``: wall, CPU time."""
    plant.reset(seed=seed)
    m, d = plant.sim.model, plant.sim.data
    ctrl = d.ctrl
    c0, t0 = time.thread_time(), time.perf_counter()
    for u in controls:
        ctrl[:] = u
        mujoco.mj_step(m, d)
    return time.perf_counter() - t0, time.thread_time() - c0
