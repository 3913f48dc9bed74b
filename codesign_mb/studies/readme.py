"""README's results section, rendered from stored results: nothing in it is typed by hand.

Two steps, so that the README can be checked without rerunning anything:

1. :func:`export_results` reads a ``codesign paper`` folder
   (:mod:`codesign_mb.studies.paper`) and writes its compact form into ``docs/``:
   ``docs/results/<study>.json``, one small JSON per study (the summary rows the README
   shows: success with its Wilson interval, reliabilities, costs, capacities; with the
   study's command, settings, seed set, wall time and commit; numbers to 6 significant
   digits), ``docs/results/paper.json`` (the run: wall times, provenance) and the study
   figures as ``docs/figures/*.png``. Per-episode tables stay in the results folder.
2. :func:`render_results` turns ``docs/results/`` into the Markdown of the results section
   and :func:`replace_block` puts it between :data:`BEGIN` and :data:`END` in README.md.
   A test renders the committed ``docs/results/`` and fails when README's block differs.

The Markdown tables of the studies are in :mod:`codesign_mb.studies.readme_tables`.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.results import ResultsDir, atomic_write, to_jsonable
from codesign_mb.plants.outcomes import FAILURE_REASONS
from codesign_mb.plants.phases import PHASES
from codesign_mb.studies.paper import MANIFEST, SUMMARY_KEYS, read_study, study_summary
from codesign_mb.studies.paper_studies import STUDIES, TABLE_STUDIES
from codesign_mb.studies.readme_crosscheck import CROSSCHECK_FILE, crosscheck_section
from codesign_mb.studies.readme_tables import SECTIONS, header, wall_times

__all__ = [
    "BEGIN",
    "END",
    "FIGURES",
    "export_results",
    "read_block",
    "render_results",
    "replace_block",
    "update_readme",
]

BEGIN = "<!-- results:begin -->"
END = "<!-- results:end -->"
"""The markers of README's generated block."""

FIGURES: dict[str, dict[str, str]] = {
    **{
        name: {"fig_pareto.png": f"fig_pareto_{scenario}.png"}
        for name, (scenario, _) in TABLE_STUDIES.items()
    },
    "table_model_free": {"fig_pareto.png": "fig_pareto_model_free.png"},
    "table_learned_realistic": {"fig_pareto.png": "fig_pareto_learned_realistic.png"},
    "table_learned_variable": {"fig_pareto.png": "fig_pareto_learned_variable.png"},
    "table_paper": {"fig_pareto.png": "fig_pareto_paper.png", "fig_lat.png": "fig_lat_paper.png"},
    "fig_cn": {"fig_cn.png": "fig_cn.png"},
    "fig_wifi": {"fig_wifi.png": "fig_wifi.png"},
}
"""Study -> {figure in its folder: name in ``docs/figures``}."""

_TABLE_COLUMNS = (
    "plant",
    "row",
    "kind",
    "reference",
    "reference_of",
    "status",
    "success_rate",
    "success_ci_low",
    "success_ci_high",
    "mean_requested_reliability",
    "delivered_fraction",
    "paper_success_rate",
    "paper_mean_reliability",
    "pareto",
    "rule_threshold_m",
    "success_by_seed",
    "mean_time_to_grasp_s",
    *(f"failures_{reason}" for reason in FAILURE_REASONS),
    *(f"est_error_mm_{phase}" for phase in PHASES),
    *(f"nees_{phase}{end}" for phase in PHASES for end in ("", "_low", "_high")),
    *(f"nees_inside_{phase}" for phase in PHASES),
)
_FIG_CN_COLUMNS = (
    "sweep",
    "belt_speed_mps",
    "estimator",
    "latency_steps",
    "reliability",
    "trials",
    "successes",
    "success_rate",
    "success_ci_low",
    "success_ci_high",
)


# -- 1. the compact form ---------------------------------------------------------------------------
def _records(frame: pd.DataFrame, columns: tuple[str, ...]) -> list[dict[str, Any]]:
    return list(frame[[c for c in columns if c in frame.columns]].to_dict("records"))


def _summary(name: str, folder: Path) -> dict[str, Any]:
    """The numbers README shows of study ``name``, read from its results folder."""
    results = ResultsDir(folder)
    if name == "lqg":
        extra = results.meta("lqg")["extra"]
        return {**extra, "rows": results.table("lqg").to_dict("records")}
    if name in TABLE_STUDIES:
        return {"rows": _records(results.table("tab_p"), _TABLE_COLUMNS)}
    if name == "fig_cn":
        return {"points": _records(results.table("fig_cn"), _FIG_CN_COLUMNS)}
    if name == "fig_wifi":
        from codesign_mb.studies.fig_wifi import capacity_ratios, capacity_table, describe_channel

        config = results.config("fig_wifi")
        target = float(config.get("success_target", 0.95))
        stop = float(config.get("stop_below", 0.0))
        curves = capacity_table(results.table("fig_wifi"), success_target=target, stop_below=stop)
        present = set(curves["channel"].astype(str))
        order = [str(c) for c in config.get("channels", [])]  # as configured, then the rest
        order += sorted(present - set(order))
        channels = {c: describe_channel(c) for c in order if c in present}
        return {
            "success_target": target,
            "channels": channels,
            "plant": config.get("plant"),
            "pipelines": {k: _stack(v) for k, v in config.get("pipelines", {}).items()},
            "curves": curves,
            "capacity_ratios": capacity_ratios(curves).to_dict("records"),
        }
    raise ValueError(f"no README summary for study {name!r}")


def _stack(pipeline: Mapping[str, Any]) -> str:
    """``"mpc + predictor, QoS static (reliability 1, latency_steps 1)"``."""

    def name(spec: Mapping[str, Any]) -> str:
        options = ", ".join(f"{k} {_g(v)}" for k, v in dict(spec.get("options") or {}).items())
        return f"{spec['kind']} ({options})" if options else str(spec["kind"])

    qos = pipeline["qos"]
    return f"{name(pipeline['controller'])} + {name(pipeline['estimator'])}, QoS {name(qos)}"


def _g(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _compact(value: Any) -> Any:
    """JSON types with floats to 6 significant digits (small files, stable diffs)."""
    if isinstance(value, float):
        return float(f"{value:.6g}") if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _compact(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_compact(v) for v in value]
    return value


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
    with atomic_write(path, "w") as fh:
        fh.write(json.dumps(_compact(to_jsonable(data)), indent=1, allow_nan=False) + "\n")


def export_results(
    results_dir: str | Path,
    docs_dir: str | Path = "docs",
    *,
    studies: Sequence[str] | None = None,
) -> list[Path]:
    """Write the compact form of a ``codesign paper`` folder into ``docs_dir``.

    ``docs_dir/results/<study>.json`` for every complete study (others' files are removed, so
    the folder describes one run), ``docs_dir/results/paper.json`` and the figures into
    ``docs_dir/figures/`` (:data:`FIGURES`). Returns the files written.

    ``studies`` (``codesign paper --only``): only these studies' files are written (or removed
    when not complete); the others' are kept, and so is ``paper.json`` but for these
    studies' entries and the totals over every entry.
    """
    unknown = sorted(set(studies or ()) - set(STUDIES[:-1]))
    if unknown:
        raise ValueError(f"unknown studies {unknown}; known: {', '.join(STUDIES[:-1])}")
    src = Path(results_dir)
    manifest_path = src / MANIFEST
    if not manifest_path.is_file():
        raise ValueError(f"{str(src)!r} has no {MANIFEST}: not a `codesign paper` results folder")
    manifest = json.loads(manifest_path.read_text())
    results, figures = Path(docs_dir) / "results", Path(docs_dir) / "figures"
    results.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name in STUDIES[:-1] if studies is None else tuple(studies):
        done = read_study(src / name)
        target = results / f"{name}.json"
        if done is None:
            target.unlink(missing_ok=True)
            continue
        shown = []
        for file, shown_as in FIGURES.get(name, {}).items():
            if (src / name / file).is_file():
                shutil.copyfile(src / name / file, figures / shown_as)
                written.append(figures / shown_as)
                shown.append(shown_as)
        record = {
            "study": name,
            **study_summary(done),
            "figures": shown,
            **_summary(name, src / name),
        }
        _write_json(target, record)
        written.append(target)
    run = {
        "command": manifest.get("command", ""),
        "seeds": manifest.get("seeds"),
        "seed": manifest.get("seed"),
        "workers": manifest.get("workers", manifest.get("config", {}).get("workers")),
        "created": manifest.get("created"),
        "studies_wall_time_s": manifest.get("studies_wall_time_s"),
        "studies_cpu_time_s": manifest.get("studies_cpu_time_s"),
        "studies": {
            name: {
                k: study.get(k) for k in (*(k for k in SUMMARY_KEYS if k != "settings"), "commit")
            }
            for name, study in manifest.get("studies", {}).items()
            if study.get("wall_time_s") is not None
        },
        "provenance": manifest.get("provenance", {}),
    }
    if studies is not None and (results / MANIFEST).is_file():
        run = _merge_run(json.loads((results / MANIFEST).read_text()), run, studies)
    _write_json(results / MANIFEST, run)
    written.append(results / MANIFEST)
    return written


def _merge_run(
    old: dict[str, Any], new: Mapping[str, Any], studies: Sequence[str]
) -> dict[str, Any]:
    """``old`` run summary with ``studies``' entries from ``new``, the totals recomputed."""
    entries = dict(old.get("studies", {}))
    for name in studies:
        entries.pop(name, None)
        if name in new["studies"]:
            entries[name] = new["studies"][name]
    order = {name: k for k, name in enumerate(STUDIES)}
    entries = dict(sorted(entries.items(), key=lambda kv: order.get(kv[0], len(order))))
    merged = {**old, "studies": entries}
    for total, key in (
        ("studies_wall_time_s", "wall_time_s"),
        ("studies_cpu_time_s", "cpu_time_s"),
    ):
        merged[total] = round(sum(float(e.get(key) or 0.0) for e in entries.values()), 1)
    return merged


# -- 2. the Markdown -------------------------------------------------------------------------------
def render_results(docs_results: str | Path, *, figures_url: str = "docs/figures") -> str:
    """The Markdown of README's results block from ``docs/results/`` (markers excluded).

    Every table says the command that produced it and the seed set; a study without its JSON
    is left out. ``figures_url`` is where README finds ``docs/figures``.
    """
    folder = Path(docs_results)
    if not (folder / MANIFEST).is_file():
        raise ValueError(f"{str(folder)!r} has no {MANIFEST}: run `codesign readme RESULTS_DIR`")
    run = json.loads((folder / MANIFEST).read_text())
    studies = {
        name: json.loads((folder / f"{name}.json").read_text())
        for name in STUDIES[:-1]
        if (folder / f"{name}.json").is_file()
    }
    parts = [header(run)]
    for name, study in studies.items():
        parts.append(SECTIONS[name](study, figures_url))
    if (folder / CROSSCHECK_FILE).is_file():
        parts.append(crosscheck_section(json.loads((folder / CROSSCHECK_FILE).read_text())))
    parts.append(wall_times(run))
    return "\n\n".join(p.strip("\n") for p in parts) + "\n"


def read_block(text: str) -> str:
    """The text between README's markers (``ValueError`` when they are not there once each)."""
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise ValueError(f"README must hold the markers {BEGIN} and {END} once each, in order")
    return text[text.index(BEGIN) + len(BEGIN) : text.index(END)].strip("\n") + "\n"


def replace_block(text: str, block: str) -> str:
    """``text`` with the part between the markers replaced by ``block``."""
    read_block(text)  # checks the markers
    head, tail = text[: text.index(BEGIN) + len(BEGIN)], text[text.index(END) :]
    return f"{head}\n{block.strip(chr(10))}\n{tail}"


def update_readme(
    readme: str | Path = "README.md", docs_dir: str | Path = "docs", *, check: bool = False
) -> bool:
    """Render ``docs_dir/results`` into ``readme``'s block; return whether the block changed.

    With ``check`` the file is left alone (the return value says whether it is stale).
    Figures are linked relative to the README's folder.
    """
    path = Path(readme)
    if not path.is_file():
        raise ValueError(f"README {str(path)!r} does not exist")
    text = path.read_text()
    figures = Path(os.path.relpath(Path(docs_dir) / "figures", path.parent)).as_posix()
    block = render_results(Path(docs_dir) / "results", figures_url=figures)
    changed = read_block(text) != block
    if changed and not check:
        with atomic_write(path, "w") as fh:
            fh.write(replace_block(text, block))
    return changed
