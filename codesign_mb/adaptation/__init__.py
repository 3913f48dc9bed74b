"""QoS adaptation policies: static, random (a reference), rule-based, learned (SAC)."""

from codesign_mb.adaptation.base import QosPolicy, RandomQos, StaticQos
from codesign_mb.adaptation.rules import AgeTriggeredQos, CovarianceTriggeredQos, tune_threshold

__all__ = [
    "AgeTriggeredQos",
    "CovarianceTriggeredQos",
    "QosPolicy",
    "RandomQos",
    "StaticQos",
    "tune_threshold",
]
