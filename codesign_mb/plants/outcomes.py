"""Why a conveyor episode failed: the events a pick can go wrong with, latched per episode.

The env (:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`) reports in ``info``, from
the step they first happen on:

``missed_grasp``
    The fingers were closed on nothing: gripper closed, no finger touching the object, and the
    fingers nearer than half the object's width.
``dropped``
    The object was lifted (``lift_height_m`` above its resting height) and later, out of the
    fingers, was back below that height.
``off_belt``
    The object, not in the fingers, left the belt (beyond its sides or end, or below its
    surface) or passed the downstream end of the gripper's workspace (out of reach).
``time_to_grasp_s``
    When both fingers first touched the object (s from the episode start); -1 before (not
    NaN, so that two infos of the same seed compare equal, as Gymnasium's checker wants).

:func:`failure_reason` turns them into one reason per failed episode, in the order of
:data:`FAILURE_REASONS`: the first event that applies, else ``timeout`` (the horizon came
first). A success has no reason (``None``).
"""

from __future__ import annotations

from numpy.typing import NDArray

from codesign_mb.robot.scene import BELT_HALF_LENGTH, BELT_HALF_WIDTH, BELT_SURFACE_Z, BELT_X

__all__ = ["FAILURE_REASONS", "OutcomeTracker", "failure_reason"]

FAILURE_REASONS = ("dropped", "missed_grasp", "off_belt", "timeout")
"""Failure reasons, in the order :func:`failure_reason` tests them."""


def failure_reason(
    success: bool, *, missed_grasp: bool, dropped: bool, off_belt: bool
) -> str | None:
    """The reason a finished episode failed (``None`` for a success).

    ``dropped`` before ``missed_grasp`` before ``off_belt``: an object that was lifted and
    lost failed at the carry whatever came before; a missed grasp explains an object that then
    ran out of reach; ``timeout`` is left for an episode where none of them happened.
    """
    if success:
        return None
    for reason, happened in zip(
        FAILURE_REASONS[:3], (dropped, missed_grasp, off_belt), strict=True
    ):
        if happened:
            return reason
    return "timeout"


class OutcomeTracker:
    """Latches the events of :data:`FAILURE_REASONS` and the time to grasp over one episode.

    Parameters
    ----------
    object_half_width_m:
        Half the object's width between the fingers (m): fingers nearer than this, touching
        nothing, have closed on nothing.
    lift_height_m:
        The lift of the success test (m).
    reach_y_m:
        Downstream end of the gripper's workspace (m, along y); an object beyond it by more
        than its half width is out of reach.
    control_period_s:
        Seconds per step.
    """

    def __init__(
        self,
        object_half_width_m: float,
        lift_height_m: float,
        reach_y_m: float,
        control_period_s: float,
    ) -> None:
        self.half_width = float(object_half_width_m)
        self.lift_height = float(lift_height_m)
        self.reach_y = float(reach_y_m) + self.half_width
        self.period = float(control_period_s)
        self.reset()

    def reset(self) -> None:
        """Start an episode: nothing happened yet."""
        self.missed_grasp = False
        self.dropped = False
        self.off_belt = False
        self.time_to_grasp_s = -1.0
        self._was_lifted = False

    def update(
        self,
        t: int,
        *,
        object_pos: NDArray,
        rise: float,
        touched: bool,
        grasped: bool,
        closed: bool,
        finger_width: float,
    ) -> None:
        """Record step ``t``: the object's centre (m) and rise above rest (m), whether a finger
        touches it, whether both do, the grip command and the finger width (m)."""
        if grasped and self.time_to_grasp_s < 0:
            self.time_to_grasp_s = t * self.period
        if closed and not touched and finger_width < self.half_width:
            self.missed_grasp = True
        lifted = rise >= self.lift_height
        self._was_lifted = self._was_lifted or lifted
        if self._was_lifted and not touched and not lifted:
            self.dropped = True
        if not touched:
            x, y, z = object_pos.tolist()
            if (
                abs(x - BELT_X) > BELT_HALF_WIDTH
                or abs(y) > BELT_HALF_LENGTH
                or y > self.reach_y
                or z < BELT_SURFACE_Z
            ):
                self.off_belt = True

    def info(self) -> dict[str, float | bool]:
        """The latched events and the time to grasp, for the env's ``info``."""
        return {
            "missed_grasp": self.missed_grasp,
            "dropped": self.dropped,
            "off_belt": self.off_belt,
            "time_to_grasp_s": self.time_to_grasp_s,
        }
