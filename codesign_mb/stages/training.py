"""SAC training machinery shared by stages A, C and D: chunks, checkpoints, resume, curves.

A run has two folders:

* the **work folder** (default ``runs/train/<stage>``, not shipped): the latest SB3 model,
  its replay buffer and ``state.json`` (steps done, wall time, training curve). Training
  proceeds in chunks of ``chunk_steps`` env steps; after each chunk all three are written
  (atomically), so an interrupted run resumes from the last chunk with ``resume=True``;
* the **output folder** (default ``runs/checkpoints/stage_a``; the shipped ones are in
  ``models/checkpoints``): the final ``model.zip``, ``training.json`` (command, seed, env
  steps, wall time, config, final evaluation; checkpoint paths portable, see
  :mod:`~codesign_mb.stages.paths`) and ``curve.json``.

No RL algorithm is written here: this is SB3's :class:`~stable_baselines3.SAC` driven by
``learn(chunk, reset_num_timesteps=False)``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from codesign_mb.core.checkpoints import reading_checkpoint
from codesign_mb.core.config import TRAINING_STEPS_CAP, Cap, check_range, to_mapping
from codesign_mb.core.results import atomic_write, package_version, to_jsonable
from codesign_mb.core.seeds import episode_seeds, seed_set
from codesign_mb.stages.paths import portable_paths

__all__ = [
    "Progress",
    "SacSpec",
    "TrainingState",
    "git_commit",
    "load_state",
    "make_sac",
    "no_progress",
    "require_at_least",
    "resume_sac",
    "seeded_torch",
    "selection_seeds",
    "stage_seeds",
    "train_sac_in_chunks",
    "training_record",
    "write_json",
    "write_output",
    "write_training_record",
]

Progress = Callable[..., Iterable[Any]]
"""``progress(iterable, *, total, description)``: :func:`codesign_mb.cli.common.track`'s shape."""


def no_progress(
    iterable: Iterable[Any], *, total: int | None = None, description: str = ""
) -> Iterator[Any]:
    """The silent :data:`Progress` (library default)."""
    yield from iterable


def require_at_least(
    config: Any, minimum: float, *names: str, prefix: str = "", cap: Cap | None = None
) -> None:
    """Raise ``ValueError`` naming the first field of ``config`` in ``names`` below ``minimum``
    (or above ``cap``).

    The stages' configs validate their counts with it: "total_steps must be >= 1, got 0".
    """
    for name in names:
        check_range(f"{prefix}{name}", getattr(config, name), ge=minimum, cap=cap)


EPOCHS_CAP = Cap(100_000, "training epochs")
WIDTH_CAP = Cap(4_096, "units of a network layer")
BUFFER_CAP = Cap(10_000_000, "transitions of a replay buffer")


def stage_seeds(seed: int, n: int) -> list[int]:
    """The episode seeds of a stage's collection or final evaluation: ``SeedSequence(seed)``'s
    state.

    The stages' own scheme (the shipped checkpoints were trained with it), distinct from the
    evaluation protocol's :func:`~codesign_mb.core.seeds.episode_seeds`.
    """
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(max(n, 1))[:n]]


def selection_seeds(n: int) -> list[int]:
    """The episodes a stage selects its shipped model on (``keep_best``): the first ``n`` of
    the ``dev`` seed set, whatever the stage and its seed (DESIGN.md, evaluation protocol:
    what is selected is chosen on ``dev``, what is reported comes from ``test``)."""
    return episode_seeds(seed_set("dev"), n) if n else []


@dataclass(frozen=True)
class SacSpec:
    """Hyper-parameters of SB3's SAC (names as in :class:`stable_baselines3.SAC`).

    ``ent_coef`` is ``"auto"``, ``"auto_<init>"`` (learned, from ``init``) or a fixed
    positive number (a number or a numeric string).
    """

    learning_rate: float = 3e-4
    buffer_size: int = 200_000
    batch_size: int = 256
    gamma: float = 0.98
    tau: float = 0.005
    learning_starts: int = 1_000
    train_freq: int = 1
    gradient_steps: int = 1
    net_arch: tuple[int, ...] = (256, 256)
    ent_coef: str | float = "auto"

    def __post_init__(self) -> None:
        require_at_least(self, 1, "buffer_size", "batch_size", prefix="sac.", cap=BUFFER_CAP)
        require_at_least(self, 1, "train_freq", prefix="sac.", cap=TRAINING_STEPS_CAP)
        require_at_least(self, 0, "learning_starts", prefix="sac.", cap=TRAINING_STEPS_CAP)
        check_range("sac.gradient_steps", self.gradient_steps, cap=EPOCHS_CAP)
        check_range("sac.net_arch", self.net_arch, cap=WIDTH_CAP)
        if self.gradient_steps == 0 or self.gradient_steps < -1:
            raise ValueError(f"sac.gradient_steps must be >= 1 or -1, got {self.gradient_steps}")
        if not 0 < self.gamma <= 1:
            raise ValueError(f"sac.gamma must be in (0, 1], got {self.gamma}")
        if not 0 < self.tau <= 1:
            raise ValueError(f"sac.tau must be in (0, 1], got {self.tau}")
        if self.learning_rate <= 0:
            raise ValueError(f"sac.learning_rate must be > 0, got {self.learning_rate}")
        if not self.net_arch or any(int(h) < 1 for h in self.net_arch):
            raise ValueError(f"sac.net_arch must be positive layer widths, got {self.net_arch}")
        ent = self.ent_coef
        if self.learns_ent_coef:
            return
        try:
            fixed = float(ent)
        except (TypeError, ValueError):
            fixed = math.nan
        if not (math.isfinite(fixed) and fixed > 0):
            raise ValueError(
                f"sac.ent_coef must be 'auto', 'auto_<x>' or a positive number, got {ent!r}"
            )

    @property
    def learns_ent_coef(self) -> bool:
        """``ent_coef`` is learned (``"auto"``, ``"auto_<init>"``), not fixed."""
        return isinstance(self.ent_coef, str) and self.ent_coef.startswith("auto")


def make_sac(
    env: gym.Env,
    spec: SacSpec,
    *,
    seed: int,
    policy: Any = "MlpPolicy",
    policy_kwargs: dict[str, Any] | None = None,
    **extra: Any,
) -> Any:
    """A fresh SB3 SAC on ``env`` (CPU, one torch thread: the machine is shared).

    ``policy``, ``policy_kwargs`` (added to the spec's ``net_arch``) and ``extra`` (SB3 SAC
    keywords, e.g. a replay buffer class) let a stage change what it needs, nothing else.
    """
    import torch
    from stable_baselines3 import SAC

    torch.set_num_threads(1)
    ent = spec.ent_coef if spec.learns_ent_coef else float(spec.ent_coef)
    return SAC(
        policy,
        env,
        learning_rate=spec.learning_rate,
        buffer_size=spec.buffer_size,
        batch_size=spec.batch_size,
        gamma=spec.gamma,
        tau=spec.tau,
        learning_starts=spec.learning_starts,
        train_freq=spec.train_freq,
        gradient_steps=spec.gradient_steps,
        ent_coef=ent,
        policy_kwargs={"net_arch": [int(h) for h in spec.net_arch], **(policy_kwargs or {})},
        seed=seed,
        device="cpu",
        verbose=0,
        **extra,
    )


@dataclass
class TrainingState:
    """What ``state.json`` in a work folder records: enough to resume and to report."""

    stage: str
    total_steps: int
    steps_done: int = 0
    wall_time_s: float = 0.0
    curve: list[dict[str, Any]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "total_steps": self.total_steps,
            "steps_done": self.steps_done,
            "wall_time_s": self.wall_time_s,
            "curve": self.curve,
            "extra": self.extra,
        }


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""

    with atomic_write(path, "w") as fh:
        json.dump(to_jsonable(data), fh, indent=2)
        fh.write("\n")


_WORK_REMEDY = "delete the work folder, or train without --resume"


def load_state(work_dir: str | Path) -> TrainingState | None:
    """The state of a previous run in ``work_dir``, or ``None``."""
    path = Path(work_dir) / "state.json"
    if not path.is_file():
        return None
    with reading_checkpoint(path, remedy=_WORK_REMEDY):
        return TrainingState(**json.loads(path.read_text()))


def _save_model(model: Any, path: Path) -> None:
    tmp = path.with_name(f".{path.stem}.tmp.zip")
    # The actor learning-rate hook is a bound method: pickled, it drags the whole model along.
    model.save(tmp, exclude=["_update_learning_rate"])
    os.replace(tmp, path)


def _save_buffer(model: Any, path: Path) -> None:
    tmp = path.with_name(f".{path.stem}.tmp.pkl")
    model.save_replay_buffer(tmp)
    os.replace(tmp, path)


def resume_sac(work_dir: str | Path, env: gym.Env) -> Any | None:
    """Load the model and replay buffer of ``work_dir`` onto ``env``, or ``None`` if absent."""
    import torch
    from stable_baselines3 import SAC

    work_dir = Path(work_dir)
    model_path = work_dir / "model.zip"
    if not model_path.is_file():
        return None
    torch.set_num_threads(1)
    with reading_checkpoint(model_path, remedy=_WORK_REMEDY):
        model = SAC.load(model_path, env=env, device="cpu")
    buffer_path = work_dir / "replay_buffer.pkl"
    if buffer_path.is_file():
        with reading_checkpoint(buffer_path, remedy=_WORK_REMEDY):
            model.load_replay_buffer(buffer_path)
    return model


def train_sac_in_chunks(
    model: Any,
    state: TrainingState,
    *,
    work_dir: str | Path,
    chunk_steps: int,
    evaluate: Callable[[Any], Mapping[str, Any]] | None = None,
    callback: Any = None,
    on_chunk: Callable[[Any, TrainingState], Mapping[str, Any]] | None = None,
    progress: Progress = no_progress,
    description: str = "training",
    save_buffer: bool = True,
    keep_best: str | Callable[[Mapping[str, Any]], float | None] | None = None,
) -> TrainingState:
    """Run ``model.learn`` chunk by chunk until ``state.total_steps``, checkpointing each chunk.

    After every chunk: ``evaluate(model)`` and ``on_chunk(model, state)`` add entries to a new
    curve point (with ``steps`` and ``wall_time_s``), then the model, its replay buffer and
    ``state.json`` are written to ``work_dir``. The step count is SB3's ``num_timesteps``, so a
    resumed run continues where the last checkpoint left it.

    With ``keep_best`` (a key of the evaluation, e.g. ``"success_rate"``, or a function of
    the curve point that scores it, ``None`` for a point that may not be shipped), the model
    of the best evaluation so far (ties: the later) is also kept as ``best_model.zip`` and
    recorded in ``state.extra["best"]`` (SB3's ``EvalCallback`` practice).
    """
    if chunk_steps < 1:
        raise ValueError(f"chunk_steps must be >= 1, got {chunk_steps}")
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    state.steps_done = int(model.num_timesteps)
    remaining = max(0, state.total_steps - state.steps_done)
    n_chunks = -(-remaining // chunk_steps)
    for _ in progress(range(n_chunks), total=n_chunks, description=description):
        n = min(chunk_steps, state.total_steps - int(model.num_timesteps))
        start = time.perf_counter()
        model.learn(n, reset_num_timesteps=False, callback=callback, progress_bar=False)
        point: dict[str, Any] = {"steps": int(model.num_timesteps)}
        if on_chunk is not None:
            point.update(on_chunk(model, state))
        if evaluate is not None:
            point.update(evaluate(model))
        state.wall_time_s += time.perf_counter() - start
        state.steps_done = int(model.num_timesteps)
        point["wall_time_s"] = round(state.wall_time_s, 2)
        state.curve.append(point)
        _save_model(model, work_dir / "model.zip")
        score = _score(keep_best, point)
        if score is not None:
            best = state.extra.get("best")
            key = keep_best if isinstance(keep_best, str) else "score"
            if best is None or score >= best.get("score", best.get(key, -np.inf)):
                state.extra["best"] = {"steps": point["steps"], key: score, "score": score}
                _save_model(model, work_dir / "best_model.zip")
        if save_buffer:
            _save_buffer(model, work_dir / "replay_buffer.pkl")
        write_json(work_dir / "state.json", state.to_json())
    return state


def _score(
    keep_best: str | Callable[[Mapping[str, Any]], float | None] | None, point: Mapping[str, Any]
) -> float | None:
    if keep_best is None:
        return None
    if isinstance(keep_best, str):
        return float(point[keep_best]) if keep_best in point else None
    return keep_best(point)


def training_record(
    *,
    stage: str,
    command: str | None,
    seed: int,
    env_steps: int,
    wall_time_s: float,
    config: Any,
    **fields: Any,
) -> dict[str, Any]:
    """Every stage's ``training.json``: what was run (command, seed, config), how much (env
    steps, wall time), from which code (package version, git commit), and the stage's own
    ``fields``."""
    return {
        "stage": stage,
        "command": command,
        "seed": seed,
        "env_steps": int(env_steps),
        "wall_time_s": round(float(wall_time_s), 1),
        **fields,
        "package_version": package_version(),
        "git_commit": git_commit(),
        "config": to_mapping(config),
    }


def write_training_record(out_dir: Path, meta: Mapping[str, Any], curve: Any) -> None:
    """``training.json`` (checkpoint paths made portable,
    :func:`~codesign_mb.stages.paths.portable_paths`) and ``curve.json`` into ``out_dir``."""
    write_json(out_dir / "training.json", portable_paths(dict(meta), out_dir))
    write_json(out_dir / "curve.json", curve)


def write_output(
    out_dir: str | Path,
    *,
    model: Any | None,
    state: TrainingState,
    config: Any,
    command: str | None,
    seed: int,
    final: Mapping[str, Any] | None = None,
    notes: str = "",
) -> Path:
    """Write the checkpoint folder: ``model.zip``, ``training.json``, ``curve.json``.

    Checkpoint paths in ``training.json`` are made portable
    (:func:`~codesign_mb.stages.paths.portable_paths`).
    """

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if model is not None:
        _save_model(model, out_dir / "model.zip")
    meta = training_record(
        stage=state.stage,
        command=command,
        seed=seed,
        env_steps=state.steps_done,
        wall_time_s=state.wall_time_s,
        config=config,
        final_evaluation=dict(final or {}),
        notes=notes,
        **state.extra,
    )
    write_training_record(out_dir, meta, state.curve)
    return out_dir


def git_commit() -> str | None:
    """The source checkout's ``HEAD`` commit (``+dirty`` with uncommitted changes), or ``None``
    outside a git checkout: what ``training.json`` records to say which code trained it."""
    import subprocess

    root = Path(__file__).resolve().parent
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{head}+dirty" if dirty else head


@contextlib.contextmanager
def seeded_torch(seed: int) -> Iterator[None]:
    """Seed torch inside the block only; the global RNG state is restored afterwards."""
    import torch

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield
