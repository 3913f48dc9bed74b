"""The model-based QoS planner: ask for a packet only when the planned grasp needs it.

Stage C of paper.tex (``eq_q_pol``) without learning, the constraint stated: at step ``t``
choose ``q_t`` in ``{0, high}`` so that, with the smallest expected number of requests, the
object's predicted lateral position uncertainty at the planned grasp step meets the grasp
tolerance (the fingers close across the object; the belt's height is known)::

    min  sum_s q_s    s.t.   sqrt(P_xx + P_yy)(t_grasp | requests) <= grasp_std_m

``P`` follows the covariance recursion of the edge's replica of the robot's belt-aware
predictor (:class:`~codesign_mb.estimation.belt_imm.BeltImmPredictor`, its averaged linear
model from the current mode probabilities); a packet requested at ``s`` measures the state at
``s`` and counts if it arrives by the grasp (``s + tau <= t_grasp``). The search: the cheapest
schedule among "the last ``m`` useful steps before the grasp", with and without the current
step (a packet now also pins the velocity down, which the last steps alone may not); the
current step is requested only if it makes the schedule strictly cheaper, or if no schedule
without it is feasible. (Later packets are fresher, so among equally cheap schedules the
planner waits.) This restricted search is exact for the pure position part of a
constant-velocity model and a heuristic beyond it; it is not a full dynamic program.

What it found on the conveyor: on ``realistic`` (dev and test seeds) the cheapest schedule is
always the last steps before the grasp, where the grasp-point check below asks anyway, so the
planner's requests coincide with the event-triggered rule's (the two table rows ran identical
episodes): with this belt model, asking early never saves a packet. Constraining the
uncertainty over the whole descent instead (the last 4 steps before the grasp) made it ask
earlier but more (16 against 11.7 packets per episode, 15 dev episodes).

The planned grasp step comes from the robot's state at ``t - 1`` (the policy reads it:
:attr:`QosPlanner.reads_robot_state`): the horizontal distance to the predicted object at an
approach speed, the height to descend at a descent speed, and the closing steps.

Event triggers on top (the event-triggered rule alone when ``lookahead=False``): a packet the
model did not expect (normalised innovation squared above the chi-square quantile
``innovation_gate``), or a suspected belt change (probability of the non-RUN modes above
``change_gate``), asks ``high`` until an expected packet arrives; so does an uncertainty
above ``grasp_std_m`` while the gripper is at the grasp point (over the object, at its
height: closing, or waiting there until the estimate is certain enough to close), or above
``closing_std_m`` while the fingers close and a packet can still make the controller
reopen them (``closing_useful_width_m``).
After the grasp (the object carried, or lifted) nothing is asked.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from codesign_mb.core.layout import entry_indices, slice_indices
from codesign_mb.network.qos import QosRequest

__all__ = ["REASONS", "QosPlanner"]

REASONS = ("nothing measured yet", "surprise", "far", "at the grasp", "closing", "plan")
"""Why the planner asks ``high`` (:attr:`QosPlanner.reason`), in the order it tests them."""


def _slug(reason: str) -> str:
    return reason.replace(" ", "_")


class QosPlanner:
    """QoS from the model (module docstring): a :class:`~codesign_mb.network.qos.QosPolicy`.

    Parameters
    ----------
    replica:
        A fresh belt-aware predictor on the plant's observation layout (the edge's replica of
        the robot's estimator), fed what the robot held.
    layout:
        The plant's observation layout (``gripper_pos`` is read).
    grasp_std_m:
        Lateral RMS position uncertainty the grasp tolerates (m; chosen on dev seeds).
    lookahead:
        Plan towards the grasp (the planner); ``False``: only the event triggers and the
        grasp-window check (the event-triggered rule).
    far_std_m:
        Ask whenever the uncertainty one packet ahead exceeds this, wherever the gripper is
        (keeps the approach on the object; ``inf``: never).
    grasp_window_m, grasp_height_m:
        The grasp point: the gripper within these of the estimated object laterally and in
        height (the MPC's own grasp conditions, ``grasp_tolerance_m`` and
        ``grasp_height_tolerance_m`` of :class:`~codesign_mb.control.mpc_config.MpcConfig`).
    closing_std_m:
        The tolerance while the fingers close (finger width below ``closing_width_m``;
        ``None``: 1.5 ``grasp_std_m``): across the object the fingers leave room, a packet
        then only has to catch a belt event.
    closing_useful_width_m:
        While the fingers close, ask only as long as they are wider than this: a packet
        asked later arrives when the fingers are on the object already, too late for the
        controller to reopen them (the cube is 45 mm wide and the fingers close 8 mm a
        step: 60 mm leaves two steps).
    """

    reads_robot_state = True
    """Given the robot's whole held observation (:class:`LinkObservationWrapper`)."""

    def __init__(
        self,
        replica: Any,
        layout: Mapping[str, slice],
        *,
        grasp_std_m: float = 0.008,
        lookahead: bool = True,
        far_std_m: float = math.inf,
        high: float = 1.0,
        latency_steps: int = 1,
        innovation_gate: float | None = 0.99,
        change_gate: float = 0.5,
        approach_speed_mps: float = 0.5,
        descend_speed_mps: float = 0.3,
        close_steps: int = 0,
        hover_height_m: float = 0.06,
        grasp_window_m: float = 0.012,
        grasp_height_m: float = 0.015,
        closing_std_m: float | None = None,
        closing_width_m: float = 0.075,
        closing_useful_width_m: float = 0.0,
        max_lookahead_steps: int = 40,
    ) -> None:
        QosRequest(high, latency_steps)
        if latency_steps < 1:
            raise ValueError(f"latency_steps must be >= 1, got {latency_steps}")
        for name, value in (
            ("grasp_std_m", grasp_std_m),
            ("approach_speed_mps", approach_speed_mps),
            ("descend_speed_mps", descend_speed_mps),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if not far_std_m > 0:
            raise ValueError(f"far_std_m must be > 0, got {far_std_m!r}")
        if innovation_gate is not None and not 0.0 < innovation_gate < 1.0:
            raise ValueError(f"innovation_gate must be in (0, 1) or None, got {innovation_gate!r}")
        if not 0.0 < change_gate <= 1.0:
            raise ValueError(f"change_gate must be in (0, 1], got {change_gate!r}")
        if "gripper_pos" not in layout:
            raise ValueError("the planner reads gripper_pos: the layout lacks it")
        self.replica = replica
        self.grasp_std_m = float(grasp_std_m)
        self.lookahead = bool(lookahead)
        self.far_std_m = float(far_std_m)
        self.latency_steps = int(latency_steps)
        self.nis_limit = (
            math.inf
            if innovation_gate is None
            else float(chi2.ppf(innovation_gate, replica.measured_dims))
        )
        self.change_gate = float(change_gate)
        self.approach_speed_mps = float(approach_speed_mps)
        self.descend_speed_mps = float(descend_speed_mps)
        self.close_steps = int(close_steps)
        self.hover_height_m = float(hover_height_m)
        self.grasp_window_m = float(grasp_window_m)
        self.grasp_height_m = float(grasp_height_m)
        self.closing_std_m = 1.5 * self.grasp_std_m if closing_std_m is None else closing_std_m
        self.closing_width_m = float(closing_width_m)
        self.closing_useful_width_m = float(closing_useful_width_m)
        self.max_lookahead_steps = int(max_lookahead_steps)
        self._gripper = slice_indices(layout["gripper_pos"])
        self._width = entry_indices(layout, "finger_width")
        self._send = QosRequest(high, self.latency_steps)
        self._skip = QosRequest(0.0, self.latency_steps)
        self.reset()

    def reset(self, *, seed: int | None = None) -> None:
        self._calls = 0
        self._updates = 0
        self._surprised = False
        self._start_z: float | None = None
        self._lifted = False
        self.reason: str | None = None
        """Why the last request asked ``high`` (``None``: it did not)."""
        self._asked: dict[str, int] = dict.fromkeys(REASONS, 0)

    # -- the policy ------------------------------------------------------------------------
    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        """``(q_t, tau)`` from what the robot held at ``t - 1`` (its state and ``y_{t-1}``)."""
        held = np.asarray(observation, dtype=float)
        calls, self._calls = self._calls, self._calls + 1
        if calls == 0:  # t = 0: the robot holds the prior
            return self._decide("nothing measured yet")
        wrapped = np.append(held, float(age))
        if calls == 1:
            self.replica.reset(wrapped)
        else:
            self.replica.estimate(wrapped, np.zeros(0))
        if self.replica.updates > self._updates:  # a new packet arrived: was it expected?
            self._updates = self.replica.updates
            modes = self.replica.mode_probabilities
            changing = modes["change"] + modes["start"]  # a speed step, a slip, a restart
            surprise = self.replica.last_nis > self.nis_limit or changing > self.change_gate
            # Closing fingers push the object themselves: no belt event to chase then; and
            # the first packet always surprises the prior (the lookahead plans the next).
            self._surprised = surprise and not self._closing(held) and self._updates > 1
        if self.replica.updates == 0:
            return self._decide("nothing measured yet")
        if self.replica.carried or self._lifted_now(held):
            return self._decide(None)
        if self._surprised:
            return self._decide("surprise")
        return self._decide(self._needed(held))

    def _decide(self, reason: str | None) -> QosRequest:
        """The request, ``high`` when there is a reason (kept in :attr:`reason`)."""
        self.reason = reason
        if reason is None:
            return self._skip
        self._asked[reason] += 1
        return self._send

    def episode_metrics(self) -> dict[str, float]:
        """Requests of the episode by reason (``qos_asked_<reason>``, :data:`REASONS`):
        which of the planner's triggers the packets were spent on. Counted as asked: a step
        with no detection to send (the link then carries nothing) counts too."""
        return {f"qos_asked_{_slug(r)}": float(n) for r, n in self._asked.items()}

    def _lifted_now(self, held: NDArray[np.float64]) -> bool:
        z = float(self.replica.state[2])
        if self._start_z is None:
            self._start_z = z
        self._lifted = self._lifted or z > self._start_z + 0.03
        return self._lifted

    def _needed(self, held: NDArray[np.float64]) -> str | None:
        """Why a packet now is needed (``None``: it is not): the uncertainty far from the
        grasp, at the grasp point, or a packet now is part of the cheapest schedule."""
        tau = self.latency_steps
        soon = self.replica.position_std_ahead(1 + tau)
        if soon > self.far_std_m:
            return "far"
        steps = self.grasp_steps(held)
        if steps <= 1 + tau or self._in_window(held):
            # At the grasp (the robot may wait there for a certain estimate): keep the
            # uncertainty the packet is used at within the tolerance; once the fingers close
            # (they only do on a certain estimate), within the looser closing tolerance.
            if self._closing(held):
                useful = self._finger_width(held) > self.closing_useful_width_m
                return "closing" if useful and soon > self.closing_std_m else None
            return "at the grasp" if soon > self.grasp_std_m else None
        if not self.lookahead:
            return None
        last = steps - tau  # the latest stamp (offset from t - 1) still useful at the grasp
        slots = list(range(2, last + 1))  # offset 1 is now (the packet of step t)

        def cheapest(now: bool) -> float:
            """Fewest packets (now, if ``now``, and the last ``m`` slots) meeting the grasp:
            bisection, feasibility being monotone in ``m``."""
            fixed = [1] if now else []

            def meets(m: int) -> bool:
                chosen = fixed + slots[len(slots) - m :]
                return self.replica.position_std_ahead(steps, chosen) <= self.grasp_std_m

            if not meets(len(slots)):
                return math.inf
            lo, hi = -1, len(slots)  # meets(hi) holds; meets(lo) is taken as failing
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if meets(mid):
                    hi = mid
                else:
                    lo = mid
            return hi + len(fixed)

        without = cheapest(False)
        if without == 0:
            return None
        return "plan" if without == math.inf or cheapest(True) < without else None

    def _closing(self, held: NDArray[np.float64]) -> bool:
        """The fingers are closing (or closed): their width is below ``closing_width_m``."""
        return self._finger_width(held) < self.closing_width_m

    def _finger_width(self, held: NDArray[np.float64]) -> float:
        """The fingers' width (``inf`` for a layout without fingers: never closing)."""
        return math.inf if self._width is None else float(np.mean(held[self._width]))

    def _offset(self, held: NDArray[np.float64]) -> tuple[float, float]:
        """The gripper's horizontal distance to the estimated object and its height above it."""
        obj, grip = self.replica.state, held[self._gripper]
        return float(np.hypot(grip[0] - obj[0], grip[1] - obj[1])), float(grip[2] - obj[2])

    def _in_window(self, held: NDArray[np.float64]) -> bool:
        """The gripper at the grasp point (over the object, at its height): closing, or
        waiting there for an estimate certain enough to close on."""
        lateral, height = self._offset(held)
        return lateral <= self.grasp_window_m and height < self.grasp_height_m

    def grasp_steps(self, held: NDArray[np.float64]) -> int:
        """Planned steps from ``t - 1`` to the grasp decision (where the controller's
        uncertainty gate is met or not): approach, descend, then ``close_steps``."""
        dt = self.replica.control_period_s
        lateral, above = self._offset(held)
        approach = max(lateral - self.grasp_window_m, 0.0) / (self.approach_speed_mps * dt)
        height = max(above, 0.0)
        if lateral > self.grasp_window_m:
            height = max(height, self.hover_height_m)
        descend = height / (self.descend_speed_mps * dt)
        steps = math.ceil(approach + descend) + self.close_steps
        return int(min(max(steps, 1), self.max_lookahead_steps))
