"""State estimation over the link: the delay-compensating predictor and learned estimators."""

from codesign_mb.estimation.base import (
    Estimator,
    PassThroughEstimator,
    split_networked_observation,
)

__all__ = ["Estimator", "PassThroughEstimator", "split_networked_observation"]
