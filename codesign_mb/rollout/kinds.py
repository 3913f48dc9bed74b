"""The QoS kinds built on an estimator replica at the edge (roles ``qos`` and ``qos_feature``
of :mod:`codesign_mb.core.registry`): they compose an adaptation policy with an estimator,
which only this layer may import both of.

================= ========================================================================
kind              what
================= ========================================================================
``rule``          the covariance-triggered rule on a predictor replica
``planner``       :class:`~codesign_mb.adaptation.planner.QosPlanner` on a belt-aware replica
``predictor_std`` feature: the predictor replica's uncertainty (hybrid: model-based at the edge)
================= ========================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.rollout import compose  # noqa: F401

register(
    "qos",
    {
        "rule": Kind("codesign_mb.rollout.compose:covariance_rule", takes_env=True),
        "planner": Kind("codesign_mb.rollout.compose:qos_planner", takes_env=True),
    },
)

register(
    "qos_feature",
    {
        "predictor_std": Kind("codesign_mb.rollout.compose:predictor_std_feature"),
    },
)
