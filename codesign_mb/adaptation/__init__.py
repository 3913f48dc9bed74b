"""QoS adaptation policies: static, rule-based, learned (SAC with a primal-dual multiplier)."""

from codesign_mb.adaptation.base import QosPolicy, StaticQos
from codesign_mb.adaptation.rules import AgeTriggeredQos, CovarianceTriggeredQos, tune_threshold

__all__ = ["AgeTriggeredQos", "CovarianceTriggeredQos", "QosPolicy", "StaticQos", "tune_threshold"]
