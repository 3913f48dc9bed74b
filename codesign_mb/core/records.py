"""Finished work kept as it finishes, so that an interrupted run resumes where it stopped.

Every long run (the episodes of ``codesign evaluate``, ``evaluate fig-cn`` and ``table``, the
trials of ``sweep`` and ``wifi capacity``, and so the studies of ``paper``) hands each
finished item to a :class:`RecordStore` in its results folder the moment the driver
receives it::

    out/.records/<group>.jsonl    one JSON line per finished item, appended

A *group* is a set of items that share everything but their own index and seed (e.g. the
episodes of one table cell); its name is the :func:`digest` of what determines them: the
components (with the content of their checkpoints), the plant, the settings, the root seed.
An *item* is named within its group (e.g. ``"<episode>:<seed>"``). A rerun reads the stored
items and computes only the others; a changed setting names another group, so a stale row
is never reused. The code is not part of a key: each line records the commit (or version)
that computed it, and reusing rows of another commit is reported (a ``RuntimeWarning``);
``fresh`` recomputes everything.

Rows round-trip exactly (floats by their shortest ``repr``, NaN and infinities included),
and a run uses the decoded row of a fresh item as well, so a resumed table equals an
uninterrupted one bit for bit. Each line is written by one ``write`` call, so a killed
driver leaves whole lines. Each line ends with a checksum of the rest of it
(``"sha256": <16 hex digits>``), so damage that still parses (a changed digit) is caught too.
A line that does not parse (torn by a full disk or a system crash, or damaged) or does not
match its checksum is reported by a ``RuntimeWarning`` naming the file and line, and its item
is computed again. (Lines without a checksum, written before there was one, are read as
they are.)
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import hashlib
import json
import math
import os
import pickle
import re
import warnings
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from codesign_mb.core.registry import ComponentSpec, resolve_checkpoint
from codesign_mb.core.results import file_digest, package_version, provenance

__all__ = ["RECORDS_DIR", "RecordStore", "digest"]

RECORDS_DIR = ".records"
"""The store's folder inside a results folder."""


# -- keys ---------------------------------------------------------------------------------------
def digest(identity: Any) -> str:
    """A stable 24-hex-digit key of ``identity``: everything an item's result depends on.

    ``identity`` may hold dataclasses (keyed with their type), mappings, sequences, numbers,
    strings, arrays, classes and functions (by import path). A :class:`ComponentSpec`'s
    checkpoint and any absolute path to an existing file or folder count by their content
    (:func:`~codesign_mb.core.results.file_digest`), so a retrained checkpoint at the same
    path is another key. Other objects count by their pickle.

    Examples
    --------
    >>> digest({"seed": 1, "q": 0.5}) == digest({"q": 0.5, "seed": 1})
    True
    >>> digest({"q": 0.5}) == digest({"q": 0.25})
    False
    """
    text = json.dumps(_canonical(identity), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _canonical(value: Any) -> Any:
    """``value`` as plain, finite JSON types (see :func:`digest`)."""
    if value is None or isinstance(value, bool | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else {"float": repr(value)}
    if isinstance(value, str | Path):
        return _path_or_text(str(value))
    if isinstance(value, np.generic):
        return _canonical(value.item())
    if isinstance(value, np.ndarray):
        return {
            "ndarray": str(value.dtype),
            "shape": list(value.shape),
            "data": _canonical(value.tolist()),
        }
    if isinstance(value, enum.Enum):
        return f"{type(value).__qualname__}.{value.name}"
    if isinstance(value, ComponentSpec) and value.checkpoint:
        return {**_dataclass(value), "checkpoint": _checkpoint(value.checkpoint)}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _dataclass(value)
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, set | frozenset):
        items = [_canonical(v) for v in value]
        return sorted(items, key=lambda v: json.dumps(v, sort_keys=True))
    if isinstance(value, type) or (callable(value) and hasattr(value, "__qualname__")):
        return f"{getattr(value, '__module__', '')}:{value.__qualname__}"
    return {
        "pickle": type(value).__qualname__,
        "sha256": hashlib.sha256(pickle.dumps(value)).hexdigest(),
    }


def _dataclass(value: Any) -> dict[str, Any]:
    fields = {f.name: _canonical(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return {"type": f"{type(value).__module__}.{type(value).__qualname__}", **fields}


def _path_or_text(text: str) -> Any:
    if os.path.isabs(text) and os.path.exists(text):
        return {"path": text, "content": _content(text)}
    return text


def _checkpoint(path: str) -> Any:
    try:
        resolved = resolve_checkpoint(path)
    except ValueError:
        return path  # missing: the run says so before any episode
    return {"path": path, "content": _content(str(resolved))}


def _content(path: str) -> str:
    stat = os.stat(path)
    return _cached_digest(path, stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=256)
def _cached_digest(path: str, mtime_ns: int, size: int) -> str:
    return file_digest(path)


# -- lines ----------------------------------------------------------------------------------------
_CHECKSUM = re.compile(rb', "sha256": "([0-9a-f]{16})"\}\s*$')
"""The end of a stored line: the checksum of the line without it."""


def _checksum(body: bytes) -> str:
    return hashlib.sha256(body).hexdigest()[:16]


def _with_checksum(body: str) -> str:
    """The JSON object ``body`` (``{...}``) with its checksum as its last member."""
    return f'{body[:-1]}, "sha256": "{_checksum(body.encode())}"}}'


def _verify(line: bytes, record: Mapping[str, Any]) -> None:
    """``ValueError`` if ``line`` (which parsed as ``record``) does not match its checksum."""
    if "sha256" not in record:
        return  # written before lines had one
    match = _CHECKSUM.search(line)
    if match is None or _checksum(line[: match.start()] + b"}") != match.group(1).decode():
        raise ValueError("its checksum does not match: the line was changed")


# -- the store ----------------------------------------------------------------------------------
class RecordStore:
    """The finished items of runs writing into one results folder (see the module docstring).

    Parameters
    ----------
    root:
        The store's folder, usually ``<results folder>/.records``.
    what:
        What an item is, for messages (``"episode"``, ``"trial"``).
    fresh:
        Reuse nothing: every item is computed again (and stored, replacing the old line).

    Attributes
    ----------
    computed, reused:
        Items of this run computed and stored, and items taken from the store.
    """

    def __init__(self, root: str | Path, *, what: str = "episode", fresh: bool = False) -> None:
        self.root = Path(root)
        self.what = what
        self.fresh = fresh
        self.computed = 0
        self.reused = 0
        self._code: str | None = None
        self._ended: set[Path] = set()  # files known to end with a whole line
        self._warned = False  # about rows of other code

    def __repr__(self) -> str:
        return f"RecordStore({str(self.root)!r}, what={self.what!r})"

    def path(self, group: str) -> Path:
        """The file of ``group``."""
        return self.root / f"{group}.jsonl"

    @property
    def code(self) -> str:
        """The source commit computing new items (``version X`` outside a git checkout)."""
        if self._code is None:
            self._code = provenance()["commit"] or f"version {package_version()}"
        return self._code

    def take(self, group: str, items: Iterable[str]) -> dict[str, dict[str, Any]]:
        """The stored rows of those ``items`` of ``group`` the store holds (none when fresh).

        They count as reused; rows computed by other code are reported once per store (a
        ``RuntimeWarning``). A line that does not parse is skipped with a ``RuntimeWarning``
        naming it (its item is then computed again); of two lines of one item the later wins.
        """
        stored = {} if self.fresh else self._read(self.path(group))
        found = {item: stored[item] for item in items if item in stored}
        self.reused += len(found)
        foreign: dict[str, int] = {}
        for _, code in found.values():
            if code != self.code:
                foreign[code] = foreign.get(code, 0) + 1
        if foreign and not self._warned:
            self._warned = True
            made = ", ".join(f"{n} by {code}" for code, n in foreign.items())
            warnings.warn(
                f"reusing finished {self.what}s of {self.root} computed by other code ({made}; "
                f"now {self.code}); --fresh (or deleting that folder) recomputes them",
                RuntimeWarning,
                stacklevel=2,
            )
        return {item: row for item, (row, _) in found.items()}

    def _read(self, path: Path) -> dict[str, tuple[dict[str, Any], str]]:
        """item -> (row, code) of a group's file; corrupt lines skipped with a warning."""
        if not path.is_file():
            return {}
        found: dict[str, tuple[dict[str, Any], str]] = {}
        for number, line in enumerate(path.read_bytes().splitlines(), start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                item, row = record["item"], record["row"]
                if not isinstance(item, str) or not isinstance(row, dict):
                    raise ValueError("not an item and its row")
                _verify(line, record)
            except (ValueError, KeyError, TypeError) as exc:
                warnings.warn(
                    f"record file {path} line {number} is corrupt ({_short(exc)}); its "
                    f"{self.what} is computed again",
                    RuntimeWarning,
                    stacklevel=3,
                )
                continue
            found[item] = (row, str(record.get("code")))
        return found

    def add(self, group: str, item: str, row: Mapping[str, Any]) -> dict[str, Any]:
        """Store one finished item; return its row as stored (what a rerun will read).

        Raises ``OSError`` saying what is kept when the line cannot be written (a full disk).
        """
        body = json.dumps({"item": item, "code": self.code, "row": dict(row)}, default=_plain)
        line = _with_checksum(body)
        stored: dict[str, Any] = json.loads(line)["row"]
        path = self.path(group)
        try:
            self._append(path, (line + "\n").encode())
        except OSError as exc:
            raise OSError(
                f"cannot store a finished {self.what} in {path}: "
                f"{exc.strerror or _short(exc)}; {self.kept} stored before it kept in "
                f"{self.root}, rerun the same command to resume"
            ) from exc
        self.computed += 1
        return stored

    def _append(self, path: Path, data: bytes) -> None:
        """Append ``data`` with one ``write`` (after a newline if the file ends mid-line)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            if path not in self._ended:
                size = os.fstat(fd).st_size
                if size and os.pread(fd, 1, size - 1) != b"\n":
                    data = b"\n" + data  # a torn last line stays alone, and is skipped
                self._ended.add(path)
            written = os.write(fd, data)
            while written < len(data):  # a short write (rare): the rest, in order
                written += os.write(fd, data[written:])
        except BaseException:
            self._ended.discard(path)  # part of the line may be there: check again next time
            raise
        finally:
            os.close(fd)

    @property
    def kept(self) -> str:
        """``"<n> finished <what>"`` of this run that are stored."""
        n = self.computed + self.reused
        return f"{n} finished {self.what}{'' if n == 1 else 's'}"

    def kept_message(self) -> str:
        """What an interruption keeps and how to resume."""
        return f"{self.kept} kept in {self.root}; rerun the same command to resume"

    @contextlib.contextmanager
    def on_interrupt(self) -> Iterator[None]:
        """On Ctrl-C inside the block, raise ``KeyboardInterrupt`` saying what is kept."""
        try:
            yield
        except KeyboardInterrupt as exc:
            if exc.args:  # already says it (an inner store)
                raise
            raise KeyboardInterrupt(self.kept_message()) from None


def _plain(value: Any) -> Any:
    """JSON for the numpy scalars and arrays a row may hold."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"a stored row holds a {type(value).__name__}: {value!r}")


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."
