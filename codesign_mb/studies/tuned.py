"""The covariance rule's tuned thresholds: the shipped file ``codesign tune --write`` fills.

``models/tuned/rule_threshold.json`` (:func:`tuned_file`) holds, per conveyor scenario, the
``threshold_m`` that ``codesign tune`` chose on the ``dev`` seed set
(:mod:`codesign_mb.studies.tune`) with what it was chosen for and how:

``threshold_m``, ``target_success``, ``target_met``, ``limited_by``
    The threshold, the success target, whether the threshold's dev success reached it and
    whether an end of the bracket set it (``"high"``: every probe met the target).
``success_rate``, ``success_ci_low``, ``success_ci_high``, ``mean_requested_reliability``
    The threshold's figures on ``dev`` (a point estimate decided ``target_met``; the interval
    says how sure it is).
``seed_set``, ``seed``, ``episodes_per_probe``, ``iterations``, ``bracket_m``, ``probes``
    The search: the named seed set and its root seed, episodes per probe, the bisection's
    steps and bracket, every probe ``(threshold_m, success_rate,
    mean_requested_reliability)``.
``row``, ``rule_options``, ``plant``
    What the threshold is valid for: the row tuned on, the rule's *effective* options but the
    threshold (:func:`rule_options`: its factory's defaults under the row's options) and the
    plant's full expanded config.
``env_steps``, ``wall_time_s``, ``command``, ``commit``, ``versions``, ``date``
    Its cost and provenance (:func:`codesign_mb.core.results.provenance`).

A table reads it through :func:`rule_threshold`: a plant whose expanded config is that of a
tuned scenario, run with the rule options it was tuned with, gets that scenario's threshold;
any other plant (custom options, a scenario not tuned yet) gets
:data:`RULE_THRESHOLD_DEFAULT_M`, and so does a tuned one whose plant config or rule options
have changed since (a stale value, with a ``RuntimeWarning``). The choice and why is recorded
in the table (``rule_threshold_m``, ``rule_threshold_source``).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from codesign_mb.core.config import from_mapping
from codesign_mb.core.registry import PlantSpec, models_dir
from codesign_mb.core.results import atomic_write, to_jsonable

__all__ = [
    "RULE_THRESHOLD_DEFAULT_M",
    "TUNED",
    "ThresholdChoice",
    "plant_config",
    "read_tuned",
    "rule_defaults",
    "rule_options",
    "rule_threshold",
    "tuned_file",
    "write_tuned",
]

TUNED = "tuned"
"""The value of a rule's ``threshold_m`` that means "the plant's tuned threshold"."""

RULE_THRESHOLD_DEFAULT_M = 0.08
"""The threshold of a plant with no tuned one: hand-picked at 0.2 m/s before the ``dev``/
``test`` protocol existed (on the seeds README reported then), not tuned on ``dev``."""

_FORMAT = 1


def tuned_file() -> Path:
    """The shipped file: ``models/tuned/rule_threshold.json`` in the package's models folder."""
    return models_dir() / "tuned" / "rule_threshold.json"


def rule_defaults() -> dict[str, Any]:
    """The keyword defaults of the covariance rule's factory, ``threshold_m`` included.

    Those of :func:`codesign_mb.rollout.compose.covariance_rule` and
    :class:`~codesign_mb.adaptation.rules.CovarianceTriggeredQos`.
    """
    from codesign_mb.adaptation.rules import CovarianceTriggeredQos
    from codesign_mb.rollout.compose import covariance_rule

    defaults: dict[str, Any] = {}
    for function in (covariance_rule, CovarianceTriggeredQos.__init__):
        for name, p in inspect.signature(function).parameters.items():
            if p.kind is p.KEYWORD_ONLY and p.default is not p.empty:
                defaults[name] = p.default
    return defaults


def rule_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """The covariance rule's effective options but ``threshold_m``, JSON-normalised.

    :func:`rule_defaults` with ``options`` on top: a threshold is tuned for these, so an
    option added to the rule later (or a changed default) makes a stored threshold stale.
    """
    effective = {**rule_defaults(), **options}
    effective.pop("threshold_m", None)
    normalised: dict[str, Any] = to_jsonable(effective)
    return normalised


def plant_config(plant: PlantSpec) -> dict[str, Any]:
    """The plant's full config (every field, defaults included), JSON-normalised."""
    config_class: Any
    if plant.name == "conveyor":
        from codesign_mb.plants.conveyor_config import ConveyorConfig as config_class
    elif plant.name == "toy":
        from codesign_mb.plants.toy import ToyConveyorConfig as config_class
    else:  # a plant kind added later: its options as given
        return {"name": plant.name, "options": to_jsonable(dict(plant.options))}
    config = from_mapping(config_class, dict(plant.options), where="plant.options")
    return {"name": plant.name, "config": to_jsonable(dataclasses.asdict(config))}


def read_tuned(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """Scenario name -> its entry (module docstring); ``{}`` when the file does not exist."""
    file = Path(path) if path is not None else tuned_file()
    if not file.is_file():
        return {}
    data = json.loads(file.read_text())
    if not isinstance(data, Mapping) or data.get("format") != _FORMAT:
        raise ValueError(f"{file} is not a tuned-threshold file of format {_FORMAT}")
    return dict(data.get("scenarios", {}))


def write_tuned(scenario: str, entry: Mapping[str, Any], path: str | Path | None = None) -> Path:
    """Store ``entry`` as ``scenario``'s (replacing its old one, keeping the others); atomic."""
    file = Path(path) if path is not None else tuned_file()
    threshold = entry.get("threshold_m")
    if not (isinstance(threshold, float | int) and math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"entry threshold_m must be a number > 0, got {threshold!r}")
    scenarios = read_tuned(file)
    scenarios[scenario] = to_jsonable(dict(entry))
    data = {
        "format": _FORMAT,
        "description": (
            "Thresholds of the covariance-triggered QoS rule chosen by `codesign tune` on the "
            "dev seed set, per conveyor scenario (codesign_mb/studies/tuned.py)."
        ),
        "scenarios": dict(sorted(scenarios.items())),
    }
    with atomic_write(file, "w") as fh:
        fh.write(json.dumps(data, indent=2, allow_nan=False) + "\n")
    return file


@dataclass(frozen=True)
class ThresholdChoice:
    """The threshold a rule runs with on a plant, and why (``source``, one line)."""

    threshold_m: float
    source: str
    scenario: str = ""


def rule_threshold(
    plant: PlantSpec,
    options: Mapping[str, Any],
    *,
    scenario: str = "",
    path: str | Path | None = None,
) -> ThresholdChoice:
    """The tuned threshold of ``plant`` for a rule with ``options``, else the default.

    A plant matches a tuned scenario when their expanded configs are equal (so the ``0.2``
    preset and ``paper``, the same plant, share one); the rule options must be those it was
    tuned with (:func:`rule_options`). A match whose options differ, or the entry of the
    plant's own ``scenario`` (its name, if it is one) stored for another config, is stale:
    the default, with a ``RuntimeWarning`` saying to rerun ``codesign tune --write``.
    """
    entries = read_tuned(path)
    config = plant_config(plant)
    wanted = rule_options(options)
    default = f"default {RULE_THRESHOLD_DEFAULT_M:g} m"
    stale = []
    if scenario in entries and entries[scenario].get("plant") != config:
        stale.append(f"{scenario} (tuned on another plant config)")
    for name, entry in entries.items():
        if entry.get("plant") != config:
            continue
        if entry.get("rule_options") != wanted:
            stale.append(f"{name} (tuned with rule options {entry.get('rule_options')})")
            continue
        return ThresholdChoice(
            float(entry["threshold_m"]),
            f"tuned on {entry['seed_set']} for {name} ({entry['episodes_per_probe']} "
            f"episodes per probe, target {entry['target_success']:g}, "
            f"{'met' if entry['target_met'] else 'NOT met'}"
            f"{', at the top of its bracket' if entry.get('limited_by') == 'high' else ''})",
            name,
        )
    if stale:
        why = f"tuned value stale for {', '.join(stale)}; rule options now {wanted}"
        warnings.warn(
            f"rule threshold: {why}; using the {default} (rerun `codesign tune --write`)",
            RuntimeWarning,
            stacklevel=2,
        )
        return ThresholdChoice(RULE_THRESHOLD_DEFAULT_M, f"{default}: {why}")
    return ThresholdChoice(RULE_THRESHOLD_DEFAULT_M, f"{default}: no tuned value for this plant")
