"""``codesign evaluate``: one configuration's seeded episodes, written with their summary.

:func:`run_evaluation` runs the episodes of an
:class:`~codesign_mb.evaluation.evaluate.EvaluateConfig` (in parallel,
:func:`~codesign_mb.evaluation.evaluate.run_config`), summarises them
(:func:`~codesign_mb.evaluation.evaluate.summarize`: success with its Wilson interval, QoS,
age and, with an MPC, its solve times and failed solves) and writes both into a results
folder.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.results import atomic_write, to_jsonable, write_results
from codesign_mb.evaluation.evaluate import EvaluateConfig, run_config

__all__ = ["EvaluationOutputs", "evaluation_label", "run_evaluation"]


def evaluation_label(config: EvaluateConfig) -> str:
    """A short name of the configuration: ``"mpc+predictor q=0.8 tau=1 (paper)"``."""
    return (
        f"{config.controller}+{config.estimator} q={config.reliability:g} "
        f"tau={config.latency_steps} ({config.scenario})"
    )


@dataclass(frozen=True)
class EvaluationOutputs:
    """What :func:`run_evaluation` wrote.

    ``files``: ``parquet``, ``csv``, ``json`` (the per-episode table) and ``summary``
    (``<name>_summary.json``).
    """

    table: pd.DataFrame
    summary: dict[str, Any]
    files: dict[str, Path] = field(default_factory=dict)


def run_evaluation(
    config: EvaluateConfig,
    out_dir: str | Path,
    *,
    name: str = "evaluate",
    progress: Callable[[int, int], None] | None = None,
) -> EvaluationOutputs:
    """Run ``config``'s episodes and write ``<name>.{parquet,csv,json}`` and its summary.

    ``progress(done, total)`` is called after each episode (e.g. a progress bar).
    The summary is also in the table's metadata (``extra.summary``).
    """
    table, summary = run_config(config, progress=progress)
    files = dict(
        write_results(out_dir, table=table, config=config, name=name, extra={"summary": summary})
    )
    files["summary"] = Path(out_dir) / f"{name}_summary.json"
    with atomic_write(files["summary"], "w") as fh:
        fh.write(json.dumps(to_jsonable(summary), indent=2) + "\n")
    return EvaluationOutputs(table, summary, files)
