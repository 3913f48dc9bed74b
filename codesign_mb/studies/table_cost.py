"""Table I's cost columns: missing checkpoints, training cost, CPU time per control step.

:func:`training_cost` follows a row's learned checkpoints through what each was trained from
(a stage-D estimator continues stage B's under stage C's policy; a stage-D QoS policy is
warm-started from stage C; a stage-B estimator is trained on the stage-A controller's
episodes) and sums the ``training.json`` records, each file once. :func:`timed_factory`
wraps a component so its per-step method (``act``, ``estimate``, ``request``) reports its
CPU time per call (``time.process_time``) in the episode's metrics.

A *row* here is anything with ``controller``, ``estimator`` and ``qos``
:class:`~codesign_mb.core.registry.ComponentSpec` attributes
(:class:`~codesign_mb.studies.table.TableRow`).
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from codesign_mb.core.registry import (
    ComponentSpec,
    Factory,
    PlantSpec,
    factory,
    make_plant,
    models_dir,
    resolve_checkpoint,
)
from codesign_mb.core.results import read_json_table

__all__ = [
    "CPU_COLUMNS",
    "RowLike",
    "TrainingCost",
    "incompatible_checkpoints",
    "missing_checkpoints",
    "timed_component",
    "timed_factory",
    "training_cost",
]

CPU_COLUMNS = ("controller_cpu_ms", "estimator_cpu_ms", "qos_cpu_ms")
"""Per-episode columns: CPU ms per call of ``act``, ``estimate`` and ``request``."""


class RowLike(Protocol):
    """A table row: its three components."""

    @property
    def controller(self) -> ComponentSpec: ...

    @property
    def estimator(self) -> ComponentSpec: ...

    @property
    def qos(self) -> ComponentSpec: ...


def _specs(row: RowLike) -> tuple[tuple[str, ComponentSpec], ...]:
    return (("controller", row.controller), ("estimator", row.estimator), ("qos", row.qos))


def missing_checkpoints(row: RowLike) -> list[str]:
    """The checkpoints ``row`` names that do not exist (a QoS folder needs its policy files)."""
    missing = []
    for _, spec in _specs(row):
        if not spec.checkpoint:
            continue
        try:
            path = resolve_checkpoint(spec.checkpoint)
        except ValueError:
            missing.append(spec.checkpoint)
            continue
        if spec.kind == "learned" and not all(
            (path / f).is_file() for f in ("model.zip", "qos_policy.json")
        ):
            missing.append(f"{spec.checkpoint} (no model.zip + qos_policy.json)")
    return missing


def incompatible_checkpoints(row: RowLike, plant: PlantSpec) -> list[str]:
    """The checkpoints of ``row`` trained on a plant whose observation differs from ``plant``'s.

    A learned component reads the observation layout it was trained on (the plant in its
    folder's ``training.json``): another belt speed is a fair test of generalisation, another
    layout (e.g. the ``realistic`` scenario's packet without the object's velocity) cannot
    be fed to it at all. Checkpoints without a recorded plant are not judged here.
    """
    found = []
    for _, spec in _specs(row):
        trained = _trained_plant(spec)
        if trained is None:  # a model-based component: no plant is built to judge it
            continue
        signature = _observation_signature(trained.name, _options_key(trained.options))
        if signature != _observation_signature(plant.name, _options_key(plant.options)):
            found.append(f"{spec.checkpoint} (trained on another observation layout)")
    return found


def _trained_plant(spec: ComponentSpec) -> PlantSpec | None:
    """The plant in the ``training.json`` beside ``spec``'s checkpoint, if it records one."""
    if not spec.checkpoint:
        return None
    try:
        path = resolve_checkpoint(spec.checkpoint)
    except ValueError:
        return None
    meta_path = path / "training.json" if path.is_dir() else path.parent / "training.json"
    meta = _training_json(meta_path)
    if meta is None:
        return None
    config = meta.get("config")
    plant = config.get("plant") if isinstance(config, Mapping) else None
    if not isinstance(plant, Mapping) or not isinstance(plant.get("name"), str):
        return None
    return PlantSpec(plant["name"], dict(plant.get("options") or {}))


def _training_json(path: Path) -> dict[str, Any] | None:
    """A checkpoint's ``training.json``; ``None`` when absent, or corrupt (with a warning)."""
    return read_json_table(path, otherwise="its training is not counted", stacklevel=3)


def _options_key(options: Mapping[str, Any]) -> str:
    return json.dumps(dict(options), sort_keys=True, default=str)


@functools.lru_cache(maxsize=32)
def _observation_signature(name: str, options_key: str) -> tuple[Any, ...]:
    """What a learned component's input depends on: the layout's names and sizes."""
    env = make_plant(PlantSpec(name, json.loads(options_key)))
    try:
        plant = env.unwrapped
        layout = getattr(plant, "observation_layout", None)
        if layout is None:
            return ("shape", tuple(env.observation_space.shape))
        return tuple((key, s.start, s.stop) for key, s in layout.items())
    finally:
        env.close()


@dataclass(frozen=True)
class TrainingCost:
    """What it took to train a row's learned components (see :func:`training_cost`)."""

    env_steps: int
    wall_time_s: float
    sources: tuple[str, ...]
    unknown: tuple[str, ...] = ()


def _display(path: Path) -> str:
    try:
        return str(path.relative_to(models_dir()))
    except ValueError:
        return str(path)


def training_cost(row: RowLike) -> TrainingCost:
    """Env steps and wall time of every training run behind ``row``'s learned components.

    For each learned checkpoint (file: its folder's ``training.json``; folder: its own), the
    ``env_steps`` (plus the ``demonstrations.demo_steps`` of stage A) and ``wall_time_s``
    recorded there are counted, then the checkpoints its ``config`` names (``controller``,
    ``estimator``, ``warm_start``, ``qos_policy``), recursively; every file is counted once.
    The estimator of a stage-D folder counts the folder's ``estimator`` section only (its QoS
    policy has its own ``qos/training.json``). Model-based components count 0; the covariance
    rule's threshold is tuned by ``codesign tune`` on the ``dev`` seeds (its episodes are in
    the tuned file, ``env_steps``) and counts 0 here (named in ``sources``). Checkpoints
    without a ``training.json`` are listed in ``unknown`` (the sums are then lower bounds).
    """
    todo = [(role, spec.checkpoint) for role, spec in _specs(row) if spec.checkpoint]
    seen: dict[tuple[str, str], tuple[int, float, str]] = {}
    unknown: list[str] = []
    while todo:
        role, checkpoint = todo.pop(0)
        try:
            path = resolve_checkpoint(checkpoint)
        except ValueError:
            unknown.append(str(checkpoint))
            continue
        meta_path = path / "training.json" if path.is_dir() else path.parent / "training.json"
        meta = _training_json(meta_path)
        if meta is None:
            unknown.append(str(checkpoint))
            continue
        section, part, label = meta, "", _display(meta_path.parent)
        sub = meta.get("estimator")
        if role == "estimator" and isinstance(sub, Mapping) and "env_steps" in sub:
            section, part, label = sub, "estimator", f"{label} (estimator)"
        key = (str(meta_path), part)
        if key in seen:
            continue
        steps = int(section.get("env_steps") or 0)
        if section is meta and isinstance(meta.get("demonstrations"), Mapping):
            steps += int(meta["demonstrations"].get("demo_steps") or 0)
        wall = section.get("wall_time_s")
        seen[key] = (steps, math.nan if wall is None else float(wall), label)
        config = meta.get("config")
        if not isinstance(config, Mapping):
            continue
        for sub_role in ("controller", "estimator"):
            ref = config.get(sub_role)
            if isinstance(ref, Mapping) and ref.get("checkpoint"):
                todo.append((sub_role, str(ref["checkpoint"])))
        for ref_key in ("warm_start", "qos_policy"):
            ref = config.get(ref_key)
            if isinstance(ref, str) and ref:
                todo.append(("qos", ref))
    sources = [label for _, _, label in seen.values()]
    if any(spec.kind == "rule" for _, spec in _specs(row)):
        sources.append("rule threshold (codesign tune on dev, not counted)")
    return TrainingCost(
        env_steps=sum(s for s, _, _ in seen.values()),
        wall_time_s=float(sum(w for _, w, _ in seen.values())),
        sources=tuple(sources),
        unknown=tuple(dict.fromkeys(unknown)),
    )


# -- CPU time per step ------------------------------------------------------------------------
class _Timed:
    """Forwards to a component, summing the CPU time of its per-step method."""

    method = ""
    role = ""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self._ns = 0
        self._calls = 0

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)

    def reset(self, *args: Any, **kwargs: Any) -> Any:
        self._ns = self._calls = 0
        return self._inner.reset(*args, **kwargs)

    def _call(self, *args: Any) -> Any:
        start = time.process_time_ns()
        out = getattr(self._inner, self.method)(*args)
        self._ns += time.process_time_ns() - start
        self._calls += 1
        return out

    def episode_metrics(self) -> dict[str, float]:
        inner = getattr(self._inner, "episode_metrics", None)
        out = dict(inner()) if callable(inner) else {}
        out[f"{self.role}_cpu_ms"] = self._ns / 1e6 / self._calls if self._calls else math.nan
        return out


class _TimedController(_Timed):
    method, role = "act", "controller"

    def act(self, *args: Any) -> Any:
        return self._call(*args)


class _TimedEstimator(_Timed):
    method, role = "estimate", "estimator"

    def estimate(self, *args: Any) -> Any:
        return self._call(*args)


class _TimedQos(_Timed):
    method, role = "request", "qos"

    def request(self, *args: Any) -> Any:
        return self._call(*args)


_TIMED = {"controller": _TimedController, "estimator": _TimedEstimator, "qos": _TimedQos}


def timed_component(env: Any, *, role: str, inner: Any) -> Any:
    """Build ``inner`` (a factory) for ``env`` and time its per-step method (a Factory target)."""
    return _TIMED[role](inner(env))


def timed_factory(role: str, spec: ComponentSpec) -> Factory:
    """A picklable factory of the ``role`` component ``spec``, timed per call (CPU ms)."""
    return Factory(
        "codesign_mb.studies.table_cost:timed_component",
        {"role": role, "inner": factory(role, spec)},
        takes_env=True,
    )
