"""``codesign tune``: the covariance rule's threshold for a success target, on the ``dev`` seeds.

The covariance-triggered rule asks for a packet when the robot's predicted position
uncertainty exceeds ``threshold_m``: the larger the threshold, the fewer packets and, past
some point, the fewer successes. :func:`run_tune` looks for the largest threshold (the least
network) whose success rate on a plant is at least ``target_success``, by bisection on a log
scale (:func:`~codesign_mb.adaptation.rules.tune_threshold`) in ``[low_m, high_m]``; each
probe is ``trials`` episodes of the model-based co-design row (MPC + predictor + the rule,
:func:`~codesign_mb.studies.table_rows.codesign_rule_row`; the rule's other options are the
row's) on the episode seeds of a named seed set, ``dev`` by default and never ``test``
(DESIGN.md, evaluation protocol: what is tuned is chosen on ``dev``, what is reported
comes from ``test``).

"At least the target" is decided on the probe's point estimate (``successes / trials``), as
the bisection needs a yes or no; its 95 % Wilson interval is reported with it, so a reader
sees how sure that is (at 100 episodes a 98 % point estimate has a lower bound of 93 %).
Success is assumed to fall as the threshold grows; on a finite sample it need not, and the
probes are all recorded so a non-monotone run is visible. When no probe reaches the target,
``low_m`` itself is measured: the chosen threshold is always one whose dev figures were
measured, with ``target_met`` saying whether it reached the target. ``limited_by`` says when
the bracket, not the plant, set the answer: ``"high"`` when every probe met the target (a
larger threshold may do as well), ``"low"`` when none did.

The results folder gets ``tune_probes`` (one row per probe, in order, ``chosen`` marking the
chosen one) and ``tune_episodes`` (every episode of every probe), with the config, the
choice and provenance in their metadata; :func:`tuned_entry` is what ``--write`` stores in
the shipped file of :mod:`codesign_mb.studies.tuned`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.adaptation.rules import tune_threshold
from codesign_mb.core.config import (
    EPISODES_CAP,
    WORKERS_CAP,
    Cap,
    check_range,
    from_mapping,
)
from codesign_mb.core.registry import PlantSpec, factory, plant_factory
from codesign_mb.core.results import provenance, to_jsonable, write_results
from codesign_mb.core.seeds import SEED_SETS, seed_set
from codesign_mb.evaluation.evaluate import evaluate, summarize
from codesign_mb.plants.scenarios import DEFAULT_SCENARIO, get_scenario, scenario_options
from codesign_mb.studies.table_rows import TableRow, codesign_rule_row
from codesign_mb.studies.tuned import plant_config, rule_options

__all__ = ["TuneConfig", "TuneResult", "run_tune", "tuned_entry", "write_tune_results"]

_REPORT_SETS = ("test",)

ITERATIONS_CAP = Cap(64, "bisection probes (each halves the bracket's log width)")
"""Seed sets reported numbers come from: never tuned on."""


@dataclass(frozen=True)
class TuneConfig:
    """What ``codesign tune`` searches (``[tune]`` in a config file).

    Parameters
    ----------
    scenario:
        The conveyor scenario tuned for (the key ``--write`` stores the threshold under).
    plant:
        A plant instead of ``scenario`` (e.g. the toy conveyor in tests); its threshold can
        not be written to the shipped file, which is keyed by scenario.
    row:
        The row whose rule is tuned (its QoS kind must be ``rule``); ``None``: the
        model-based co-design row. Its rule options but ``threshold_m`` are kept.
    target_success:
        Success rate (point estimate on the seed set) a threshold must reach.
    trials:
        Episodes per probe.
    workers:
        Worker processes.
    iterations:
        Bisection probes (the bracket's log-width halves with each).
    low_m, high_m:
        The bracket of thresholds (m), ``0 < low_m < high_m``.
    seed_set:
        The named seed set (:data:`~codesign_mb.core.seeds.SEED_SETS`) probed; ``test`` is
        refused.
    """

    scenario: str = DEFAULT_SCENARIO
    plant: PlantSpec | None = None
    row: TableRow | None = None
    target_success: float = 0.98
    trials: int = 100
    workers: int = 1
    iterations: int = 7
    low_m: float = 0.002
    high_m: float = 1.0
    seed_set: str = "dev"

    def __post_init__(self) -> None:
        get_scenario(self.scenario)  # an unknown name names the choices
        if isinstance(self.plant, Mapping):
            object.__setattr__(self, "plant", from_mapping(PlantSpec, self.plant, where="plant"))
        if isinstance(self.row, Mapping):
            object.__setattr__(self, "row", from_mapping(TableRow, self.row, where="row"))
        if self.tuned_row().qos.kind != "rule":
            raise ValueError(f"row qos must be the covariance rule, got {self.tuned_row().qos}")
        if not 0.0 <= self.target_success <= 1.0:
            raise ValueError(f"target_success must be in [0, 1], got {self.target_success}")
        caps = {"trials": EPISODES_CAP, "workers": WORKERS_CAP, "iterations": ITERATIONS_CAP}
        for name, cap in caps.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
            check_range(name, value, cap=cap)
        if not (math.isfinite(self.high_m) and 0.0 < self.low_m < self.high_m):
            raise ValueError(f"need 0 < low_m < high_m, got {self.low_m}, {self.high_m}")
        seed_set(self.seed_set)  # an unknown name names the sets
        if self.seed_set in _REPORT_SETS:
            raise ValueError(
                f"refusing to tune on the {self.seed_set!r} seed set: reported numbers come "
                "from it, so tuning must not see it (use 'dev'; DESIGN.md, evaluation protocol)"
            )

    def tuned_row(self) -> TableRow:
        """The row whose rule is tuned."""
        return self.row if self.row is not None else codesign_rule_row()

    def plant_spec(self) -> PlantSpec:
        """The plant: :attr:`plant`, else the conveyor of :attr:`scenario`."""
        if self.plant is not None:
            return self.plant
        return PlantSpec("conveyor", scenario_options(self.scenario))

    def target_name(self) -> str:
        """What was tuned for: the scenario's name, or ``"plant"`` for a custom plant."""
        return "plant" if self.plant is not None else self.scenario

    def seed(self) -> int:
        """The root seed of :attr:`seed_set`."""
        return SEED_SETS[self.seed_set]


@dataclass(frozen=True)
class TuneResult:
    """What :func:`run_tune` found.

    ``threshold_m`` is the chosen threshold and ``chosen`` its probe (a row of ``probes``);
    ``target_met`` whether its success reached the target; ``limited_by`` ``"high"`` or
    ``"low"`` when the bracket's end set it (module docstring), else ``""``; ``probes`` one
    row per probe
    (``probe``, ``threshold_m``, ``success_rate``, ``success_ci_low``, ``success_ci_high``,
    ``mean_requested_reliability``, ``delivered_fraction``, ``meets_target``, ``chosen``);
    ``episodes`` every episode (with ``probe`` and ``threshold_m``).
    """

    config: TuneConfig
    threshold_m: float
    target_met: bool
    chosen: dict[str, Any]
    probes: pd.DataFrame
    episodes: pd.DataFrame
    wall_time_s: float
    limited_by: str = ""


def run_tune(
    config: TuneConfig, *, progress: Callable[[int, int], None] | None = None
) -> TuneResult:
    """Bisect the rule's threshold on the seed set (module docstring); return every probe.

    ``progress(done, total)`` is called after each probe (``total``: the iterations, one
    more if ``low_m`` has to be measured).
    """
    row = config.tuned_row()
    plant = plant_factory(config.plant_spec())
    controller = factory("controller", row.controller)
    estimator = factory("estimator", row.estimator)
    tables: dict[float, pd.DataFrame] = {}
    started = time.perf_counter()

    def measure(threshold_m: float) -> tuple[float, float]:
        qos = dataclasses.replace(row.qos, options={**row.qos.options, "threshold_m": threshold_m})
        table = evaluate(
            controller,
            estimator,
            factory("qos", qos),
            plant,
            config.trials,
            config.seed(),
            workers=config.workers,
        )
        tables[threshold_m] = table.assign(probe=len(tables), threshold_m=threshold_m)
        if progress is not None:
            progress(len(tables), max(len(tables), config.iterations))
        summary = summarize(table)
        return summary["success_rate"], summary["mean_requested_reliability"]

    best, probes = tune_threshold(
        measure,
        target_success=config.target_success,
        low=config.low_m,
        high=config.high_m,
        iterations=config.iterations,
    )
    feasible = [p.success_rate >= config.target_success for p in probes]
    if not any(feasible):
        measure(config.low_m)  # nothing probed reached the target: measure the fallback
    limited_by = "high" if all(feasible) else "" if any(feasible) else "low"
    frame = _probe_frame(tables, config.target_success, chosen=best)
    chosen = {str(k): v for k, v in frame[frame["chosen"]].iloc[0].items()}
    episodes = pd.concat(tables.values(), ignore_index=True)
    return TuneResult(
        config=config,
        threshold_m=best,
        target_met=bool(chosen["meets_target"]),
        chosen=chosen,
        probes=frame,
        episodes=episodes,
        wall_time_s=round(time.perf_counter() - started, 1),
        limited_by=limited_by,
    )


def _probe_frame(
    tables: Mapping[float, pd.DataFrame], target_success: float, *, chosen: float
) -> pd.DataFrame:
    rows = []
    for threshold_m, table in tables.items():
        s = summarize(table)
        rows.append(
            {
                "probe": int(table["probe"].iloc[0]),
                "threshold_m": threshold_m,
                "trials": s["trials"],
                "success_rate": s["success_rate"],
                "success_ci_low": s["success_ci_low"],
                "success_ci_high": s["success_ci_high"],
                "mean_requested_reliability": s["mean_requested_reliability"],
                "delivered_fraction": s["delivered_fraction"],
                "meets_target": s["success_rate"] >= target_success,
                "chosen": threshold_m == chosen,
                "env_steps": int(table["steps"].sum()),
            }
        )
    return pd.DataFrame(rows)


def _search(result: TuneResult) -> dict[str, Any]:
    """The search's settings and choice, as stored in the results folder and the tuned file."""
    config, chosen = result.config, result.chosen
    row = config.tuned_row()
    return {
        "target": config.target_name(),
        "threshold_m": result.threshold_m,
        "target_success": config.target_success,
        "target_met": result.target_met,
        "limited_by": result.limited_by,
        "success_rate": chosen["success_rate"],
        "success_ci_low": chosen["success_ci_low"],
        "success_ci_high": chosen["success_ci_high"],
        "mean_requested_reliability": chosen["mean_requested_reliability"],
        "seed_set": config.seed_set,
        "seed": config.seed(),
        "episodes_per_probe": config.trials,
        "iterations": config.iterations,
        "bracket_m": [config.low_m, config.high_m],
        "row": row.name,
        "controller": to_jsonable(row.controller),
        "estimator": to_jsonable(row.estimator),
        "rule_options": rule_options(row.qos.options),
        "plant": plant_config(config.plant_spec()),
        "probes": [
            {k: p[k] for k in ("threshold_m", "success_rate", "mean_requested_reliability")}
            for p in result.probes.to_dict("records")
        ],
        "env_steps": int(result.probes["env_steps"].sum()),
        "wall_time_s": result.wall_time_s,
    }


def tuned_entry(result: TuneResult, *, command: str = "") -> dict[str, Any]:
    """The entry ``--write`` stores for the scenario (:mod:`codesign_mb.studies.tuned`)."""
    if result.config.plant is not None:
        raise ValueError("a custom plant's threshold cannot be written: the file is by scenario")
    made = provenance()
    return {
        **_search(result),
        "command": command,
        "commit": made["commit"],
        "versions": made["versions"],
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def write_tune_results(
    result: TuneResult, out_dir: str | Path, *, command: str = ""
) -> dict[str, Path]:
    """Write ``tune_probes`` and ``tune_episodes`` into ``out_dir`` (with provenance)."""
    extra = {**_search(result), "command": command}
    files = {
        "tune_probes": write_results(
            out_dir, table=result.probes, config=result.config, name="tune_probes", extra=extra
        )["json"],
        "tune_episodes": write_results(
            out_dir, table=result.episodes, config=result.config, name="tune_episodes", extra=extra
        )["json"],
    }
    return files
