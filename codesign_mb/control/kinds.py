"""The controllers by kind (role ``controller`` of :mod:`codesign_mb.core.registry`).

========== ==============================================================================
kind       what
========== ==============================================================================
``sac``    :class:`~codesign_mb.control.sac.SacController`: a SAC-trained actor (checkpoint)
``bc``     the same class: a behaviour-cloned actor (stage A's ``bc.zip``, SAC's start)
``mpc``    :class:`~codesign_mb.control.mpc.MpcController` (``options``: its kwargs)
``scripted`` :class:`~codesign_mb.control.scripted.ScriptedPickController`
``toy_pick`` :class:`~codesign_mb.control.scripted.ToyPickController` (toy plant only)
========== ==============================================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codesign_mb.core.registry import Kind, register

if TYPE_CHECKING:  # the targets, for import-linter and the type checker; imported when built
    from codesign_mb.control import mpc, sac, scripted  # noqa: F401

register(
    "controller",
    {
        "sac": Kind("codesign_mb.control.sac:SacController.load", checkpoint_keyword="path"),
        "bc": Kind("codesign_mb.control.sac:SacController.load", checkpoint_keyword="path"),
        "mpc": Kind("codesign_mb.control.mpc:MpcController.from_env", takes_env=True),
        "scripted": Kind(
            "codesign_mb.control.scripted:ScriptedPickController.from_env", takes_env=True
        ),
        "toy_pick": Kind("codesign_mb.control.scripted:ToyPickController.from_env", takes_env=True),
    },
)
