"""Locate the robot and scene descriptions shipped as package data (``codesign_mb.models``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["PANDA_URDF", "SCENE_XML", "asset_path"]

PANDA_URDF = "panda/panda.urdf"
"""The Panda arm + gripper description, read by both MuJoCo and Pinocchio."""

SCENE_XML = "scene_conveyor.xml"
"""The conveyor scene (table, belt, cameras) the robot is attached to."""


def asset_path(relative: str) -> Path:
    """Filesystem path of a file in ``codesign_mb.models`` (the repository's ``models/``).

    Raises
    ------
    FileNotFoundError
        If the asset is missing, with how to fix it (the package data was not installed).
    """
    try:
        root = resources.files("codesign_mb.models")
    except ModuleNotFoundError as exc:  # pragma: no cover - broken install
        raise FileNotFoundError(_missing(relative)) from exc
    path = Path(str(root.joinpath(relative)))
    if not path.is_file():
        raise FileNotFoundError(_missing(relative))
    return path


def _missing(relative: str) -> str:
    return (
        f"robot asset {relative!r} not found in the package data codesign_mb.models; "
        "reinstall the package so that models/ is included (from the repository: "
        "`pip install -e .`, or rebuild the wheel), and check that models/"
        f"{relative} exists"
    )
