"""The studies of ``codesign paper``: their names, settings and equivalent commands.

:class:`PaperConfig` is what ``codesign paper`` runs; :func:`study_settings` gives each
study's settings (what determines its results) and :func:`study_command` the ``codesign``
command that computes the same results. :mod:`codesign_mb.studies.paper` runs them
(resuming) and writes the manifest: what is run is here, how it is run is there.

The studies are the existing ones, called with the settings README's results section needs,
each on the ``test`` seed set (:data:`~codesign_mb.core.seeds.SEED_SETS`) and each into its
own subfolder of the results folder ``OUT``:

``lqg/``
    The linear baseline, :func:`~codesign_mb.studies.demo.run_lqg_demo`
    (``codesign demo --scenario lqg``): table ``lqg``, one row per reliability.
``table_realistic/``, ``table_variable/``
    :func:`~codesign_mb.studies.table_figures.run_table_study` with the model-based rows and
    their reference rows on that scenario (``codesign table --scenario NAME --pipeline
    model-based``): ``tab_p``, ``tab_p_episodes``, ``tab_p.md``, ``fig_pareto.png``, Fig. 5;
    the QoS planner's row also gets its clairvoyant-schedule ``bound`` row (:data:`BOUND_ROWS`).
``table_model_free/``
    The paper's Table I (``--scenario paper --pipeline model-free``): its learned rows and their
    references, pooled over three evaluation seeds (:data:`POOLED_SEEDS`; ``--seeds``).
``table_paper/``
    The same with every row, learned ones included (``--scenario paper --pipeline all``; the
    learned checkpoints were trained on the paper scenario only).
``fig_cn/``
    Fig. 4, :func:`~codesign_mb.studies.fig_cn.run_fig_cn_study` (``codesign evaluate fig-cn``).
``fig_wifi/``
    Fig. 6, :func:`~codesign_mb.studies.fig_wifi_figures.run_capacity_study` with the grid of
    ``configs/fig_wifi.toml`` (:data:`FIG_WIFI_GRID`; ``codesign wifi capacity -c
    configs/fig_wifi.toml``).
``figures/<study>/``
    ``codesign report`` of each study's folder (:func:`~codesign_mb.studies.report.build_report`:
    the figures by their one renderer and a ``report.md``).
"""

from __future__ import annotations

import shlex
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from codesign_mb.core.config import EPISODES_CAP, WORKERS_CAP, check_range
from codesign_mb.core.results import to_jsonable
from codesign_mb.core.seeds import seed_set
from codesign_mb.studies.table_rows import PLANNER_ROW

__all__ = [
    "BOUND_ROWS",
    "FIG_WIFI_GRID",
    "POOLED_SEEDS",
    "STUDIES",
    "TABLE_STUDIES",
    "PaperConfig",
    "study_command",
    "study_settings",
]

TABLE_STUDIES: dict[str, tuple[str, str]] = {
    "table_realistic": ("realistic", "model-based"),
    "table_variable": ("variable", "model-based"),
    "table_model_free": ("paper", "model-free"),
    "table_paper": ("paper", "all"),
    "table_learned_realistic": ("realistic", "learned"),
    "table_learned_variable": ("variable", "learned"),
}
"""Table study -> (scenario, pipeline). The learned rows' checkpoints are the paper scenario's,
but for ``table_learned_*``'s (the learned stack trained on ``realistic``, issue 30; on
``variable`` it meets belts it was not trained on)."""

BOUND_ROWS: dict[str, tuple[str, ...]] = {
    "table_realistic": (PLANNER_ROW,),
    "table_variable": (PLANNER_ROW,),
}
"""Table study -> the co-design rows that get a clairvoyant-schedule ``bound`` row
(:mod:`~codesign_mb.studies.table_bound`; issue 34): the benchmarks' best co-design."""

POOLED_SEEDS: dict[str, int] = {"table_model_free": 3}
"""Table study -> how many evaluation root seeds it pools (the set's root and the next ones):
Table I, whose learned rows vary from one evaluation seed to the next."""

STUDIES: tuple[str, ...] = ("lqg", *TABLE_STUDIES, "fig_cn", "fig_wifi", "figures")
"""Every study of the run, in run order (``figures`` renders the others, so it comes last)."""

FIG_WIFI_GRID: dict[str, Any] = {
    "stack": "realistic",
    "robots": (1, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 24, 28, 32, 40, 48),
    "channels": ("paper",),
    "schedulers": ("greedy", "convex"),
    "stop_below": 0.5,
    "episodes_per_robot": 1,
    "warmup_episodes": 1,
}
"""Fig. 6's grid, the same as ``configs/fig_wifi.toml`` (a test checks they agree)."""

_SMOKE: dict[str, dict[str, Any]] = {
    "lqg": {"episodes": 2, "horizon": 40},
    "table": {"trials": 1},
    "fig_cn": {"trials": 1, "delays": (0, 3), "reliabilities": (1.0, 0.2)},
    "fig_wifi": {
        "trials": 1,
        "robots": (1, 2),
        "channels": ("paper",),
        "schedulers": ("greedy",),
        "max_steps": 40,
    },
}
"""Tiny settings (``smoke``): every code path, a few episodes each."""


@dataclass(frozen=True)
class PaperConfig:
    """What ``codesign paper`` runs.

    Parameters
    ----------
    trials:
        Episodes per row and plant of the tables.
    realistic_trials:
        Episodes per row of the benchmark scenarios' tables, ``realistic`` and ``variable``
        (their ``blind`` and ``oracle`` references are read at 200 episodes).
    model_free_trials:
        Episodes per row and evaluation seed of Table I (``table_model_free``).
    fig_cn_trials:
        Episodes per point of Fig. 4 (64 points).
    wifi_trials:
        Trials (N-robot episodes) per point of Fig. 6 (a point's success is pooled over its
        ``trials x N`` robot-episodes).
    lqg_episodes:
        Episodes per reliability of the linear baseline.
    workers:
        Worker processes of every study (results do not depend on it); ``None``: 2, or 1
        with ``smoke`` (starting a pool costs more than a few episodes).
    seeds:
        The named seed set every study runs on (``test``: reported numbers).
    only, skip:
        Study names (:data:`STUDIES`) to run only, or to leave out.
    smoke:
        Tiny settings (a few episodes per study) to check the whole run quickly.
    force:
        Rerun studies whose folder is complete with the same settings.
    """

    trials: int = 100
    realistic_trials: int = 200
    model_free_trials: int = 200
    fig_cn_trials: int = 100
    wifi_trials: int = 20
    lqg_episodes: int = 8
    workers: int | None = None
    seeds: str = "test"
    only: tuple[str, ...] = ()
    skip: tuple[str, ...] = ()
    smoke: bool = False
    force: bool = False

    def __post_init__(self) -> None:
        numbers = (
            "trials",
            "realistic_trials",
            "model_free_trials",
            "fig_cn_trials",
            "wifi_trials",
            "lqg_episodes",
        )
        for name in (*numbers, "workers"):
            value = getattr(self, name)
            if name == "workers" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
            check_range(name, value, cap=WORKERS_CAP if name == "workers" else EPISODES_CAP)
        seed_set(self.seeds)  # an unknown name names the sets
        for name in ("only", "skip"):
            value = tuple(getattr(self, name))
            object.__setattr__(self, name, value)
            unknown = [s for s in value if s not in STUDIES]
            if unknown:
                raise ValueError(
                    f"{name} must name studies among {', '.join(STUDIES)}, got {unknown!r}"
                )

    def worker_count(self) -> int:
        """``workers``, or its default: 2, or 1 with ``smoke``."""
        return self.workers if self.workers is not None else 1 if self.smoke else 2

    def selected(self) -> tuple[str, ...]:
        """The studies to run, in run order."""
        return tuple(s for s in STUDIES if (not self.only or s in self.only) and s not in self.skip)


# -- settings and commands ----------------------------------------------------------------------
def study_settings(name: str, config: PaperConfig) -> dict[str, Any]:
    """The settings that determine study ``name``'s results (JSON types); not ``figures``'.

    Worker counts are not settings: the results do not depend on them.
    """
    seed = seed_set(config.seeds)
    smoke = config.smoke
    if name == "lqg":
        settings: dict[str, Any] = {"episodes": config.lqg_episodes, "seed": seed}
        settings.update(_SMOKE["lqg"] if smoke else {})
    elif name in TABLE_STUDIES:
        scenario, pipeline = TABLE_STUDIES[name]
        benchmark = scenario in ("realistic", "variable")
        trials = config.realistic_trials if benchmark else config.trials
        if name in POOLED_SEEDS:
            trials = config.model_free_trials
        settings = {"scenario": scenario, "pipeline": pipeline, "trials": trials}
        settings.update(_SMOKE["table"] if smoke else {}, seed=seed)
        if name in POOLED_SEEDS:
            settings["root_seeds"] = [seed + k for k in range(POOLED_SEEDS[name])]
        if name in BOUND_ROWS:
            settings["bound"] = list(BOUND_ROWS[name])
    elif name == "fig_cn":
        settings = {"trials": config.fig_cn_trials, "seed": seed}
        settings.update(_SMOKE["fig_cn"] if smoke else {})
    elif name == "fig_wifi":
        settings = {**FIG_WIFI_GRID, "trials": config.wifi_trials, "seed": seed}
        settings.update(_SMOKE["fig_wifi"] if smoke else {})
    else:
        raise ValueError(f"study must be one of {', '.join(STUDIES[:-1])}, got {name!r}")
    return dict(to_jsonable({**settings, "seeds": config.seeds}))


def study_command(name: str, settings: Mapping[str, Any]) -> str:
    """The ``codesign`` command that computes the same results as study ``name``."""
    s, seed = dict(settings), f"--seed {settings.get('seed', 0)}"
    if name == "lqg":
        extra = f" --horizon {s['horizon']}" if "horizon" in s else ""
        return f"codesign demo --scenario lqg -n {s['episodes']}{extra} {seed}"
    if name in TABLE_STUDIES:
        if s.get("root_seeds"):
            seed = "--seeds " + ",".join(str(k) for k in s["root_seeds"])
        bound = "".join(f" --bound {shlex.quote(row)}" for row in s.get("bound", ()))
        return (
            f"codesign table --scenario {s['scenario']} --pipeline {s['pipeline']} "
            f"-n {s['trials']} {seed}{bound}"
        )
    if name == "fig_cn":
        grid = "".join(f" --delay {d}" for d in s.get("delays", ()))
        grid += "".join(f" -q {q:g}" for q in s.get("reliabilities", ()))
        return f"codesign evaluate fig-cn -n {s['trials']}{grid} {seed}"
    if name == "fig_wifi":
        base = f"codesign wifi capacity -c configs/fig_wifi.toml --trials {s['trials']} {seed}"
        if {k: s[k] for k in FIG_WIFI_GRID} == to_jsonable(FIG_WIFI_GRID) and "max_steps" not in s:
            return base
        robots = ",".join(str(n) for n in s["robots"])
        return (
            f"codesign wifi capacity --stack {s['stack']} --robots {robots} "
            f"--channels {','.join(s['channels'])} --schedulers {','.join(s['schedulers'])} "
            f"--stop-below {s['stop_below']:g} --trials {s['trials']}"
            + (f" --max-steps {s['max_steps']}" if s.get("max_steps") else "")
            + f" {seed}"
        )
    if name == "figures":
        return "codesign report OUT/<study> -o OUT/figures/<study>"
    raise ValueError(f"study must be one of {', '.join(STUDIES)}, got {name!r}")
