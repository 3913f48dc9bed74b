"""Traces as one Parquet file: the channel in row groups of ticks, read window by window.

Layout (``solvers/README.md``): one row per tick (``tick``, ``ul_bpss`` and ``dl_bpss`` as
``fixed_size_list<double>[n_stations]``) in row groups of ``ticks_per_group`` ticks, and one
row per admitted frame (the columns of :attr:`Trace.COLUMNS`, int64) in row groups of their
own; each row leaves the other kind's columns null. The key-value metadata ``codesign`` holds
the header (:class:`ParquetHeader`: format, config, sizes, which row groups are which), so
:class:`ParquetTrace` reads the frames table and then only the row groups of the ticks asked
for: the channel of a long trace is never in memory whole.

Validation is :class:`~codesign_mb.wifi.sim.TraceFile`'s (every number finite and in range,
station ids, deadlines after the capture and within the horizon), with one-line errors that
name the field and the file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa  # type: ignore[import-untyped]
import pyarrow.parquet as pq  # type: ignore[import-untyped]
from numpy.typing import NDArray

from codesign_mb.core.config import (
    ROBOTS_CAP,
    STEPS_CAP,
    Cap,
    ConfigError,
    check_range,
    from_mapping,
    show,
    to_mapping,
)
from codesign_mb.core.results import atomic_write
from codesign_mb.wifi.config import WifiConfig
from codesign_mb.wifi.sim import TRACE_CELLS_CAP, Trace, check_frames

__all__ = [
    "PARQUET_FORMAT",
    "ParquetHeader",
    "ParquetTrace",
    "TraceWriter",
    "load_parquet",
    "save_parquet",
]

PARQUET_FORMAT = "codesign-wifi-trace-parquet/1"
TICKS_PER_GROUP = 2000
"""Ticks of a channel row group (2 s of 1 ms ticks: 0.8 MB per 48 stations and hop)."""
FRAMES_PER_GROUP = 200_000
STREAMED_TICKS_CAP = Cap(100_000_000, "ticks of a trace read by window: 27 h of 1 ms ticks")
_META_KEY = b"codesign"
_CHANNEL = ("tick", "ul_bpss", "dl_bpss")


def _schema(n_stations: int) -> pa.Schema:
    row = pa.list_(pa.float64(), n_stations)
    channel = [("tick", pa.int64()), ("ul_bpss", row), ("dl_bpss", row)]
    return pa.schema(channel + [(c, pa.int64()) for c in Trace.COLUMNS])


@dataclass(frozen=True)
class ParquetHeader:
    """The key-value metadata ``codesign`` of a Parquet trace, checked by ``from_mapping``."""

    format: str
    horizon_ticks: int
    n_stations: int
    ticks_per_group: int
    channel_groups: tuple[int, ...]
    frame_groups: tuple[int, ...]
    config: dict[str, Any]
    comment: str = ""

    def __post_init__(self) -> None:
        if self.format != PARQUET_FORMAT:
            raise ValueError(f"format must be {PARQUET_FORMAT!r}, got {show(self.format)}")
        check_range("horizon_ticks", self.horizon_ticks, ge=1, cap=STREAMED_TICKS_CAP)
        check_range("n_stations", self.n_stations, ge=1, cap=ROBOTS_CAP)
        check_range("ticks_per_group", self.ticks_per_group, ge=1)
        groups = math.ceil(self.horizon_ticks / self.ticks_per_group)
        if len(self.channel_groups) != groups:
            raise ValueError(
                f"channel_groups must list {groups} row groups (horizon_ticks "
                f"{self.horizon_ticks} / ticks_per_group {self.ticks_per_group}), "
                f"got {len(self.channel_groups)}"
            )
        both = self.channel_groups + self.frame_groups
        if len(set(both)) != len(both):
            raise ValueError("channel_groups and frame_groups must name distinct row groups")

    def group_ticks(self, g: int) -> tuple[int, int]:
        """Ticks ``[first, end)`` of channel row group ``g`` (its index in channel_groups)."""
        first = g * self.ticks_per_group
        return first, min(first + self.ticks_per_group, self.horizon_ticks)


class TraceWriter:
    """Write a trace as it is recorded: ticks and frames in, row groups out (atomically).

    Use as a context manager; the file appears at ``path`` when the block ends without an
    error, holding ``horizon_ticks`` ticks (:meth:`add_ticks`) and the frames added.
    """

    def __init__(
        self,
        path: str | Path,
        config: WifiConfig,
        n_stations: int,
        horizon_ticks: int,
        *,
        ticks_per_group: int = TICKS_PER_GROUP,
        comment: str = "",
    ) -> None:
        check_range("ticks_per_group", ticks_per_group, ge=1)
        check_range("horizon_ticks", horizon_ticks, ge=1, cap=STREAMED_TICKS_CAP)
        planned = tuple(range(math.ceil(horizon_ticks / ticks_per_group)))  # set at close
        self.header = ParquetHeader(
            format=PARQUET_FORMAT,
            horizon_ticks=horizon_ticks,
            n_stations=n_stations,
            ticks_per_group=ticks_per_group,
            channel_groups=planned,
            frame_groups=(),
            config=to_mapping(config),
            comment=comment,
        )
        self._schema = _schema(n_stations)
        self._stack = contextlib.ExitStack()
        fh = self._stack.enter_context(atomic_write(path, "wb"))
        self._writer = pq.ParquetWriter(fh, self._schema, compression="zstd")
        self._groups: dict[str, list[int]] = {"channel": [], "frames": []}
        self._ul: list[NDArray[np.float64]] = []
        self._dl: list[NDArray[np.float64]] = []
        self._ticks = 0  # ticks written to row groups
        self._pending = 0  # ticks buffered
        self._frames: list[dict[str, NDArray[np.int64]]] = []
        self._pending_frames = 0

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
            return
        with contextlib.suppress(Exception):
            self._writer.close()
        self._stack.__exit__(kind, exc, tb)  # the temporary file is removed

    def add_ticks(self, ul_bpss: NDArray[np.float64], dl_bpss: NDArray[np.float64]) -> None:
        """Append ticks: ``(n_stations, k)`` arrays; full row groups are written at once."""
        ul, dl = np.asarray(ul_bpss, dtype=float), np.asarray(dl_bpss, dtype=float)
        if ul.shape != dl.shape or ul.ndim != 2 or ul.shape[0] != self.header.n_stations:
            raise ValueError(
                f"ul_bpss and dl_bpss must both have shape ({self.header.n_stations}, k), "
                f"got {ul.shape} and {dl.shape}"
            )
        if self._ticks + self._pending + ul.shape[1] > self.header.horizon_ticks:
            raise ValueError(f"more than horizon_ticks = {self.header.horizon_ticks} ticks")
        self._ul.append(ul)
        self._dl.append(dl)
        self._pending += ul.shape[1]
        while self._pending >= self.header.ticks_per_group:
            self._flush_ticks(self.header.ticks_per_group)

    def _flush_ticks(self, k: int) -> None:
        ul, dl = np.concatenate(self._ul, axis=1), np.concatenate(self._dl, axis=1)
        self._ul, self._dl = [ul[:, k:]], [dl[:, k:]]
        self._pending -= k
        n = self.header.n_stations
        columns: dict[str, pa.Array] = {
            "tick": pa.array(np.arange(self._ticks, self._ticks + k, dtype=np.int64)),
            "ul_bpss": pa.FixedSizeListArray.from_arrays(pa.array(ul[:, :k].T.ravel()), n),
            "dl_bpss": pa.FixedSizeListArray.from_arrays(pa.array(dl[:, :k].T.ravel()), n),
        }
        self._ticks += k
        self._write("channel", columns, k)

    def add_frames(self, frames: pd.DataFrame) -> None:
        """Append admitted frames (the columns of :attr:`Trace.COLUMNS`), in order; full row
        groups of frames are written at once."""
        self._frames.append({c: frames[c].to_numpy(dtype=np.int64) for c in Trace.COLUMNS})
        self._pending_frames += len(frames)
        while self._pending_frames >= FRAMES_PER_GROUP:
            self._flush_frames(FRAMES_PER_GROUP)

    def _flush_frames(self, k: int) -> None:
        table = {c: np.concatenate([part[c] for part in self._frames]) for c in Trace.COLUMNS}
        self._frames = [{c: v[k:] for c, v in table.items()}]
        self._pending_frames -= k
        self._write("frames", {c: pa.array(v[:k]) for c, v in table.items()}, k)

    def _write(self, kind: str, columns: dict[str, pa.Array], rows: int) -> None:
        full = {
            f.name: columns[f.name] if f.name in columns else pa.nulls(rows, f.type)
            for f in self._schema
        }
        self._writer.write_table(pa.table(full, schema=self._schema))
        self._groups[kind].append(len(self._groups["channel"]) + len(self._groups["frames"]))

    def close(self) -> None:
        """Write the last row groups and the header; the file is then at its path."""
        if self._pending:
            self._flush_ticks(self._pending)
        if self._pending_frames:
            self._flush_frames(self._pending_frames)
        if self._ticks != self.header.horizon_ticks:
            raise ValueError(
                f"the trace has {self._ticks} ticks, not horizon_ticks = "
                f"{self.header.horizon_ticks}"
            )
        self.header = dataclasses.replace(
            self.header,
            channel_groups=tuple(self._groups["channel"]),
            frame_groups=tuple(self._groups["frames"]),
        )
        header = json.dumps(to_mapping(self.header))
        self._writer.add_key_value_metadata({_META_KEY.decode(): header})
        self._writer.close()
        self._stack.close()


def save_parquet(
    trace: Trace,
    path: str | Path,
    *,
    ticks_per_group: int = TICKS_PER_GROUP,
) -> None:
    """Write ``trace`` (held whole) as a Parquet trace, a row group of ticks at a time."""
    with TraceWriter(
        path, trace.config, trace.n_stations, trace.horizon_ticks, ticks_per_group=ticks_per_group
    ) as writer:
        writer.add_frames(trace.frames)
        for g in range(math.ceil(trace.horizon_ticks / ticks_per_group)):
            writer.add_ticks(*trace.channel(g * ticks_per_group, (g + 1) * ticks_per_group))


class ParquetTrace:
    """A Parquet trace opened for reading by window: header and frames in memory, channel not.

    Satisfies :class:`~codesign_mb.wifi.offline_windows.TraceSource`. :meth:`open` checks the
    whole file, one row group at a time. Pickled (to a pool's worker), it leaves its frames
    table behind: a worker reads ticks with :meth:`channel`.
    """

    def __init__(self, path: Path, header: ParquetHeader, frames: pd.DataFrame) -> None:
        self.path = path
        self.header = header
        self.config = from_mapping(WifiConfig, header.config, where="config")
        self.horizon_ticks = header.horizon_ticks
        self.n_stations = header.n_stations
        self.frames = frames
        self._file: pq.ParquetFile | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "frames": None, "_file": None}

    @classmethod
    def open(cls, path: str | Path) -> ParquetTrace:
        """Open and check the trace at ``path``; errors are one line naming field and file."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"instance file {str(path)!r} does not exist")
        try:
            pf = pq.ParquetFile(path)
            header = _read_header(pf)
            _check_layout(pf, header)
            frames = _read_frames(pf, header)
            trace = cls(path, header, frames)
            for g in range(len(header.channel_groups)):
                _read_ticks(pf, header, g, check=True)
        except (pa.ArrowException, OSError) as exc:
            raise ValueError(
                f"instance file {str(path)!r} is not a readable Parquet trace: {exc}"
            ) from None
        except ValueError as exc:
            raise ConfigError(f"{exc} (instance file {str(path)!r})") from exc
        trace._file = pf
        return trace

    def channel(
        self, first_tick: int, end_tick: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``ul_bpss`` and ``dl_bpss`` of ticks ``[first_tick, end_tick)``, ``(n_stations, k)``,
        read from the row groups that hold them only."""
        if not 0 <= first_tick < end_tick <= self.horizon_ticks:
            raise ValueError(
                f"ticks [{first_tick}, {end_tick}) are not in [0, {self.horizon_ticks})"
            )
        check_range(
            f"ul_bpss and dl_bpss of ticks [{first_tick}, {end_tick})",
            (end_tick - first_tick) * self.n_stations,
            cap=TRACE_CELLS_CAP,
        )
        if self._file is None:
            self._file = pq.ParquetFile(self.path)
        tpg = self.header.ticks_per_group
        g0, g1 = first_tick // tpg, (end_tick - 1) // tpg
        groups = [self.header.channel_groups[g] for g in range(g0, g1 + 1)]
        table = self._file.read_row_groups(groups, columns=["ul_bpss", "dl_bpss"])
        table = table.slice(first_tick - g0 * tpg, end_tick - first_tick)
        return _matrix(table, "ul_bpss", self.n_stations), _matrix(
            table, "dl_bpss", self.n_stations
        )

    def to_trace(self) -> Trace:
        """The whole trace in memory (capped like a JSON instance)."""
        where = f" (instance file {str(self.path)!r})"
        try:
            check_range("horizon_ticks", self.horizon_ticks, cap=STEPS_CAP)
            check_range(
                "ul_bpss and dl_bpss", self.n_stations * self.horizon_ticks, cap=TRACE_CELLS_CAP
            )
        except ValueError as exc:
            raise ConfigError(f"{exc}{where}") from exc
        ul, dl = self.channel(0, self.horizon_ticks)
        return Trace(self.config, self.horizon_ticks, ul, dl, self.frames)


def load_parquet(path: str | Path) -> Trace:
    """Read a Parquet trace whole (:meth:`ParquetTrace.open`, :meth:`ParquetTrace.to_trace`)."""
    return ParquetTrace.open(path).to_trace()


def _read_header(pf: pq.ParquetFile) -> ParquetHeader:
    raw = (pf.metadata.metadata or {}).get(_META_KEY)
    if raw is None:
        raise ValueError(
            f"a Parquet trace needs the key-value metadata 'codesign' (format {PARQUET_FORMAT!r})"
        )
    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"the metadata 'codesign' is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"the metadata 'codesign' must be a JSON object, got {show(data)}")
    return from_mapping(ParquetHeader, data)


def _check_layout(pf: pq.ParquetFile, header: ParquetHeader) -> None:
    """The columns' types and the row groups' sizes the header announces."""
    expected = _schema(header.n_stations)
    schema = pf.schema_arrow
    for f in expected:
        got = schema.field(f.name).type if f.name in schema.names else None
        if got != f.type:
            raise ValueError(f"column {f.name} must be of type {f.type}, got {got}")
    n_groups = pf.metadata.num_row_groups
    for i in header.channel_groups + header.frame_groups:
        check_range("channel_groups and frame_groups", i, ge=0, le=n_groups - 1)
    for g, i in enumerate(header.channel_groups):
        first, end = header.group_ticks(g)
        rows = pf.metadata.row_group(i).num_rows
        if rows != end - first:
            raise ValueError(f"row group {i} must hold ticks [{first}, {end}), got {rows} rows")


def _read_frames(pf: pq.ParquetFile, header: ParquetHeader) -> pd.DataFrame:
    columns = list(Trace.COLUMNS)
    if header.frame_groups:
        table = pf.read_row_groups(list(header.frame_groups), columns=columns)
    else:
        table = pa.table({c: pa.array([], pa.int64()) for c in columns})
    for c in columns:
        if table.column(c).null_count:
            raise ValueError(f"frames.{c} must be an integer in every frame row, got null")
    frames = pd.DataFrame({c: table.column(c).to_numpy() for c in columns})
    check_frames(
        {c: frames[c].to_numpy() for c in columns}, header.n_stations, header.horizon_ticks
    )
    return frames


def _read_ticks(
    pf: pq.ParquetFile, header: ParquetHeader, g: int, *, check: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Channel row group ``g``: ``(n_stations, k)`` UL and DL matrices, checked if ``check``."""
    first, end = header.group_ticks(g)
    table = pf.read_row_group(header.channel_groups[g], columns=list(_CHANNEL))
    if check:
        ticks = table.column("tick")
        if ticks.null_count or not np.array_equal(ticks.to_numpy(), np.arange(first, end)):
            raise ValueError(
                f"tick of row group {header.channel_groups[g]} must run {first}..{end - 1}"
            )
    ul, dl = (_matrix(table, name, header.n_stations) for name in ("ul_bpss", "dl_bpss"))
    if check:
        for name, m in (("ul_bpss", ul), ("dl_bpss", dl)):
            bad = np.argwhere(~np.isfinite(m))
            if bad.size:
                s, k = bad[0]
                raise ValueError(
                    f"{name} must be finite, got {m[s, k]} at station {s}, tick {first + k}"
                )
            check_range(name, m.min(), ge=0)
    return ul, dl


def _matrix(table: pa.Table, name: str, n_stations: int) -> NDArray[np.float64]:
    column = table.column(name)
    if column.null_count:
        raise ValueError(f"{name} must be a list of {n_stations} numbers at every tick, got null")
    values = column.combine_chunks().flatten().to_numpy(zero_copy_only=False)
    return np.asarray(values, dtype=np.float64).reshape(-1, n_stations).T
