"""Checkpoint paths as the stages record them in JSON: portable, never absolute.

A ``training.json`` or ``qos_policy.json`` names the checkpoints its run was built from
(``controller.checkpoint``, ``estimator.checkpoint``, ``warm_start``, ``qos_policy``). They are
written relative to the package's ``models`` folder when they lie inside it (the form every
shipped config uses, ``checkpoints/stage_a/model.zip``), else relative to the folder holding
the JSON file, so a checkpoint folder can be moved or installed elsewhere and still be read.
:func:`resolve_recorded` reads them back: the JSON file's folder first, then
:func:`~codesign_mb.core.registry.resolve_checkpoint` (working directory, ``models``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from codesign_mb.adaptation.learned import LearnedQosPolicy
from codesign_mb.core.registry import ComponentSpec, models_dir, resolve_checkpoint

__all__ = [
    "PATH_KEYS",
    "portable_path",
    "portable_paths",
    "recorded_components",
    "resolve_recorded",
]

PATH_KEYS = ("checkpoint", "warm_start", "qos_policy")
"""The keys whose string values are checkpoint paths, at any depth of a recorded mapping."""


def portable_path(path: str | Path, base: str | Path) -> str:
    """``path`` as recorded in a JSON file in the folder ``base``.

    Relative to :func:`~codesign_mb.core.registry.models_dir` when the checkpoint lies inside
    it, else relative to ``base``; a path that does not resolve is kept as given.
    """
    try:
        target = resolve_checkpoint(path)
    except ValueError:
        return str(path)
    models = models_dir()
    if target.is_relative_to(models):
        return target.relative_to(models).as_posix()
    return Path(os.path.relpath(target, Path(base).resolve())).as_posix()


def portable_paths(data: Any, base: str | Path) -> Any:
    """A copy of ``data`` (JSON-like) with every :data:`PATH_KEYS` string made portable."""
    if isinstance(data, Mapping):
        return {
            k: portable_path(v, base)
            if k in PATH_KEYS and isinstance(v, str) and v
            else portable_paths(v, base)
            for k, v in data.items()
        }
    if isinstance(data, list | tuple):
        return [portable_paths(v, base) for v in data]
    return data


def resolve_recorded(path: str | Path, base: str | Path) -> Path:
    """The checkpoint a JSON file in the folder ``base`` recorded as ``path``.

    Relative paths are looked up in ``base`` first, then as
    :func:`~codesign_mb.core.registry.resolve_checkpoint` does (``ValueError`` if absent).
    """
    p = Path(path).expanduser()
    if not p.is_absolute() and (Path(base) / p).exists():
        return (Path(base) / p).resolve()
    return resolve_checkpoint(p)


def recorded_components(policy_dir: str | Path) -> dict[str, ComponentSpec]:
    """The controller and estimator a saved QoS policy was trained for, checkpoints resolved.

    Read from its ``qos_policy.json`` (written by stage C); roles it does not record are absent.
    """
    policy_dir = Path(policy_dir)
    meta = LearnedQosPolicy.read_meta(policy_dir)
    out: dict[str, ComponentSpec] = {}
    for role in ("controller", "estimator"):
        entry = meta.get(role)
        if not isinstance(entry, Mapping):
            continue
        checkpoint = entry.get("checkpoint")
        if checkpoint:
            checkpoint = str(resolve_recorded(checkpoint, policy_dir))
        out[role] = ComponentSpec(entry["kind"], checkpoint, dict(entry.get("options") or {}))
    return out
