"""The phases of a conveyor episode, from the true state: where an estimation error matters.

:func:`episode_phase` labels a step from what the env
(:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`) knows and reports in ``info``
(``info["phase"]``, an index into :data:`PHASES`):

``belt`` (0)
    The object is free (riding the belt; after a drop, wherever it lies) and the gripper is
    outside the grasp window.
``grasp`` (1)
    Descending and grasping: the object is free and the gripper is in the *grasp window*,
    within :data:`GRASP_WINDOW_RADIUS_M` of the object's centre horizontally and at most
    :data:`GRASP_WINDOW_HEIGHT_M` above it.
``carried`` (2)
    The object is in the fingers (both touch it) or lifted (its centre at least the success
    test's lift height above its rest on the belt).

Before the object spawned there is no object and no phase: :data:`NOT_SPAWNED` (-1).
"""

from __future__ import annotations

import math

from numpy.typing import NDArray

__all__ = [
    "GRASP_WINDOW_HEIGHT_M",
    "GRASP_WINDOW_RADIUS_M",
    "NOT_SPAWNED",
    "PHASES",
    "episode_phase",
]

PHASES = ("belt", "grasp", "carried")
"""The phases, in order; :func:`episode_phase` returns an index into this tuple."""

NOT_SPAWNED = -1
"""The label of a step before the object spawned (no phase)."""

GRASP_WINDOW_RADIUS_M = 0.04
"""Horizontal reach of the grasp window (m): half the open finger span (8 cm); farther, the
object cannot be between the fingers."""

GRASP_WINDOW_HEIGHT_M = 0.05
"""Height of the grasp window above the object's centre (m): below the 6 cm above the grasp
point where the MPC and the scripted controller hover before they descend, so inside the
window the descent has begun."""


def episode_phase(
    object_pos: NDArray, gripper_pos: NDArray, *, grasped: bool, lifted: bool, spawned: bool
) -> int:
    """The phase of a step (an index into :data:`PHASES`, or :data:`NOT_SPAWNED`).

    ``object_pos`` is the object's true centre and ``gripper_pos`` the TCP (m, world frame);
    ``grasped``: both fingers touch the object; ``lifted``: its centre is at least the lift
    height above its rest; ``spawned``: the object is on the scene.
    """
    if not spawned:
        return NOT_SPAWNED
    if grasped or lifted:
        return 2
    ox, oy, oz = object_pos.tolist()
    gx, gy, gz = gripper_pos.tolist()
    if gz - oz <= GRASP_WINDOW_HEIGHT_M and math.hypot(gx - ox, gy - oy) <= GRASP_WINDOW_RADIUS_M:
        return 1
    return 0
