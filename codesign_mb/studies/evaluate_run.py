"""``codesign evaluate``: one configuration's seeded episodes, written with their summary.

:func:`run_evaluation` runs the episodes of an
:class:`~codesign_mb.evaluation.evaluate.EvaluateConfig` (in parallel,
:func:`~codesign_mb.evaluation.evaluate.run_config`), summarises them
(:func:`~codesign_mb.evaluation.evaluate.summarize`: success with its Wilson interval, QoS,
age and, with an MPC, its solve times and failed solves) and writes both into a results
folder. Every finished episode is kept in the folder's record store as it finishes
(:mod:`codesign_mb.core.records`), so an interrupted run resumes without recomputing.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.records import RECORDS_DIR, RecordStore
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
    (``<name>_summary.json``); ``computed`` and ``reused``: episodes run now and taken from
    an earlier run's records.
    """

    table: pd.DataFrame
    summary: dict[str, Any]
    files: dict[str, Path] = field(default_factory=dict)
    computed: int = 0
    reused: int = 0


def run_evaluation(
    config: EvaluateConfig,
    out_dir: str | Path,
    *,
    name: str = "evaluate",
    progress: Callable[[int, int], None] | None = None,
    fresh: bool = False,
) -> EvaluationOutputs:
    """Run ``config``'s episodes and write ``<name>.{parquet,csv,json}`` and its summary.

    ``progress(done, total)`` is called after each episode (e.g. a progress bar). Finished
    episodes are kept in ``<out_dir>/.records`` and reused by a rerun (``fresh``: none are).
    The summary is also in the table's metadata (``extra.summary``).
    """
    store = RecordStore(Path(out_dir) / RECORDS_DIR, fresh=fresh)
    with store.on_interrupt():
        table, summary = run_config(config, progress=progress, store=store)
    extra = {"summary": summary, "computed": store.computed, "reused": store.reused}
    files = dict(write_results(out_dir, table=table, config=config, name=name, extra=extra))
    files["summary"] = Path(out_dir) / f"{name}_summary.json"
    with atomic_write(files["summary"], "w") as fh:
        fh.write(json.dumps(to_jsonable(summary), indent=2) + "\n")
    return EvaluationOutputs(table, summary, files, store.computed, store.reused)
