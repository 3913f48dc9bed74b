"""The abstract wireless link (paper.tex sec. 2-3): QoS requests, loss, latency, age."""

from codesign_mb.network.link import (
    PRIOR_TIMESTAMP,
    BernoulliLink,
    Link,
    ObservationBuffer,
    Packet,
    Reception,
)
from codesign_mb.network.qos import QosCost, QosPolicy, QosRequest, reliability_cost
from codesign_mb.network.wrapper import LinkObservationWrapper, NetworkedPlant

__all__ = [
    "PRIOR_TIMESTAMP",
    "BernoulliLink",
    "Link",
    "LinkObservationWrapper",
    "NetworkedPlant",
    "ObservationBuffer",
    "Packet",
    "QosCost",
    "QosPolicy",
    "QosRequest",
    "Reception",
    "reliability_cost",
]
