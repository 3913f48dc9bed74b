"""The estimators by kind (role ``estimator`` of :mod:`codesign_mb.core.registry`).

================ =========================================================================
kind             what
================ =========================================================================
``none``         :class:`~codesign_mb.estimation.base.PassThroughEstimator` (stale observation)
``mlp``/``lstm`` a learned estimator from its checkpoint (``learned.load_estimator``)
``sequence``     the Gaussian sequence estimator (:mod:`~codesign_mb.estimation.sequence`)
``predictor``    :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`
``belt_imm``     :class:`~codesign_mb.estimation.belt_imm.BeltImmPredictor` (switching belt)
================ =========================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.estimation import base, belt_imm, learned, predictor  # noqa: F401

register(
    "estimator",
    {
        "none": Kind("codesign_mb.estimation.base:PassThroughEstimator.from_env", takes_env=True),
        # The learned ones: load_estimator builds the network their checkpoint records.
        "mlp": Kind("codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"),
        "lstm": Kind("codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"),
        "sequence": Kind(
            "codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"
        ),
        "predictor": Kind(
            "codesign_mb.estimation.predictor:DelayCompensatingPredictor.from_env", takes_env=True
        ),
        "belt_imm": Kind(
            "codesign_mb.estimation.belt_imm:BeltImmPredictor.from_env", takes_env=True
        ),
    },
)
