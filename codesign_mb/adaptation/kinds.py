"""The QoS policies and QoS-policy features by kind (roles ``qos`` and ``qos_feature`` of
:mod:`codesign_mb.core.registry`); the kinds on an estimator replica (``rule``, ``planner``,
``predictor_std``) are registered by :mod:`codesign_mb.rollout.kinds`, which may build one.

==================== =====================================================================
kind                 what
==================== =====================================================================
``static``           :class:`~codesign_mb.adaptation.base.StaticQos` (``options``)
``random``           :class:`~codesign_mb.adaptation.base.RandomQos`: ``q = 1`` w.p. ``probability``
``schedule``         :class:`~codesign_mb.adaptation.base.ScheduledQos`: ``q = 1`` at ``steps``
``age_rule``         :class:`~codesign_mb.adaptation.rules.AgeTriggeredQos`
``learned``          :class:`~codesign_mb.adaptation.learned.LearnedQosPolicy` (checkpoint folder)
``elapsed_time``     feature :class:`~codesign_mb.adaptation.learned.ElapsedTimeFeature` (``t/T``)
``held_history``     feature :class:`~codesign_mb.adaptation.model_free_features.HeldHistoryFeature`
                     (model-free: ``t / T``, held-position differences, lift, from ``(y, zeta)``)
``belief``           feature :class:`~codesign_mb.adaptation.belief_features.BeliefFeature`: the
                     robot's estimate and its uncertainty (bound to its estimator by the loop)
==================== =====================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.adaptation import (  # noqa: F401
        base,
        belief_features,
        learned,
        model_free_features,
        rules,
    )

register(
    "qos",
    {
        "static": Kind("codesign_mb.adaptation.base:StaticQos"),
        "random": Kind("codesign_mb.adaptation.base:RandomQos"),
        "schedule": Kind("codesign_mb.adaptation.base:ScheduledQos"),
        "age_rule": Kind("codesign_mb.adaptation.rules:AgeTriggeredQos"),
        "learned": Kind(
            "codesign_mb.adaptation.learned:LearnedQosPolicy.from_env",
            takes_env=True,
            checkpoint_keyword="directory",
        ),
    },
)

register(
    "qos_feature",
    {
        "elapsed_time": Kind("codesign_mb.adaptation.learned:ElapsedTimeFeature.from_env"),
        "held_history": Kind(
            "codesign_mb.adaptation.model_free_features:HeldHistoryFeature.from_env"
        ),
        "belief": Kind("codesign_mb.adaptation.belief_features:BeliefFeature.from_env"),
    },
)
