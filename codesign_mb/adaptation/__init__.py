"""QoS adaptation policies: static, rule-based, learned (SAC with a primal-dual multiplier)."""

from codesign_mb.adaptation.base import QosPolicy, StaticQos

__all__ = ["QosPolicy", "StaticQos"]
