"""``codesign wifi``: the 802.11ax rate table, traces for the allocation LP, and Fig. 6 capacity."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from codesign_mb.cli.common import (
    SCENARIO_HELP,
    ConfigOption,
    FreshOption,
    JsonOption,
    OutOption,
    SeedOption,
    cli_errors,
    comma_list,
    emit,
    explicit,
    load_config,
    note,
    progress_bar,
    track,
    writable_folder,
)

__all__ = [
    "capacity_command",
    "crosscheck_command",
    "phy_table_command",
    "register",
    "trace_command",
]


_MEASURE_WORDS = {"mean": "mean success at the target", "interval": "not below it, Wilson"}
"""How each capacity measure of ``capacity_ratios`` reads in a note."""


def _parse_robots(text: str) -> tuple[int, ...]:
    """``"1..8"``, ``"1,2,4,8"`` or ``"6"`` -> robot counts (capped before a range is made)."""
    from codesign_mb.core.config import ROBOTS_CAP, check_range

    text = text.strip()
    try:
        if ".." in text:
            lo, hi = (int(x) for x in text.split("..", 1))
            if lo > hi:
                raise ValueError
            check_range("robots", hi, cap=ROBOTS_CAP)
            return tuple(range(lo, hi + 1))
        return comma_list(text, "robots", item=int, example="1..8 or 1,2,4")
    except ValueError as exc:
        if str(exc).startswith("robots"):
            raise
        raise ValueError(f"robots must look like 1..8 or 1,2,4, got {text!r}") from None


def phy_table_command(
    bandwidth: Annotated[
        int, typer.Option("--bandwidth", "-b", help="Channel width in MHz: 20, 40 or 80.")
    ] = 40,
    gi: Annotated[
        float, typer.Option("--gi", help="Downlink (HE MU) guard interval in us: 0.8, 1.6 or 3.2.")
    ] = 0.8,
    ul_gi: Annotated[
        float, typer.Option("--ul-gi", help="Uplink (HE TB) guard interval in us: 1.6 or 3.2.")
    ] = 1.6,
    streams: Annotated[int, typer.Option("--streams", help="Spatial streams: 1 or 2.")] = 1,
    as_json: JsonOption = False,
) -> None:
    """802.11ax data rate (Mb/s) of every RU size and MCS 0-11, at the DL and the UL GI."""
    from codesign_mb.wifi.phy import PhyConfig

    phy = PhyConfig(
        bandwidth_mhz=bandwidth,
        guard_interval_us=gi,
        ul_guard_interval_us=ul_gi,
        spatial_streams=streams,
    )
    emit(phy.rate_table(), as_json=as_json, title=f"802.11ax rates, {bandwidth} MHz, Mb/s")


def trace_command(
    out: Annotated[
        Path,
        typer.Argument(
            help="Instance file to write: JSON, or Parquet if it ends in .parquet (row groups "
            "of ticks, solved window by window).",
            dir_okay=False,
        ),
    ],
    robots: Annotated[int, typer.Option("--robots", help="Number of robots.")] = 6,
    steps: Annotated[int, typer.Option("--steps", help="Control steps (40 ms each).")] = 10,
    reliability: Annotated[
        float, typer.Option("--reliability", "-q", help="Requested reliability q in [0, 1].")
    ] = 1.0,
    latency: Annotated[
        int, typer.Option("--latency", help="Latency request tau in steps (>= 1).")
    ] = 1,
    channel: Annotated[
        str, typer.Option("--channel", help="Cell preset: paper or better.")
    ] = "paper",
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Record a static-QoS traffic trace as an instance for ``codesign solve``.

    Parquet is written as it is recorded (an hour of 48 robots in bounded memory); JSON is
    recorded whole, so capped. The progress bar counts the ticks recorded.
    """
    from codesign_mb.studies.offline_lp import write_trace

    with progress_bar("ticks", disable=as_json) as progress:
        t = write_trace(
            out,
            channel=channel,
            robots=robots,
            steps=steps,
            reliability=reliability,
            latency_steps=latency,
            seed=seed,
            progress=progress,
        )
    note(f"wrote {out} ({t.frames} frames, {t.horizon_ticks} ticks)")
    if as_json:
        summary = {"instance": str(out), "robots": t.n_stations, "frames": t.frames}
        emit({**summary, "horizon_ticks": t.horizon_ticks}, as_json=True)


_CURVE_COLUMNS = (
    "channel",
    "scheduler",
    "pipeline",
    "robots",
    "success_rate",
    "success_ci_low",
    "success_ci_high",
    "mean_reliability",
    "delivered_fraction",
    "capacity_robots",
    "stopped_at_robots",
)
"""The columns of the curves ``codesign wifi capacity`` prints as a table (JSON: all)."""


def capacity_command(
    ctx: typer.Context,
    robots: Annotated[
        str, typer.Option("--robots", help="Robot counts: 1..8 or 1,2,4,8.")
    ] = "1,2,4,6,8,10",
    channels: Annotated[
        str, typer.Option("--channels", help="Cell presets, comma separated: paper,better.")
    ] = "paper,better",
    schedulers: Annotated[
        str, typer.Option("--schedulers", help="Allocators, comma separated: greedy,convex.")
    ] = "greedy,convex",
    stack: Annotated[
        str,
        typer.Option(
            "--stack",
            help="Plant and pipelines: realistic (the realistic scenario, MPC + belt IMM, "
            "static QoS vs the QoS planner: Fig. 6), conveyor (0.6 m/s, MPC + predictor, "
            "static vs the covariance rule) or toy.",
        ),
    ] = "conveyor",
    scenario: Annotated[
        str | None,
        typer.Option(
            "--scenario",
            help=f"{SCENARIO_HELP} The conveyor every robot runs (stack conveyor or realistic). "
            "\\[default: the stack's plant]",
            show_default=False,
        ),
    ] = None,
    trials: Annotated[int, typer.Option("--trials", "-n", help="Episodes per point.")] = 4,
    stop_below: Annotated[
        float,
        typer.Option(
            "--stop-below",
            help="Early stop: a curve whose mean success at a robot count is below this runs "
            "none of its larger counts (0: all run; at most the 95 % target).",
        ),
    ] = 0.0,
    max_steps: Annotated[
        int | None,
        typer.Option(
            "--max-steps", help="Episode cap in steps (40 ms). \\[default: the plant's horizon]"
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option("--workers", "-j", "-w", help="Processes running points in parallel.")
    ] = 1,
    out: OutOption = Path("results/fig_wifi"),
    config: ConfigOption = None,
    seed: SeedOption = 0,
    fresh: FreshOption = False,
    as_json: JsonOption = False,
) -> None:
    """Task success vs number of robots on one channel (Fig. 6), per pipeline x scheduler.

    Writes OUT/fig_wifi.parquet, .csv and .json (one row per trial) and OUT/fig_wifi.png,
    and prints each curve with its capacity (most robots at 95 % success) and the co-design
    over static capacity per cell and scheduler. Robot counts run in ascending order; with
    --stop-below a curve stops once its success falls below it. Finished trials are kept in
    OUT/.records as they finish: rerun an interrupted command to resume it.

    The plant and the pipelines (controller, estimator, QoS policy) come from --stack, or
    from the config file's plant and pipelines tables (in a capacity table or at the top
    level), which also takes robots_by_channel (e.g. better = [8, 16, 32]).
    """
    from codesign_mb.studies.fig_wifi import CapacityConfig, capacity_ratios
    from codesign_mb.studies.fig_wifi_figures import run_capacity_study

    overrides: dict[str, Any] = explicit(
        ctx,
        {
            "robots": robots,
            "channels": channels,
            "schedulers": schedulers,
            "stack": stack,
            "scenario": scenario,
            "trials": trials,
            "stop_below": stop_below,
            "max_steps": max_steps,
            "workers": workers,
            "seed": seed,
        },
    )
    for key in ("channels", "schedulers"):
        if key in overrides:
            overrides[key] = list(comma_list(str(overrides[key]), key))
    if "robots" in overrides:
        overrides["robots"] = list(_parse_robots(str(overrides["robots"])))
    cfg = load_config(CapacityConfig, config, overrides, section="capacity")
    writable_folder("--out", out)
    n_points = len(cfg.points())
    if not as_json:
        stop = f", fewer with the early stop below {cfg.stop_below:.0%}" if cfg.stop_below else ""
        note(f"{n_points} trials: at most {cfg.robot_episodes()} robot-episodes{stop}")
    _, curves, files = run_capacity_study(
        cfg,
        out,
        progress=lambda pts: track(pts, total=n_points, description="capacity", disable=as_json),
        fresh=fresh,
    )
    if not as_json:
        note(f"results written to {files['parquet']}, {files['csv']} and {files['png']}")
        for r in capacity_ratios(curves).to_dict("records"):
            note(
                f"{r['channel']}, {r['scheduler']} ({_MEASURE_WORDS[r['measure']]}): capacity "
                f"co-design {r['codesign_capacity']} / static {r['static_capacity']} robots = "
                f"{r['ratio']:.3g} ({r['bound']})"
            )
    shown = curves if as_json else curves[[c for c in _CURVE_COLUMNS if c in curves]]
    emit(shown, as_json=as_json, title="task success vs robots (fig_wifi)")


def crosscheck_command(
    mcs: Annotated[str, typer.Option("--mcs", help="MCS values, comma separated.")] = "0,3,7",
    captures: Annotated[
        str, typer.Option("--captures", help="staggered, synchronised or both, comma separated.")
    ] = "staggered,synchronised",
    schedulers: Annotated[
        str, typer.Option("--schedulers", help="Our allocators, comma separated.")
    ] = "greedy,convex",
    ns3: Annotated[
        str,
        typer.Option("--ns3", help="ns-3 set-ups: su, su-rts, ofdma (comma separated) or none."),
    ] = "su,su-rts,ofdma",
    max_stations: Annotated[
        int, typer.Option("--max-stations", help="Upper end of the capacity search.")
    ] = 64,
    periods: Annotated[
        int, typer.Option("--periods", help="40 ms periods counted per run (after 2 warm-up).")
    ] = 8,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Also write the table and assumptions (JSON), after every cell. \\[default: none]",
            show_default=False,
        ),
    ] = None,
    ns3_from: Annotated[
        Path | None,
        typer.Option(
            "--ns3-from",
            help="Reuse the ns-3 results of an earlier --out file (same grid); reading them "
            "needs no ns-3. \\[default: none]",
            show_default=False,
        ),
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Capacity (robots with >= 95 % of frames in 40 ms) of our cell model and of ns-3's.

    Same traffic both sides: N stations, 13,500 B up and 32 B down per 40 ms, one fixed MCS,
    no channel errors. ns-3 (optional dependency: pip install 'codesign-mb\\[ns3]') runs its
    802.11ax model single-user (EDCA; su-rts: with RTS/CTS for the camera frames and an AP
    TXOP) and with its round-robin OFDMA scheduler.
    """
    import json

    from codesign_mb.core.config import check_writable
    from codesign_mb.core.results import atomic_write
    from codesign_mb.wifi.crosscheck import (
        CrosscheckConfig,
        MissingNs3Result,
        assumptions,
        crosscheck,
        ns3_missing,
        read_ns3_run,
    )
    from codesign_mb.wifi.ns3_driver import ns3_available

    access = (
        () if ns3.strip() in ("", "none") else comma_list(ns3, "ns3", example="su,su-rts,ofdma")
    )
    cfg = CrosscheckConfig(
        mcs=comma_list(mcs, "mcs", item=int, example="0,3,7"),
        captures=comma_list(captures, "captures", example="staggered,synchronised"),
        schedulers=comma_list(schedulers, "schedulers", example="greedy,convex"),
        ns3_access=access,
        max_stations=max_stations,
        periods=periods,
    )
    if out is not None:
        check_writable("out", out)
    # A recorded run is read as JSON: reusing it needs no ns-3, unless it lacks a cell.
    known = read_ns3_run(ns3_from) if ns3_from is not None else None
    simulate = bool(access) and ns3_available()
    if access and not simulate:
        missing = ns3_missing(cfg, known)
        if missing:
            shown = ", ".join(f"{a} at MCS {m}, {c}" for m, c, a in missing[:3])
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise ValueError(
                "ns-3 is not installed: pip install 'codesign-mb[ns3]', or --ns3 none"
                + (
                    f"; the recorded run {str(ns3_from)!r} has no ns-3 result for {shown}{more}"
                    if ns3_from is not None
                    else ", or --ns3-from an earlier --out file that has its results"
                )
            )

    def save(rows: list[dict[str, Any]]) -> None:
        if out is not None:
            report = {"rows": rows, "assumptions": assumptions(cfg), "tolerance": cfg.tolerance}
            with atomic_write(out, "w") as fh:
                json.dump(report, fh, indent=1)

    try:
        rows = crosscheck(
            cfg,
            progress=None if as_json else note,
            ns3_known=known,
            on_row=save,
            simulate_ns3=simulate,
        )
    except MissingNs3Result as exc:
        raise ValueError(f"{exc} (recorded run {str(ns3_from)!r})") from None
    table = [{k: v for k, v in r.items() if not k.endswith("_fractions")} for r in rows]
    report: dict[str, Any] = {
        "rows": rows,
        "assumptions": assumptions(cfg),
        "tolerance": cfg.tolerance,
    }
    if out is not None:
        note(f"wrote {out}")
    if as_json:
        emit(report, as_json=True)
    else:
        emit(table, as_json=False, title="capacity (robots at 95 % delivered): ours vs ns-3")
        for name, text in report["assumptions"].items():
            note(f"{name}: {text}")


def register(app: typer.Typer) -> None:
    """Add ``codesign wifi ...`` to ``app``."""
    wifi = typer.Typer(
        help="WiFi 6 OFDMA cell: PHY rates, allocation traces, capacity (Fig. 6).",
        no_args_is_help=True,
    )
    wifi.command("phy-table")(cli_errors(phy_table_command))
    wifi.command("trace")(cli_errors(trace_command))
    wifi.command("capacity")(cli_errors(capacity_command))
    wifi.command("crosscheck")(cli_errors(crosscheck_command))
    app.add_typer(wifi, name="wifi")
