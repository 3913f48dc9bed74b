"""What every training stage shares: where it writes, whether it resumes, how it reports.

A stage is a function ``train(config, run) -> summary`` (:class:`Trainer`) with a frozen config
dataclass; the four of paper.tex's pipeline (A: the ideal controller, B: the estimator, C: the
QoS policy, D: the joint synthesis) are the ``stage`` kinds of the component registry
(:mod:`codesign_mb.stages.kinds`), so the command line and the studies find a stage, its config
and its trainer in one place. Provenance (command, seeds, steps, wall time, git commit) is
:func:`~codesign_mb.stages.training.training_record`'s, written by every stage.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from codesign_mb.stages.training import Progress, no_progress

__all__ = ["StageRun", "Trainer"]


@dataclass(frozen=True)
class StageRun:
    """Where and how one stage trains.

    Parameters
    ----------
    out_dir:
        Where the stage writes its checkpoint and ``training.json``.
    work_dir:
        Its resumable state (replay buffers, collected data, fits, curves).
    resume:
        Continue what ``work_dir`` holds instead of starting over.
    progress:
        ``progress(iterable, *, total, description)`` (the command line's progress bar).
    command:
        The command line, recorded in ``training.json``.
    """

    out_dir: Path
    work_dir: Path
    resume: bool = False
    progress: Progress = field(default=no_progress, compare=False)
    command: str | None = None

    def __post_init__(self) -> None:
        for name in ("out_dir", "work_dir"):
            value = getattr(self, name)
            if not isinstance(value, (str, Path)) or not str(value):
                raise TypeError(f"{name} must be a path, got {value!r}")
            object.__setattr__(self, name, Path(value))
        if not isinstance(self.resume, bool):
            raise TypeError(f"resume must be a bool, got {self.resume!r}")
        if not callable(self.progress):
            raise TypeError(f"progress must be callable, got {self.progress!r}")

    def prepare_work_dir(self, stale: Iterable[str]) -> Path:
        """Create ``work_dir``; unless resuming, drop what a previous run left there: the files
        with a suffix (``.npz``) or a name (``curves.json``) in ``stale``."""
        self.work_dir.mkdir(parents=True, exist_ok=True)
        if not self.resume:
            drop = set(stale)
            for old in self.work_dir.glob("*"):
                if old.suffix in drop or old.name in drop:
                    old.unlink()
        return self.work_dir


class Trainer(Protocol):
    """A stage's trainer: writes ``run.out_dir`` and returns the summary it wrote."""

    def __call__(self, config: Any, run: StageRun) -> dict[str, Any]: ...
