"""How conveyor belts behave: the switching model the belt-aware predictor filters with.

The object rides a belt whose speed is not sent (the packet carries a perceived position):
it is a state. The belt runs, changes speed, stops and restarts, and the object slips now and
then; a jump-Markov linear model describes it with four modes that share one state,
``x = (o, w, b)``: the object's position ``o`` and velocity ``w`` (world frame, m and m/s;
the belt runs along +y) and the edge camera's constant position bias ``b`` (m)::

    RUN    o+ = o + dt w,  w+ = w + dt a,    a ~ N(0, sigma_a^2 I)      (constant velocity)
    CHANGE the same, plus a velocity kick k ~ N(0, K)                   (speed step, slip)
    STOP   o+ = o,         w+ = 0                                       (belt stopped)
    START  o+ = o,         w+ = w_nom + k,  k ~ N(0, K_start)           (belt (re)starts)
    b+ = b in every mode; a packet measures z = o + b + v, v ~ N(0, R) (and w, if perceived).

Mode switches are a Markov chain (:attr:`BeltModel.transitions`): from RUN (and from CHANGE
and START, after their one step) a change with probability ``p_change``, of which the share
``stop_fraction`` are stops; from STOP a restart with ``p_restart``. Before the object appears
on the belt it waits at its start, at rest: the STOP mode with the prior's weight.

:meth:`BeltModel.from_plant` reads the probabilities and sizes from a conveyor's config, so
the model is the plant's own description, not a tuned guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["MODES", "BeltModel"]

MODES = ("run", "change", "stop", "start")
"""The belt's modes, in the order of :attr:`BeltModel.transitions`."""

RUN, CHANGE, STOP, START = range(4)
N_STATE = 9  # o (3), w (3), b (3)


@dataclass(frozen=True)
class BeltModel:
    """Parameters of the switching belt model (see the module docstring).

    Parameters
    ----------
    control_period_s:
        ``dt`` (s).
    nominal_velocity_mps:
        ``w_nom``: the belt velocity a (re)start goes to on average (world frame).
    accel_std_mps2:
        ``sigma_a`` of the RUN mode (small speed drift).
    change_kick_std_mps:
        Standard deviations of a CHANGE's velocity kick along x, y (the belt) and z.
    start_speed_std_mps:
        Standard deviation of the speed a START reaches, along the belt.
    change_probability, stop_fraction, restart_probability:
        ``p_change`` per step, the share of changes that are stops, ``p_restart`` per step.
    position_noise_std_m, velocity_noise_std_mps:
        Perception noise ``R``.
    bias_std_m:
        Prior standard deviation of the camera's bias ``b`` per axis (0: no bias).
    """

    control_period_s: float
    nominal_velocity_mps: tuple[float, float, float] = (0.0, 0.2, 0.0)
    accel_std_mps2: float = 0.25
    change_kick_std_mps: tuple[float, float, float] = (0.05, 0.1, 0.01)
    start_speed_std_mps: float = 0.1
    change_probability: float = 0.05
    stop_fraction: float = 0.2
    restart_probability: float = 0.08
    position_noise_std_m: float = 0.002
    velocity_noise_std_mps: float = 0.02
    bias_std_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("control_period_s", "position_noise_std_m", "velocity_noise_std_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        for name in ("accel_std_mps2", "start_speed_std_mps", "bias_std_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        for name in ("change_probability", "stop_fraction", "restart_probability"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        if len(self.nominal_velocity_mps) != 3 or len(self.change_kick_std_mps) != 3:
            raise ValueError("nominal_velocity_mps and change_kick_std_mps need 3 entries")

    @classmethod
    def from_plant(cls, plant: Any, **overrides: Any) -> BeltModel:
        """The model of a conveyor plant (:class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`).

        Changes every ``belt_change_steps`` (mean interval) plus the object's slips, the
        kick of a speed step from the speed jitter, a (re)start's speed from the episode speed
        range; constant belts keep a small change probability (an unmodelled event stays
        possible, so one does not break the filter).
        """
        cfg = plant.config
        dt = float(plant.control_period_s)
        v_nom = float(cfg.belt_speed_mps)
        low, high = cfg.belt_change_steps
        variable = cfg.belt_profile == "variable"
        p_change = 2.0 / (low + high) if variable else 0.0
        p_slip = float(cfg.disturbance_probability)
        jitter = float(cfg.belt_speed_jitter) if variable else 0.0
        # A step draws a new speed v_ep U(1 - j, 1 + j) independent of the old one.
        step_std = math.sqrt(2.0) * v_nom * jitter / math.sqrt(3.0)
        slip = float(cfg.disturbance_speed_std_mps)
        p_stop = p_change * cfg.belt_stop_probability
        p_total = p_change * (1 - cfg.belt_stop_probability) + p_slip
        # The kick of a CHANGE: the mixture of a speed step (along y) and a slip (x and y).
        w_step = p_change * (1 - cfg.belt_stop_probability) / p_total if p_total > 0 else 0.0
        kick_y = math.sqrt(w_step * step_std**2 + (1 - w_step) * slip**2) if p_total else 0.05
        kick_x = math.sqrt((1 - w_step) * slip**2) if p_total else 0.02
        spread = 0.0
        if cfg.belt_speed_range_mps:
            lo, hi = cfg.belt_speed_range_mps
            spread = (hi - lo) / math.sqrt(12.0)  # U(lo, hi)
        start_std = math.sqrt(spread**2 + (v_nom * jitter) ** 2 / 3.0 + 0.02**2)
        options: dict[str, Any] = {
            "control_period_s": dt,
            # An object riding a belt rocks and creeps: one-step residuals grow with the speed
            # (variable belt, exact perception, every packet, 60 dev episodes: belt NEES 19.9
            # with 0.25 m/s^2, 0.64 with 1.0 m/s^2; 0.85 v_nom between).
            "accel_std_mps2": max(0.85 * v_nom, 0.25),
            "nominal_velocity_mps": (0.0, v_nom, 0.0),
            "change_kick_std_mps": (max(kick_x, 0.01), max(kick_y, 0.02), 0.01),
            "start_speed_std_mps": start_std,
            "change_probability": min(max(p_total + p_stop, 1e-3), 0.5),
            "stop_fraction": (p_stop / (p_total + p_stop) if p_change > 0 else 0.01),
            "restart_probability": 2.0 / (low + high) if variable else 0.1,
            # Exact perception (the paper's plant) keeps a floor: the simulator's own jitter.
            "position_noise_std_m": max(float(cfg.perception_noise_std_m), 2e-4),
            "velocity_noise_std_mps": max(float(cfg.velocity_noise_std_mps), 2e-3),
            "bias_std_m": float(cfg.perception_bias_std_m),
        }
        options.update(overrides)
        return cls(**options)

    # -- the matrices -----------------------------------------------------------------------
    @property
    def transitions(self) -> NDArray[np.float64]:
        """``Pi[i, j]``: probability of mode ``j`` at ``t + 1`` given mode ``i`` at ``t``."""
        p, f, r = self.change_probability, self.stop_fraction, self.restart_probability
        moving = [1.0 - p, p * (1.0 - f), p * f, 0.0]
        return np.array([moving, moving, [0.0, 0.0, 1.0 - r, r], moving])

    def dynamics(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Per mode ``(A, c, Q)``: ``x+ = A x + c + noise``, noise ``N(0, Q)``; shapes
        ``(4, 9, 9)``, ``(4, 9)``, ``(4, 9, 9)`` (built once per model, read-only)."""
        return self._dynamics

    @cached_property
    def _dynamics(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        dt, eye, zero = self.control_period_s, np.eye(3), np.zeros((3, 3))
        cv = np.block([[eye, dt * eye, zero], [zero, eye, zero], [zero, zero, eye]])
        rest = np.block([[eye, zero, zero], [zero, zero, zero], [zero, zero, eye]])
        q = self.accel_std_mps2**2
        q_cv = np.zeros((N_STATE, N_STATE))
        q_cv[:6, :6] = q * np.block(
            [[dt**4 / 4 * eye, dt**3 / 2 * eye], [dt**3 / 2 * eye, dt**2 * eye]]
        )
        kick = np.zeros((N_STATE, N_STATE))
        kick[3:6, 3:6] = np.diag(np.square(self.change_kick_std_mps))
        at_rest = np.zeros((N_STATE, N_STATE))
        at_rest[:6, :6] = np.diag([1e-4**2] * 3 + [1e-3**2] * 3)  # a stopped object barely moves
        start = at_rest.copy()
        start[3:6, 3:6] = np.diag([0.01**2, self.start_speed_std_mps**2, 0.01**2])
        A = np.stack([cv, cv, rest, rest])
        c = np.zeros((4, N_STATE))
        c[START, 3:6] = self.nominal_velocity_mps
        Q = np.stack([q_cv, q_cv + kick, at_rest, start])
        for matrix in (A, c, Q):
            matrix.setflags(write=False)  # shared by every caller
        return A, c, Q

    def measurement(self, *, velocity: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(H, R)`` of a packet: the biased position ``o + b`` (and the velocity ``w``)."""
        eye, zero = np.eye(3), np.zeros((3, 3))
        if not velocity:
            return np.hstack([eye, zero, eye]), self.position_noise_std_m**2 * eye
        H = np.block([[eye, zero, eye], [zero, eye, zero]])
        R = np.diag([self.position_noise_std_m**2] * 3 + [self.velocity_noise_std_mps**2] * 3)
        return H, R

    def average_dynamics(
        self, probabilities: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A linear model of the mixture's spread one step ahead from mode ``probabilities``:
        ``(A, Q)`` whose covariance recursion bounds what the modes do on average.

        ``A`` is the constant-velocity matrix; ``Q`` adds to RUN's noise the expected kick of a
        change and, weighted by the chance of a (re)start, the spread of a start speed, so the
        look-ahead of the QoS planner grows its uncertainty as fast as the belt may change.
        """
        A, _, Q = self.dynamics()
        moving = float(probabilities[RUN] + probabilities[CHANGE] + probabilities[START])
        p = self.change_probability
        stopped = float(probabilities[STOP])
        q_eff = Q[RUN] + p * (1 - self.stop_fraction) * (Q[CHANGE] - Q[RUN])
        v = np.asarray(self.nominal_velocity_mps)
        restart = np.zeros((N_STATE, N_STATE))
        restart[3:6, 3:6] = Q[START][3:6, 3:6] + np.outer(v, v)
        stop = np.zeros((N_STATE, N_STATE))
        stop[3:6, 3:6] = np.outer(v, v)
        q_eff = (
            q_eff
            + stopped * self.restart_probability * restart
            + moving * p * self.stop_fraction * stop
        )
        return A[RUN], q_eff
