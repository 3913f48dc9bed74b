"""``codesign paper``: every table and figure README shows, in one run, into one folder.

The studies, with their settings and equivalent commands, are those of
:mod:`codesign_mb.studies.paper_studies` (:data:`~codesign_mb.studies.paper_studies.STUDIES`,
each into its own subfolder of the results folder ``OUT``); this module runs them.

A study's folder is complete when its ``study.json`` exists (written last: the study's
settings, the equivalent command, its wall time and provenance). A study runs into a hidden
``.<name>.partial`` folder that replaces its folder only when done, so an interrupted run
leaves the previous complete folder or none. A complete folder with the same settings is
reused (``force`` reruns it). Inside a study, every finished episode or trial is kept in
the partial folder's record store (``.records``, :mod:`codesign_mb.core.records`) as it
finishes, so a rerun after an interruption continues the study where it stopped (deleting
``.<name>.partial`` starts it afresh); the store goes once the study is complete.
``OUT/paper.json`` is the manifest: every study's status (``ran``; ``reused``: complete with
the same settings; ``kept``: not selected, complete from an earlier run; ``not selected``),
settings, command and wall time, the run's total wall time and the provenance (commit,
versions, SHA-256 of the checkpoints).
README's results section is rendered from this folder by :mod:`codesign_mb.studies.readme`.
"""

from __future__ import annotations

import contextlib
import json
import resource
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.records import RECORDS_DIR
from codesign_mb.core.registry import resolve_checkpoint
from codesign_mb.core.results import (
    atomic_write,
    provenance,
    read_json_table,
    to_jsonable,
    write_results,
)
from codesign_mb.core.seeds import seed_set
from codesign_mb.studies.paper_studies import (
    STUDIES,
    TABLE_STUDIES,
    PaperConfig,
    study_command,
    study_settings,
)

__all__ = [
    "MANIFEST",
    "STUDY_FILE",
    "SUMMARY_KEYS",
    "PaperRun",
    "read_study",
    "run_paper",
    "study_summary",
]

STUDY_FILE = "study.json"
"""Written last into a study's folder: its settings, command, wall time and provenance."""

MANIFEST = "paper.json"
"""The manifest of the results folder."""

Progress = Callable[..., Iterable[Any]]
"""``progress(stream, total=..., description=...)`` wraps a stream of finished work items."""

Log = Callable[[str], None]


# -- the studies ----------------------------------------------------------------------------------
def _run_lqg(settings: Mapping[str, Any], out: Path) -> None:
    from codesign_mb.studies.demo import LqgDemoConfig, run_lqg_demo

    fields = {k: settings[k] for k in ("episodes", "seed", "horizon") if k in settings}
    cfg = LqgDemoConfig(**fields)
    result = run_lqg_demo(cfg)  # seconds: no progress bar
    rows = pd.DataFrame(result.pop("rows"))
    write_results(out, table=rows, config=cfg, name="lqg", extra=result)


def _run_table(
    name: str, settings: Mapping[str, Any], out: Path, workers: int, progress: Progress
) -> dict[str, Path]:
    from codesign_mb.studies.table import TableConfig
    from codesign_mb.studies.table_figures import run_table_study

    cfg = TableConfig(
        scenario=settings["scenario"],
        pipeline=settings["pipeline"],
        trials=settings["trials"],
        seed=settings["seed"],
        seeds=tuple(settings.get("root_seeds", ())),
        bound=tuple(settings.get("bound", ())),
        workers=workers,
    )
    run_table_study(cfg, out, progress=progress, command=study_command(name, settings))
    return _checkpoints(cfg)


def _checkpoints(cfg: Any) -> dict[str, Path]:
    """The learned checkpoints a table's rows use, by their path as the rows name them."""
    found: dict[str, Path] = {}
    for row in cfg.table_rows():
        for spec in (row.controller, row.estimator, row.qos):
            if spec.checkpoint and spec.checkpoint not in found:
                try:
                    found[spec.checkpoint] = resolve_checkpoint(spec.checkpoint)
                except ValueError:
                    continue  # the table lists the row as skipped, with the reason
    return found


def _run_fig_cn(settings: Mapping[str, Any], out: Path, workers: int, progress: Progress) -> None:
    from codesign_mb.studies.fig_cn import FigCnConfig, run_fig_cn_study

    grid = {k: settings[k] for k in ("delays", "reliabilities") if k in settings}
    cfg = FigCnConfig(trials=settings["trials"], seed=settings["seed"], workers=workers, **grid)
    run_fig_cn_study(
        cfg, out, progress=lambda it, total: progress(it, total=total, description="fig_cn")
    )


def _run_fig_wifi(settings: Mapping[str, Any], out: Path, workers: int, progress: Progress) -> None:
    from codesign_mb.core.config import from_mapping
    from codesign_mb.studies.fig_wifi import CapacityConfig
    from codesign_mb.studies.fig_wifi_figures import run_capacity_study

    fields = {k: v for k, v in settings.items() if k != "seeds"}
    cfg = from_mapping(CapacityConfig, {**fields, "workers": workers})
    total = len(cfg.points())
    run_capacity_study(
        cfg, out, progress=lambda it: progress(it, total=total, description="fig_wifi")
    )


def _run_figures(inputs: Mapping[str, Any], out: Path, root: Path) -> None:
    from codesign_mb.studies.report import build_report

    for name in inputs:
        build_report(root / name, out / name)


# -- the run --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PaperRun:
    """What :func:`run_paper` did: the manifest it wrote and each study's status."""

    out_dir: Path
    manifest: dict[str, Any]
    status: dict[str, str] = field(default_factory=dict)

    @property
    def path(self) -> Path:
        return self.out_dir / MANIFEST


def read_study(folder: str | Path) -> dict[str, Any] | None:
    """The ``study.json`` of a complete study folder, or ``None``.

    A ``study.json`` that does not parse is reported (``RuntimeWarning`` naming it) and its
    study counts as not complete, so it is run again.
    """
    return read_json_table(Path(folder) / STUDY_FILE, otherwise="the study is run again")


def run_paper(
    config: PaperConfig,
    out_dir: str | Path,
    *,
    progress: Progress | None = None,
    log: Log | None = None,
    command: str = "",
) -> PaperRun:
    """Run the selected studies into ``out_dir`` (resuming), then write the manifest.

    ``progress`` wraps each study's stream of finished episodes or points; ``log`` gets one
    line per study (ran, reused, with its wall time; a reused study made at another commit is
    said to be so). Returns the manifest and the statuses.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wrap: Progress = progress or (lambda stream, **_: stream)
    say: Log = log or (lambda _: None)
    started = time.perf_counter()
    status: dict[str, str] = {}
    commit = provenance()["commit"]
    with _say_what_is_kept(out):
        for name in config.selected():
            status[name] = _run_or_reuse(name, config, out, commit, wrap, say)
    manifest = _manifest(config, out, status, time.perf_counter() - started, command)
    with atomic_write(out / MANIFEST, "w") as fh:
        fh.write(json.dumps(manifest, indent=2, allow_nan=False) + "\n")
    return PaperRun(out, manifest, status)


@contextlib.contextmanager
def _say_what_is_kept(out: Path) -> Iterator[None]:
    """On Ctrl-C: the complete studies are kept, and so is the partial one's progress."""
    try:
        yield
    except KeyboardInterrupt as exc:
        complete = [name for name in STUDIES if read_study(out / name) is not None]
        done = f"complete studies kept in {out}: {', '.join(complete) or 'none'}"
        inner = f"; {exc.args[0]}" if exc.args else "; rerun the same command to resume"
        raise KeyboardInterrupt(done + inner) from None


def _run_or_reuse(
    name: str, config: PaperConfig, out: Path, commit: str | None, wrap: Progress, say: Log
) -> str:
    """Run study ``name``, or reuse its complete folder; its status (``ran``, ``reused``)."""
    if name == "figures":
        settings: dict[str, Any] = {"inputs": _finished_inputs(out)}
    else:
        settings = study_settings(name, config)
    done = read_study(out / name)
    if done is not None and done.get("settings") == settings and not config.force:
        then = done.get("provenance", {}).get("commit")
        stale = f"; made at commit {then}, now {commit}: --force reruns" if then != commit else ""
        say(f"{name}: complete, reused ({done.get('wall_time_s', 0):.0f} s when run{stale})")
        return "reused"
    seconds = _run_study(name, settings, out, config.worker_count(), wrap)
    say(f"{name}: {seconds:.0f} s -> {out / name}")
    return "ran"


def _finished_inputs(out: Path) -> dict[str, str]:
    """The complete study folders ``figures`` renders, with when each finished."""
    found = {}
    for name in STUDIES[:-1]:
        done = read_study(out / name)
        if done is not None:
            found[name] = str(done.get("finished", ""))
    return found


def _run_study(
    name: str, settings: dict[str, Any], out: Path, workers: int, progress: Progress
) -> float:
    """Run one study into ``.<name>.partial``, write its ``study.json``, swap it into place.

    The partial folder's record store (``.records``: the finished episodes of an interrupted
    run, keyed by what determines them) is kept; anything else in it goes.
    """
    partial, folder = out / f".{name}.partial", out / name
    _clear_partial(partial, keep=(RECORDS_DIR,))
    partial.mkdir(parents=True, exist_ok=True)
    resumed = _stored_records(partial / RECORDS_DIR)  # an interrupted run's, reused
    started_at = datetime.now(UTC).isoformat(timespec="seconds")
    started, cpu = time.perf_counter(), _cpu_seconds()
    checkpoints: Mapping[str, Path] = {}
    if name == "lqg":
        _run_lqg(settings, partial)
    elif name in TABLE_STUDIES:
        checkpoints = _run_table(name, settings, partial, workers, progress)
    elif name == "fig_cn":
        _run_fig_cn(settings, partial, workers, progress)
    elif name == "fig_wifi":
        _run_fig_wifi(settings, partial, workers, progress)
    else:
        _run_figures(settings["inputs"], partial, out)
    seconds = time.perf_counter() - started
    record = {
        "study": name,
        "command": study_command(name, settings),
        "settings": settings,
        "workers": workers,
        "wall_time_s": round(seconds, 1),
        "cpu_time_s": round(_cpu_seconds() - cpu, 1),
        "resumed_records": resumed,
        "started": started_at,
        "finished": datetime.now(UTC).isoformat(timespec="seconds"),
        "provenance": provenance(checkpoints),
    }
    with atomic_write(partial / STUDY_FILE, "w") as fh:
        fh.write(json.dumps(to_jsonable(record), indent=2, allow_nan=False) + "\n")
    shutil.rmtree(partial / RECORDS_DIR, ignore_errors=True)  # done: its tables hold them
    old = out / f".{name}.old"
    shutil.rmtree(old, ignore_errors=True)
    if folder.exists():
        folder.rename(old)
    partial.rename(folder)
    shutil.rmtree(old, ignore_errors=True)
    return seconds


SUMMARY_KEYS = ("command", "settings", "wall_time_s", "cpu_time_s", "resumed_records", "finished")
"""What the manifest and ``docs/results`` keep of a study's ``study.json`` (and its commit)."""


def study_summary(done: Mapping[str, Any]) -> dict[str, Any]:
    """A study's :data:`SUMMARY_KEYS` and the commit that made it: its command, settings, times
    (and the stored records a resumed run reused) and end."""
    return {
        **{k: done.get(k) for k in SUMMARY_KEYS},
        "commit": done.get("provenance", {}).get("commit"),
    }


def _stored_records(store: Path) -> int:
    """Records (episodes, trials) an earlier run left in a partial folder's store: this run
    reuses them, so its wall and CPU times cover only the rest."""
    if not store.is_dir():
        return 0
    count = 0
    for path in store.glob("*.jsonl"):
        with path.open("rb") as fh:
            count += sum(1 for line in fh if line.strip())
    return count


def _clear_partial(partial: Path, *, keep: tuple[str, ...]) -> None:
    """Remove ``partial``'s files and folders but those named in ``keep``."""
    if not partial.is_dir():
        shutil.rmtree(partial, ignore_errors=True)
        return
    for entry in partial.iterdir():
        if entry.name in keep:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its finished children (the pool
    workers): on a shared machine, what a study costs regardless of who else runs."""
    own, children = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _manifest(
    config: PaperConfig, out: Path, status: dict[str, str], seconds: float, command: str
) -> dict[str, Any]:
    """``paper.json``: every study's record (or why absent), wall times, provenance."""
    studies: dict[str, Any] = {}
    checkpoints: dict[str, str] = {}
    for name in STUDIES:
        done = read_study(out / name)
        if done is None:
            studies[name] = {"status": status.get(name, "not selected")}
            continue
        studies[name] = {"status": status.get(name, "kept"), **study_summary(done)}
        checkpoints.update(done.get("provenance", {}).get("checkpoints", {}))
    recorded = [s["wall_time_s"] for s in studies.values() if s.get("wall_time_s") is not None]
    cpu = [s["cpu_time_s"] for s in studies.values() if s.get("cpu_time_s") is not None]
    record = provenance()
    record["checkpoints"] = dict(sorted(checkpoints.items()))
    return dict(
        to_jsonable(
            {
                "command": command,
                "config": asdict(config),
                "workers": config.worker_count(),
                "seeds": config.seeds,
                "seed": seed_set(config.seeds),
                "created": datetime.now(UTC).isoformat(timespec="seconds"),
                "wall_time_s": round(seconds, 1),
                "studies_wall_time_s": round(sum(recorded), 1),
                "studies_cpu_time_s": round(sum(cpu), 1),
                "studies": studies,
                "provenance": record,
            }
        )
    )
