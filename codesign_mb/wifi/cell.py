"""N robots on one WiFi 6 channel: the shared cell, its per-station ``Link``s, lockstep rollouts.

Lockstep
--------
Robot ``i`` captures its step-``t`` camera frame at tick ``c_i(t) = t * P + o_i`` (``P`` = 40
ticks, ``o_i`` its capture offset) and reads its step-``t`` observation at the same instant,
so a state is delivered with latency ``tau`` iff both its frames arrive by ``c_i(t + tau)``
([deadline]). :meth:`WifiLink.step` advances the shared channel *lazily* to ``c_i(t)``:
that needs every frame captured before then, i.e. every other robot ``j`` must already have
submitted its step whose capture precedes ``c_i(t)``. Stepping the robots round-robin in
order of their offsets (:attr:`SharedChannel.step_order`) guarantees it, and
:func:`codesign_mb.rollout.rollout_shared` does exactly that; a robot that runs ahead raises
``RuntimeError``.
Because a camera frame needs airtime, ``tau = 0`` cannot be met on this link and is rejected.

Channel process
---------------
Distances are drawn once per episode, Rician block-fading gains once per coherence block per
station (the same for UL and DL), then link adaptation picks each hop's MCS (``choose_mcs``).
A frame's fate on each hop is drawn when it is admitted, with that hop's delivery probability.
``eq_drop``'s ``q0`` is the station's own link-level delivery in the current block (the product
of its hops' delivery probabilities, :attr:`ChannelProcess.delivery`), not a configured
constant, so a robot that asks for ``q`` on an unloaded link gets ``q`` (or all the link
delivers, when that is less).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.config import check_range
from codesign_mb.network.link import ObservationBuffer, Packet, Reception
from codesign_mb.network.qos import QosRequest
from codesign_mb.wifi.config import WifiConfig, make_allocator
from codesign_mb.wifi.engine import ChannelEngine, FallbackCount, Frame
from codesign_mb.wifi.recorder import TraceChunk, TraceRecorder, TrafficOnlyEngine
from codesign_mb.wifi.sim import TRACE_CELLS_CAP, Trace
from codesign_mb.wifi.traffic import drop_probability

__all__ = [
    "ChannelProcess",
    "SharedChannel",
    "TraceChunk",
    "WifiLink",
    "generate_trace",
    "join_chunks",
    "record_trace",
]


class ChannelProcess:
    """Seeded per-station SNR, MCS and delivery probability over time ([snr], [per])."""

    def __init__(self, config: WifiConfig, n_stations: int, rng: np.random.Generator) -> None:
        self.config = config
        self.n = n_stations
        ch = config.channel
        place_rng, self._fade_rng = rng.spawn(2)
        self.distances_m = ch.place(n_stations, place_rng)
        self.block_ticks = max(1, round(ch.coherence_ms * 1000.0 / config.mac.tick_us))
        mac, traffic = config.mac, config.traffic
        self.ul_bytes = mac.psdu_bits(traffic.ul_frame_bytes) / 8
        self.dl_bytes = mac.psdu_bits(traffic.dl_frame_bytes) / 8
        self._block = -1
        self.ul_snr_db = self.dl_snr_db = np.zeros(n_stations)
        self.ul_mcs = self.dl_mcs = np.zeros(n_stations, dtype=np.int64)
        self.ul_pdr = self.dl_pdr = np.zeros(n_stations)
        self.ul_bpss = self.dl_bpss = np.zeros(n_stations)

    def at(self, tick: int) -> None:
        """Make the state current for ``tick`` (draws a new block when one starts)."""
        block = tick // self.block_ticks
        while self._block < block:
            self._block += 1
            self._draw()

    @property
    def delivery(self) -> NDArray[np.float64]:
        """Per station, the probability that a frame's UL and DL hops both get through in
        the current block: the link-level PDR ``q0`` of ``eq_drop``."""
        return self.ul_pdr * self.dl_pdr

    def _draw(self) -> None:
        ch, phy = self.config.channel, self.config.phy
        gain = ch.fading_gain((self.n,), self._fade_rng)
        bw = phy.bandwidth_mhz
        self.ul_snr_db = ch.snr_db(self.distances_m, gain, bw, uplink=True)
        self.dl_snr_db = ch.snr_db(self.distances_m, gain, bw, uplink=False)
        self.ul_mcs, self.ul_pdr = ch.adapt(self.ul_snr_db, self.ul_bytes)
        self.dl_mcs, self.dl_pdr = ch.adapt(self.dl_snr_db, self.dl_bytes)
        self.ul_bpss = phy.bits_per_subcarrier_symbol(self.ul_mcs)
        self.dl_bpss = phy.bits_per_subcarrier_symbol(self.dl_mcs)


@dataclass
class _Station:
    """One robot in the cell: its step, frame-dropping stream, observation buffer, tallies.

    ``t`` is the step of the robot's current episode, which began at the channel's step
    ``origin`` (0 but after :meth:`SharedChannel.rejoin`); the tallies run over every episode
    since the channel's reset.
    """

    rng: np.random.Generator
    buffer: ObservationBuffer
    t: int = 0
    origin: int = 0
    active: bool = True
    requested: float = 0.0
    admitted: int = 0
    steps: int = 0

    def restart(self, rng: np.random.Generator, buffer: ObservationBuffer) -> None:
        """Start a new episode with these stream and buffer."""
        self.rng, self.buffer = rng, buffer
        self.t, self.active = 0, True


class SharedChannel:
    """One WiFi 6 cell shared by ``n_stations`` robots; :attr:`links` are their ``Link``s.

    Parameters
    ----------
    config:
        The cell; ``config.scheduler`` picks the allocator unless ``scheduler`` is given.
    n_stations:
        Number of robots.
    seed:
        Seed of the channel (placement, fading, frame fates) and the default seeds of the
        stations' frame-dropping streams; :meth:`reset` may replace it.
    scheduler:
        Overrides ``config.scheduler``.

    The episode's results: :meth:`summary` (per station), :attr:`fallbacks` (ticks whose
    allocator could not use its solver's solution) and :meth:`trace`.

    Examples
    --------
    >>> ch = SharedChannel(WifiConfig(), 2, seed=0)
    >>> ch.reset(seed=0)
    >>> for link in ch.links:
    ...     link.reset(prior=[0.0])
    >>> rx = [ch.links[i].step([1.0], QosRequest(1.0, 1)) for i in ch.step_order]
    >>> [r.age for r in rx]
    [1, 1]
    """

    def __init__(
        self,
        config: WifiConfig,
        n_stations: int,
        *,
        seed: int | None = None,
        scheduler: str | None = None,
    ) -> None:
        if isinstance(n_stations, bool) or not isinstance(n_stations, int) or n_stations < 1:
            raise ValueError(f"n_stations must be an integer >= 1, got {n_stations!r}")
        self.config = config
        self.n = n_stations
        self.scheduler = scheduler or config.scheduler
        self.seed = seed
        tick_us = config.mac.tick_us
        self.period_ticks = config.traffic.period_ticks(tick_us)
        self.offsets = config.traffic.offsets_ticks(n_stations, tick_us)
        self.step_order: tuple[int, ...] = tuple(
            int(i) for i in np.lexsort((np.arange(n_stations), self.offsets))
        )
        self.ul_bits = config.mac.psdu_bits(config.traffic.ul_frame_bytes)
        self.dl_bits = config.mac.psdu_bits(config.traffic.dl_frame_bytes)
        self.links: tuple[WifiLink, ...] = tuple(WifiLink(self, i) for i in range(n_stations))
        self.reset(seed=seed)

    # ------------------------------------------------------------------ episodes
    def reset(self, *, seed: int | None = None) -> None:
        """Start an episode: empty queues, tick 0, new placement and fading from ``seed``."""
        if seed is not None:
            self.seed = seed
        root = np.random.SeedSequence(self.seed)
        chan_ss, fate_ss, drop_ss = root.spawn(3)
        self.process = ChannelProcess(self.config, self.n, np.random.default_rng(chan_ss))
        self._fate_rng = np.random.default_rng(fate_ss)
        self._drop_seeds = drop_ss.spawn(self.n)
        self.engine = ChannelEngine(
            self.config,
            self.n,
            make_allocator(self.config, self.n, self.scheduler),
            make_allocator(self.config, self.n, self.scheduler),
        )
        self._recorder = TraceRecorder()
        self._stations = [
            _Station(np.random.default_rng(s), ObservationBuffer()) for s in self._drop_seeds
        ]
        self._frames: list[Frame] = []

    @property
    def started(self) -> bool:
        """Whether any station has stepped in this episode."""
        return self.engine.tick > 0 or any(s.t > 0 for s in self._stations)

    def capture_tick(self, station: int, step: int) -> int:
        """``c_i(t)``: the tick robot ``station`` captures (and reads) step ``step``.

        ``step`` counts from the start of the robot's current episode.
        """
        step += self._stations[station].origin
        return step * self.period_ticks + int(self.offsets[station])

    def rejoin(self, station: int) -> None:
        """Robot ``station`` starts its next episode at its next step, the others going on.

        Continuous operation (a robot picks one object after another): its queued frames are
        dropped, its step count restarts from 0 at the channel's current step for it; the
        link's :meth:`WifiLink.reset` then gives it a new buffer (and stream) without
        restarting the channel.
        """
        st = self._stations[station]
        self.engine.drop_station(station)
        self.engine.delivered[station].clear()
        st.origin += st.t
        st.t, st.active = 0, True

    # ------------------------------------------------------------------ time
    def _advance_to(self, tick: int, station: int) -> None:
        for j, st in enumerate(self._stations):
            if j != station and st.active and self.capture_tick(j, st.t) < tick:
                raise RuntimeError(
                    f"lockstep violated: station {station} reached tick {tick} while station "
                    f"{j} has not sent its step {st.t} (captured at tick "
                    f"{self.capture_tick(j, st.t)}); step the robots in channel.step_order"
                )
        engine, process = self.engine, self.process
        while engine.tick < tick:
            process.at(engine.tick)
            self._recorder.ul.append(process.ul_bpss.copy())
            self._recorder.dl.append(process.dl_bpss.copy())
            engine.run_tick(process.ul_bpss, process.dl_bpss)

    def _submit(self, station: int, value: NDArray, qos: QosRequest) -> Reception:
        st = self._stations[station]
        if not st.active:
            raise RuntimeError(f"station {station} was closed; reset it first")
        if qos.latency_steps < 1:
            raise ValueError(
                "latency_steps must be >= 1 on a WiFi link (the camera and state frames need "
                f"airtime), got {qos.latency_steps}"
            )
        t = st.t
        cap = self.capture_tick(station, t)
        self._advance_to(cap, station)
        self.process.at(cap)
        # eq_drop: one uniform per step whatever q is, so streams align across QoS policies.
        u = st.rng.random()
        admitted = qos.reliability > 0 and u >= self._drop_probability(station, qos.reliability)
        fate = self._fate_rng.random(2)  # drawn for every step, admitted or not
        st.requested += qos.reliability
        st.steps += 1
        if admitted:
            deadline = cap + qos.latency_steps * self.period_ticks  # [deadline]
            ul_ok = bool(fate[0] < self.process.ul_pdr[station])
            dl_ok = bool(fate[1] < self.process.dl_pdr[station])
            frame = Frame(
                station, t, cap, deadline, self.ul_bits, self.dl_bits, ul_ok, dl_ok, value
            )
            self.engine.add(frame)
            self._frames.append(frame)
            self._recorder.frames.append(
                (
                    station,
                    st.origin + t,
                    cap,
                    deadline,
                    self.ul_bits,
                    self.dl_bits,
                    int(ul_ok),
                    int(dl_ok),
                )
            )
            st.admitted += 1
        buffer = st.buffer
        arrived = self.engine.delivered[station]
        for frame in arrived:
            buffer.push(Packet(frame.step, frame.value), t)
        arrived.clear()
        st.t = t + 1
        return buffer.receive(t, delivered=admitted, like=value)

    def _drop_probability(self, station: int, reliability: float) -> float:
        """``eq_drop`` with ``q0`` the station's own link delivery in this coherence block.

        ``q0`` is :attr:`ChannelProcess.delivery` (the product of the station's UL and DL
        frame delivery probabilities at the MCS link adaptation chose, which the AP knows), so
        an unloaded link delivers a frame with probability ``q`` when ``q <= q0`` and ``q0``
        above. A link that delivers nothing (``q0 = 0``) drops nothing: the limit as ``q0``
        falls to 0.
        """
        link = float(self.process.delivery[station])
        return drop_probability(reliability, link) if link > 0.0 else 0.0

    def close(self, station: int) -> None:
        """The robot of ``station`` left (episode over): drop its queue, stop waiting for it."""
        self._stations[station].active = False
        self.engine.drop_station(station)

    # ------------------------------------------------------------------ results
    def summary(self) -> pd.DataFrame:
        """Per station: frames admitted/delivered/late/lost, latency, RU airtime, mean q."""
        table = self.engine.summary()
        table["steps"] = [s.steps for s in self._stations]
        table["mean_reliability"] = [
            s.requested / s.steps if s.steps else np.nan for s in self._stations
        ]
        table["distance_m"] = self.process.distances_m
        table["offset_ticks"] = self.offsets
        return table

    @property
    def fallbacks(self) -> FallbackCount:
        """Ticks of this episode whose allocator fell back from its solver (UL, DL)."""
        return self.engine.fallbacks

    def trace(self) -> Trace:
        """The episode so far as a :class:`Trace` (admitted frames and channel per tick)."""
        return self._recorder.trace(self.config, self.n)


class WifiLink:
    """Station ``index`` of a :class:`SharedChannel`, as a :class:`codesign_mb.network.Link`.

    :meth:`step` sends ``x_t`` as a camera frame (dropped before the queue with probability
    ``1 - q/q0``, ``eq_drop``, ``q0`` this station's link delivery in the current coherence
    block: :attr:`ChannelProcess.delivery`) with deadline ``tau`` steps, advances the shared
    channel to this robot's step ``t`` and returns what has arrived. ``Reception.delivered``
    is whether the frame was admitted to the queue: whether it arrives in time is known only
    later.
    """

    def __init__(self, channel: SharedChannel, index: int) -> None:
        self.channel = channel
        self.index = index

    @classmethod
    def single(cls, config: WifiConfig | None = None, *, seed: int | None = None) -> WifiLink:
        """A link alone on its own channel (one robot)."""
        return SharedChannel(config or WifiConfig(), 1, seed=seed).links[0]

    def reset(self, *, seed: int | None = None, prior: ArrayLike | None = None) -> None:
        """Start this robot's episode; restarts the channel if this robot had already stepped.

        After :meth:`SharedChannel.rejoin` the robot is at step 0 again: only its buffer (and,
        with a ``seed``, its stream) is renewed, the channel goes on.

        With a ``seed``, the station's frame-dropping stream is re-seeded with it, and so is the
        channel of a single-station cell: a single-robot episode is reproducible from its seed.
        """
        ch = self.channel
        if ch._stations[self.index].t > 0 or (ch.n == 1 and seed is not None):
            ch.reset(seed=seed)  # this robot starts a new episode: so does the channel
        st = ch._stations[self.index]
        rng = st.rng if seed is None else np.random.default_rng(seed)
        st.restart(rng, ObservationBuffer(prior))

    def step(self, state: ArrayLike, qos: QosRequest) -> Reception:
        value = np.array(state, dtype=float)
        return self.channel._submit(self.index, value, qos)

    def close(self) -> None:
        """This robot's episode is over; the others go on without waiting for it."""
        self.channel.close(self.index)


# --------------------------------------------------------------------------- drivers


def record_trace(
    config: WifiConfig,
    n_stations: int,
    *,
    steps: int,
    reliability: float | Sequence[float] = 1.0,
    latency_steps: int = 1,
    seed: int = 0,
    chunk_steps: int = 250,
) -> Iterator[TraceChunk]:
    """:func:`generate_trace`'s recording, ``chunk_steps`` control steps at a time.

    Yields consecutive :class:`TraceChunk` s whose ticks and frames, put end to end, are
    ``generate_trace``'s trace bit for bit whatever ``chunk_steps``: the chunks only cut the
    same lockstep run (every random stream is drawn in the same order), and hold about
    ``chunk_steps`` steps of channel and frames each, so a trace too long to hold (an hour of
    48 robots) is written as it is recorded (``codesign wifi trace OUT.parquet``).
    """
    check_range("chunk_steps", chunk_steps, ge=1)
    q = np.broadcast_to(np.asarray(reliability, dtype=float), (n_stations,))
    channel = SharedChannel(config, n_stations, seed=seed, scheduler="greedy")
    for link in channel.links:
        link.reset(prior=np.zeros(1))
    engine = channel.engine  # traffic only: no allocation needed to record a trace
    channel.engine = TrafficOnlyEngine(config, n_stations, engine.ul_allocator, engine.dl_allocator)
    for first in range(0, steps, chunk_steps):
        for _ in range(first, min(first + chunk_steps, steps)):
            for i in channel.step_order:
                channel._submit(i, np.zeros(1), QosRequest(float(q[i]), latency_steps))
        channel._frames.clear()  # the recorder has them; the engine queues nothing
        yield channel._recorder.take(n_stations)
    for i in range(n_stations):
        channel.close(i)
    channel._advance_to((steps + latency_steps) * channel.period_ticks, -1)
    yield channel._recorder.take(n_stations)


def generate_trace(
    config: WifiConfig,
    n_stations: int,
    *,
    steps: int,
    reliability: float | Sequence[float] = 1.0,
    latency_steps: int = 1,
    seed: int = 0,
) -> Trace:
    """A trace of ``steps`` control steps of static-QoS traffic (no robots), for the allocators.

    Every robot requests ``reliability`` (one value or one per station) and ``latency_steps``;
    frames are admitted by ``eq_drop`` and the channel runs ``latency_steps`` steps past the
    last capture so every deadline falls inside the horizon. The trace is held whole, so its
    size is capped (:data:`~codesign_mb.wifi.sim.TRACE_CELLS_CAP`); :func:`record_trace` gives
    the same recording in parts.
    """
    ticks = (steps + latency_steps) * config.traffic.period_ticks(config.mac.tick_us)
    check_range("robots x ticks of the trace", n_stations * ticks, cap=TRACE_CELLS_CAP)
    chunks = record_trace(
        config,
        n_stations,
        steps=steps,
        reliability=reliability,
        latency_steps=latency_steps,
        seed=seed,
        chunk_steps=max(steps, 1),
    )
    return join_chunks(config, chunks)


def join_chunks(config: WifiConfig, chunks: Iterable[TraceChunk]) -> Trace:
    """The whole :class:`Trace` of :func:`record_trace`'s chunks, put end to end."""
    parts = list(chunks)
    return Trace(
        config=config,
        horizon_ticks=sum(c.ul_bpss.shape[1] for c in parts),
        ul_bpss=np.concatenate([c.ul_bpss for c in parts], axis=1),
        dl_bpss=np.concatenate([c.dl_bpss for c in parts], axis=1),
        frames=pd.concat([c.frames for c in parts], ignore_index=True),
    )
