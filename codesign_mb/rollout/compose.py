"""Compositions that need two sibling layers at once: a QoS rule on a predictor replica, LQG.

Estimation, control and adaptation do not import one another; what combines them (the
covariance-triggered QoS rule reads a replica of the robot's predictor, LQG pairs the LQR with
the Kalman filter) is composed here, one layer above them. The component registry names
these factories by kind (``qos = "rule"``, ``qos_feature = "predictor_std"``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike

from codesign_mb.adaptation.learned import PredictorStdFeature
from codesign_mb.adaptation.planner import QosPlanner
from codesign_mb.adaptation.rules import CovarianceTriggeredQos, PredictorReplica
from codesign_mb.control.lqr import LqrController
from codesign_mb.core.config import as_matrix
from codesign_mb.estimation.belt_imm import BeltImmPredictor
from codesign_mb.estimation.kalman import KalmanEstimator, steady_state_covariance
from codesign_mb.estimation.predictor import DelayCompensatingPredictor
from codesign_mb.plants.linear import LinearPlantSpec

__all__ = [
    "LqgCost",
    "covariance_rule",
    "covariance_rule_on",
    "lqg",
    "lqg_average_cost",
    "predictor_replica",
    "predictor_replica_on",
    "predictor_std_feature",
    "qos_planner",
    "remote_predictor_arguments",
]


def remote_predictor_arguments(
    env: Any, predictor_options: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """``layout``, ``control_period_s`` and predictor options of the edge's replica for ``env``.

    The remote layout of the plant, and the robot's predictor settings
    (:meth:`DelayCompensatingPredictor.from_env`), overridden by ``predictor_options``.
    """
    plant = env.unwrapped
    remote = plant.remote_slice
    layout = {
        name: slice(s.start - remote.start, s.stop - remote.start)
        for name, s in plant.observation_layout.items()
        if s.start >= remote.start and s.stop <= remote.stop
    }
    reference = DelayCompensatingPredictor.from_env(env)
    options = {
        "prior_velocity": tuple(reference.prior_velocity),
        "position_noise_std": reference.position_noise_std,
        "velocity_noise_std": reference.velocity_noise_std,
        "accel_std": reference.accel_std,
        **dict(predictor_options or {}),
    }
    return {"layout": layout, "control_period_s": float(plant.control_period_s), **options}


def predictor_replica(
    env: Any,
    *,
    lift_margin_m: float | None = 0.03,
    predictor_options: Mapping[str, Any] | None = None,
) -> PredictorReplica:
    """The edge's replica of the robot's predictor for a plant (wrapped or not)."""
    arguments = remote_predictor_arguments(env, predictor_options)
    layout, period = arguments.pop("layout"), arguments.pop("control_period_s")
    return predictor_replica_on(
        layout, period, lift_margin_m=lift_margin_m, predictor_options=arguments
    )


def covariance_rule(
    env: Any,
    *,
    lift_margin_m: float | None = 0.03,
    predictor_options: Mapping[str, Any] | None = None,
    **options: Any,
) -> CovarianceTriggeredQos:
    """The covariance-triggered QoS rule for a plant: a replica with the robot's settings.

    ``options`` are :class:`CovarianceTriggeredQos`'s (``threshold_m``, ``low``, ``high``,
    ``latency_steps``); ``predictor_options`` override what is read from the plant.
    """
    replica = predictor_replica(
        env, lift_margin_m=lift_margin_m, predictor_options=predictor_options
    )
    return CovarianceTriggeredQos(replica, **options)


def covariance_rule_on(
    layout: Mapping[str, slice],
    control_period_s: float,
    *,
    lift_margin_m: float | None = 0.03,
    predictor_options: Mapping[str, Any] | None = None,
    **options: Any,
) -> CovarianceTriggeredQos:
    """The covariance-triggered QoS rule on a remote ``layout``, without a plant (tests, docs)."""
    replica = predictor_replica_on(
        layout, control_period_s, lift_margin_m=lift_margin_m, predictor_options=predictor_options
    )
    return CovarianceTriggeredQos(replica, **options)


def predictor_replica_on(
    layout: Mapping[str, slice],
    control_period_s: float,
    *,
    lift_margin_m: float | None = 0.03,
    predictor_options: Mapping[str, Any] | None = None,
) -> PredictorReplica:
    """A predictor replica on a remote ``layout``, without a plant (tests, docs)."""
    predictor = DelayCompensatingPredictor(
        layout, control_period_s=control_period_s, **dict(predictor_options or {})
    )
    return PredictorReplica(predictor, lift_margin_m=lift_margin_m)


def predictor_std_feature(
    env: Any,
    *,
    latency_steps: int = 1,
    scale_m: float = 0.01,
    lift_indicator: bool = True,
    elapsed_time: bool = True,
    lift_margin_m: float | None = 0.03,
    predictor_options: dict[str, Any] | None = None,
) -> PredictorStdFeature:
    """The ``predictor_std`` QoS features for a plant: the robot's predictor settings, horizon."""
    replica = predictor_replica(
        env, lift_margin_m=lift_margin_m, predictor_options=predictor_options
    )
    horizon = getattr(env.unwrapped, "horizon", None)
    return PredictorStdFeature(
        replica,
        horizon=None if horizon is None else int(horizon),
        latency_steps=latency_steps,
        scale_m=scale_m,
        lift_indicator=lift_indicator,
        elapsed_time=elapsed_time,
    )


@dataclass(frozen=True, slots=True)
class LqgCost:
    """The average LQG cost per step, split into its two Riccati terms."""

    control: float
    """``tr(S W)``: the cost of the process noise under perfect state feedback."""
    estimation: float
    """``tr(K' (R + B' S B) K Sigma)``: the price of the estimation error."""

    @property
    def total(self) -> float:
        """``control + estimation``, per step."""
        return self.control + self.estimation


def lqg_average_cost(
    plant: LinearPlantSpec,
    state_cost: ArrayLike,
    input_cost: ArrayLike,
    *,
    posterior_cov: ArrayLike | None = None,
) -> LqgCost:
    """Expected infinite-horizon average cost per step of certainty-equivalent LQG.

    ``J = tr(S W) + tr(K' (R + B' S B) K Sigma)`` (module docstring).

    Parameters
    ----------
    plant:
        The plant (``A``, ``B``, ``C``, ``W``, ``V``).
    state_cost, input_cost:
        ``Q`` ``(n, n)`` and ``R`` ``(m, m)`` of the stage cost ``x' Q x + u' R u``.
    posterior_cov:
        ``Sigma = lim E[P_{t|t}]``, shape ``(n, n)``; default the stationary posterior
        covariance of the Kalman filter with every measurement delivered at once (``q = 1``).
    """
    ctrl = LqrController.for_plant(plant, state_cost, input_cost)
    n = plant.n_states
    if posterior_cov is None:
        _, sigma = steady_state_covariance(plant.A, plant.C, plant.W, plant.V)
    else:
        sigma = as_matrix("posterior_cov", posterior_cov, (n, n))
    K, S, B = ctrl.gain, ctrl.riccati, plant.B
    weight = K.T @ (ctrl.input_cost + B.T @ S @ B) @ K
    return LqgCost(control=float(np.trace(S @ plant.W)), estimation=float(np.trace(weight @ sigma)))


def lqg(
    env: gym.Env, *, max_delay_steps: int = 64, use_arrivals: bool = True
) -> tuple[KalmanEstimator, LqrController]:
    """Certainty-equivalent LQG for ``env``: the Kalman estimator and the LQR on its estimate.

    ``env`` is a :class:`LinearPlantEnv`, usually behind a
    :class:`~codesign_mb.network.LinkObservationWrapper`; pass the pair to
    :func:`~codesign_mb.rollout.rollout`.

    Examples
    --------
    >>> from codesign_mb.adaptation.base import StaticQos
    >>> from codesign_mb.rollout import rollout
    >>> from codesign_mb.network import BernoulliLink, LinkObservationWrapper
    >>> from codesign_mb.plants.linear import LinearPlantEnv, scalar_unstable
    >>> env = LinkObservationWrapper(
    ...     LinearPlantEnv(scalar_unstable(), horizon=50), BernoulliLink(), StaticQos(0.9)
    ... )
    >>> estimator, controller = lqg(env)
    >>> len(rollout(env, estimator, controller, seed=0))
    50
    """
    estimator = KalmanEstimator.for_env(
        env, max_delay_steps=max_delay_steps, use_arrivals=use_arrivals
    )
    return estimator, LqrController.for_env(env)


def qos_planner(
    env: Any,
    *,
    grasp_std_m: float = 0.01,
    far_std_m: float = math.inf,
    closing_std_m: float | None = None,
    closing_useful_width_m: float = 0.0,
    grasp_window_m: float = 0.012,
    grasp_height_m: float = 0.015,
    lookahead: bool = True,
    latency_steps: int = 1,
    innovation_gate: float | None = 0.99,
    change_gate: float = 0.5,
    model_options: Mapping[str, Any] | None = None,
) -> Any:
    """The model-based QoS planner for a plant, on a replica of the robot's belt-aware predictor.

    The keywords are :class:`~codesign_mb.adaptation.planner.QosPlanner`'s (``lookahead =
    False``: the event-triggered rule); ``model_options`` override fields of the belt model
    read from the plant (give the robot's own).
    """
    replica = BeltImmPredictor.from_env(env, model_options=model_options)
    return QosPlanner(
        replica,
        env.unwrapped.observation_layout,
        grasp_std_m=grasp_std_m,
        far_std_m=far_std_m,
        closing_std_m=closing_std_m,
        closing_useful_width_m=closing_useful_width_m,
        grasp_window_m=grasp_window_m,
        grasp_height_m=grasp_height_m,
        lookahead=lookahead,
        latency_steps=latency_steps,
        innovation_gate=innovation_gate,
        change_gate=change_gate,
    )
