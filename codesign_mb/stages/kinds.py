"""The training stages by kind (role ``stage`` of :mod:`codesign_mb.core.registry`): the
trainer (a :class:`~codesign_mb.stages.stage.Trainer`) and, as ``config``, its config dataclass.

===== ===================================================================================
kind  what
===== ===================================================================================
``a`` :func:`~codesign_mb.stages.stage_a.train_stage_a`: the ideal controller (SAC from demos)
``b`` :func:`~codesign_mb.stages.stage_b.train_stage_b`: the estimators (DAgger rounds)
``c`` :func:`~codesign_mb.stages.stage_c.train_stage_c`: the QoS policy (SAC + dual ascent)
``d`` :func:`~codesign_mb.stages.stage_d.train_stage_d`: the joint synthesis (B and C again)
===== ===================================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.stages import stage_a, stage_b, stage_c, stage_d  # noqa: F401

register(
    "stage",
    {
        name: Kind(
            f"codesign_mb.stages.stage_{name}:train_stage_{name}",
            config=f"codesign_mb.stages.stage_{name}:Stage{name.upper()}Config",
        )
        for name in "abcd"
    },
)
