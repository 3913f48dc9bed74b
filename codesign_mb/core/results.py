"""Results folders: tidy tables written atomically with their config and provenance.

Every experiment writes into one results folder, one *table* per ``name``::

    out/
      tab_p.parquet        the tidy table (one row per observation, one column per variable)
      tab_p.csv            the same table as CSV, for spreadsheets and diffs
      tab_p.json           metadata: name, config, package version, timestamp, columns, extra

Each file is written to a temporary file in the same folder, flushed and ``fsync``-ed, then
moved into place with ``os.replace`` (atomic on POSIX), so an interrupted run leaves either
the previous complete file or none, never half a file. A table's old ``.json`` metadata
is removed before its other files are replaced and the new one is written last: a table is
complete when its metadata exists (:class:`ResultsDir` lists only those), so a rewrite killed
half-way leaves that table unlisted (each file the old or the new one, whole) until it is
written again, never new rows under an old config.
A killed write may leave its temporary file (``.<file>.<random>.tmp``), which no reader takes
for a result.

The table names and columns that ``codesign report`` understands are documented in
:mod:`codesign_mb.studies.report`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import platform
import re
import subprocess
import tempfile
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import UTC, date, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import IO, Any

import numpy as np
import pandas as pd

__all__ = [
    "ResultsDir",
    "atomic_write",
    "file_digest",
    "package_version",
    "provenance",
    "read_json_table",
    "to_jsonable",
    "write_results",
]

_VERSIONED = ("numpy", "scipy", "pandas", "mujoco", "pin", "casadi", "cvxpy", "osqp", "torch",
              "stable-baselines3", "gymnasium")  # fmt: skip
"""Distributions whose versions every results file records."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_UMASK = os.umask(0)
os.umask(_UMASK)  # read the process umask once; mkstemp's files are 0600, results are not
_FORMATS = ("parquet", "csv", "json")


def read_json_table(path: Path, *, otherwise: str, stacklevel: int = 2) -> dict[str, Any] | None:
    """The JSON object (a table) in ``path``; ``None`` when it is absent or corrupt.

    A file that does not parse, or holds something other than an object, is reported by a
    ``RuntimeWarning`` naming it and saying what happens ``otherwise`` (e.g. "the study is run
    again"): a corrupt record costs a recomputation, never the run.
    """
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"a {type(data).__name__}, not a table")
    except (ValueError, UnicodeDecodeError) as exc:
        warnings.warn(
            f"{path} is corrupt ({' '.join(str(exc).split())}); {otherwise}",
            RuntimeWarning,
            stacklevel=stacklevel + 1,
        )
        return None
    return data


def package_version() -> str:
    """The installed ``codesign_mb`` version (``"unknown"`` when not installed)."""
    try:
        return version("codesign_mb")
    except PackageNotFoundError:
        return "unknown"


def _git_commit() -> str | None:
    """The commit of the source checkout this package runs from (``+dirty`` if modified)."""
    source = Path(__file__).resolve().parents[2]
    if not (source / ".git").exists():
        return None
    try:
        commit = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+dirty" if dirty else "")


def file_digest(path: str | Path) -> str:
    """``sha256:<hex>`` of a file, or of every file under a folder (sorted relative paths)."""
    p = Path(path)
    digest = hashlib.sha256()
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    for f in files:
        if p.is_dir():
            digest.update(f.relative_to(p).as_posix().encode())
        digest.update(f.read_bytes())
    return f"sha256:{digest.hexdigest()}"


def provenance(checkpoints: Mapping[str, str | Path] | None = None) -> dict[str, Any]:
    """What produced a result: source commit, package and dependency versions, checkpoints.

    ``checkpoints`` maps a name (e.g. ``"stage_a"``) to a file or folder; each is recorded by
    its content hash, so a result can be matched to the exact weights that made it.
    """
    versions = {}
    for dist in _VERSIONED:
        with contextlib.suppress(PackageNotFoundError):
            versions[dist] = version(dist)
    return {
        "commit": _git_commit(),
        "versions": versions,
        "checkpoints": {k: file_digest(v) for k, v in (checkpoints or {}).items()},
    }


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file next to ``path``; on success fsync it and ``os.replace`` it there.

    If the body raises, the temporary file is removed and ``path`` is untouched; an
    ``OSError`` that names no file (a full disk) is raised again naming ``path``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_write(d / "x.txt", "w") as fh:
    ...     _ = fh.write("hello")
    >>> (d / "x.txt").read_text()
    'hello'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            # e.g. a full disk: say which file could not be written (it is left as it was)
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    _fsync_dir(path.parent)


def _fsync_dir(directory: Path) -> None:
    # Make the rename itself durable; not supported everywhere (e.g. Windows), hence best effort.
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def to_jsonable(value: Any) -> Any:
    """Convert results (numpy scalars/arrays, dataclasses, paths, frames) to plain JSON types.

    Non-finite floats become ``None`` so the output is strict JSON.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_jsonable(dataclasses.asdict(value))
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, datetime | date):
        return value.isoformat()
    if isinstance(value, pd.DataFrame):
        return to_jsonable(value.to_dict(orient="records"))
    if isinstance(value, pd.Series):
        return to_jsonable(value.to_dict())
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, Sequence | set | frozenset):
        return [to_jsonable(v) for v in value]
    return str(value)


def _tidy(table: pd.DataFrame) -> pd.DataFrame:
    if not isinstance(table, pd.DataFrame):
        raise TypeError(f"table must be a pandas.DataFrame, got {type(table).__name__}")
    if not isinstance(table.index, pd.RangeIndex) or table.index.name is not None:
        table = table.reset_index()
    if isinstance(table.columns, pd.MultiIndex):
        raise ValueError("table must have flat column names (tidy), got a MultiIndex")
    bad = [c for c in table.columns if not isinstance(c, str)]
    if bad:
        raise ValueError(f"table column names must be strings, got {bad!r}")
    if table.columns.has_duplicates:
        dup = sorted(set(table.columns[table.columns.duplicated()]))
        raise ValueError(f"table has duplicate columns {dup!r}")
    return table.reset_index(drop=True)


def write_results(
    out_dir: str | Path,
    *,
    table: pd.DataFrame,
    config: Any,
    name: str,
    extra: Mapping[str, Any] | None = None,
    checkpoints: Mapping[str, str | Path] | None = None,
) -> dict[str, Path]:
    """Write ``table`` as ``<name>.parquet`` + ``<name>.csv`` + ``<name>.json`` into ``out_dir``.

    Parameters
    ----------
    out_dir:
        The results folder (created if missing). Existing files of the same ``name`` are
        replaced atomically, their metadata removed first (see the module docstring); other
        tables in the folder are left alone.
    table:
        A tidy ``pandas.DataFrame``: string column names, one row per observation. A
        non-default index is turned into columns.
    config:
        The config that produced the table: a dataclass, a mapping or ``None``. Stored as JSON.
    name:
        Table name, e.g. ``"tab_p"`` (letters, digits, ``_ . -``).
    extra:
        More JSON-able metadata (seeds, wall time, command line, ...).
    checkpoints:
        Learned components the table was made with, by name: recorded by content hash in
        the metadata's ``provenance`` (with the source commit and dependency versions).

    Returns
    -------
    dict
        ``{"parquet": path, "csv": path, "json": path}``.
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"results name must match {_NAME.pattern}, got {name!r}")
    table = _tidy(table)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"results folder {str(out)!r} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    paths = {fmt: out / f"{name}.{fmt}" for fmt in _FORMATS}
    meta = {
        "name": name,
        "package": "codesign_mb",
        "version": package_version(),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "provenance": provenance(checkpoints),
        "n_rows": len(table),
        "columns": {c: str(t) for c, t in table.dtypes.items()},
        "config": to_jsonable(dataclasses.asdict(config))
        if dataclasses.is_dataclass(config) and not isinstance(config, type)
        else to_jsonable(config),
        "extra": to_jsonable(dict(extra or {})),
        "files": {fmt: p.name for fmt, p in paths.items()},
    }
    meta_text = json.dumps(meta, indent=2, allow_nan=False) + "\n"
    writers: list[tuple[Path, str, Callable[[IO[Any]], Any]]] = [
        (paths["parquet"], "wb", lambda fh: table.to_parquet(fh, index=False)),
        (paths["csv"], "w", lambda fh: table.to_csv(fh, index=False)),
        (paths["json"], "w", lambda fh: fh.write(meta_text)),  # last: marks completion
    ]
    # The old metadata goes first: a run killed between two files leaves no table listed
    # (its files each whole, old or new), never new rows under the old config.
    with contextlib.suppress(FileNotFoundError):
        os.unlink(paths["json"])
    for path, mode, write in writers:
        with atomic_write(path, mode) as fh:
            write(fh)
    return paths


class ResultsDir:
    """Read a results folder written by :func:`write_results`.

    Examples
    --------
    >>> import tempfile
    >>> d = tempfile.mkdtemp()
    >>> _ = write_results(d, table=pd.DataFrame({"a": [1, 2]}), config={"k": 1}, name="t")
    >>> r = ResultsDir(d)
    >>> r.names, r.table("t")["a"].tolist(), r.config("t")
    (['t'], [1, 2], {'k': 1})
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise ValueError(f"results folder {str(self.path)!r} does not exist")

    def __repr__(self) -> str:
        return f"ResultsDir({str(self.path)!r}, names={self.names!r})"

    @property
    def names(self) -> list[str]:
        """Complete tables (metadata and Parquet present), sorted."""
        return sorted(
            p.stem
            for p in self.path.glob("*.json")
            if not p.name.startswith(".") and (self.path / f"{p.stem}.parquet").is_file()
        )

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self.names

    def _require(self, name: str) -> None:
        if name not in self:
            present = ", ".join(self.names) or "none"
            raise ValueError(
                f"no table {name!r} in results folder {str(self.path)!r}; present: {present}"
            )

    def table(self, name: str) -> pd.DataFrame:
        """The table ``name`` (read from Parquet)."""
        self._require(name)
        return pd.read_parquet(self.path / f"{name}.parquet")

    def meta(self, name: str) -> dict[str, Any]:
        """The metadata of ``name``: version, created, config, extra, columns, n_rows.

        A file that is not a JSON object with a ``config`` is a ``ValueError`` naming it.
        """
        self._require(name)
        path = self.path / f"{name}.json"
        try:
            meta = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"results file {str(path)!r} is not valid JSON: {exc}") from None
        if not isinstance(meta, dict) or "config" not in meta:
            raise ValueError(
                f"results file {str(path)!r} must hold a JSON object with a 'config', "
                f"got {type(meta).__name__}{' without config' if isinstance(meta, dict) else ''}"
            )
        return meta

    def config(self, name: str) -> Any:
        """The config stored with ``name`` (plain JSON types)."""
        return self.meta(name)["config"]

    def tables(self) -> dict[str, pd.DataFrame]:
        """Every complete table, by name."""
        return {n: self.table(n) for n in self.names}
