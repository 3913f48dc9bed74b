"""The plants by kind (roles ``plant``, ``perception`` and ``linear_plant`` of
:mod:`codesign_mb.core.registry`).

=============================== ==========================================================
role / kind                     what
=============================== ==========================================================
plant ``conveyor``              :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace`
                                (``ConveyorConfig`` options)
plant ``toy``                   :class:`~codesign_mb.plants.toy.ToyConveyor`
                                (``ToyConveyorConfig`` options)
perception ``gaussian``         :class:`~codesign_mb.plants.perception.GaussianPerception`:
                                noise, bias, missed detections of the config
perception ``camera``           :class:`~codesign_mb.plants.camera_perception.CameraPerception`,
                                calibrated from the edge camera (``codesign calibrate-perception``)
linear_plant ``scalar``         :func:`~codesign_mb.plants.linear.scalar_unstable`
linear_plant ``double_integrator`` :func:`~codesign_mb.plants.linear.double_integrator`
linear_plant ``pendulum``       :func:`~codesign_mb.plants.linear.inverted_pendulum`
=============================== ==========================================================

Gymnasium ids (``codesign_mb/ConveyorPickPlace-v0`` ...) are Gymnasium's own registry,
filled by :mod:`codesign_mb.plants`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.plants import conveyor, conveyor_config, linear, perception, toy  # noqa: F401

register(
    "plant",
    {
        "conveyor": Kind(
            "codesign_mb.plants.conveyor:ConveyorPickPlace.from_options",
            config="codesign_mb.plants.conveyor_config:ConveyorConfig",
        ),
        "toy": Kind(
            "codesign_mb.plants.toy:ToyConveyor.from_options",
            config="codesign_mb.plants.toy:ToyConveyorConfig",
        ),
    },
)

register(
    "perception",
    {
        "gaussian": Kind("codesign_mb.plants.perception:GaussianPerception.from_config"),
        "camera": Kind("codesign_mb.plants.perception:camera_perception"),
    },
)

register(
    "linear_plant",
    {
        "scalar": Kind("codesign_mb.plants.linear:scalar_unstable"),
        "double_integrator": Kind("codesign_mb.plants.linear:double_integrator"),
        "pendulum": Kind("codesign_mb.plants.linear:inverted_pendulum"),
    },
)
