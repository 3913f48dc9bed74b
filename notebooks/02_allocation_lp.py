# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # The RU allocation LP: the value of airtime and how many robots fit a 40 MHz channel
#
# Every robot sends a camera frame (13,500 bytes) up to the access point each control step
# (40 ms) and gets a state frame (32 bytes) back; both must be through before the robot reads
# its observation $\tau$ steps later ([deadline]). The AP lays out OFDMA resource units
# (RUs) every 1 ms tick. Three schedulers face the same traffic (`codesign_mb.wifi`):
#
# * **greedy** (the paper, sec. 5): stations in deadline order, each the smallest RU that
#   finishes its frame in time if served every remaining tick ([greedy]);
# * **convex** (online): admission control ([admit]: Moore-Hodgson on the channel seen
#   as one machine, so the band goes to frames that can still make it), then a QP over
#   fractional RU assignments ([qp]) rounded to a valid layout ([round]);
# * **offline optimum**: the whole-horizon LP [lp] over a recorded trace. With $U_{fk}$,
#   $V_{fk}$ the parts of frame $f$'s camera and state frames sent by tick $k$,
#   $$\max \sum_f V_{f,\mathrm{last}} \quad \text{s.t.} \quad
#   \sum_f \frac{B^{UL}_f (U_{fk} - U_{f,k-1})}{b_{ik}} \le S\,(N_{UL} - (N_{UL} - N'_{UL}) y_k),
#   \quad V_{fk} - V_{f,k-1} \le y_k,$$
#   monotone $U, V \in [0, 1]$, the state frame after its camera frame, and the DL capacity.
#   $S$ is the data subcarriers of the whole band, $b_{ik}$ the bits per subcarrier and symbol
#   of station $i$'s MCS, $N_{UL}$ ($N'_{UL}$) the data symbols of an UL PPDU without (with)
#   a DL exchange in the tick. Every schedule the simulator can run is feasible for it, so
#   its optimum bounds every online scheduler.
#
# The LP's **dual prices** on the per-tick capacity rows say what one more tick of the whole
# band would be worth, in frames delivered in time: the value of airtime.
#
# Set `CODESIGN_SMOKE=1` for small settings (the test suite does).

# %%
import json
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import codesign_mb
from codesign_mb.studies.fig_wifi import CHANNEL_PRESETS, describe_channel
from codesign_mb.studies.offline_hour import per_minute
from codesign_mb.studies.offline_lp import COMPARED, COMPARED_KEYS, solve_instance, write_trace
from codesign_mb.wifi import generate_trace, offline_optimum, replay
from codesign_mb.wifi.offline import airtime_prices
from codesign_mb.wifi.phy import data_rate_mbps

SMOKE = os.environ.get("CODESIGN_SMOKE") == "1"
STEPS = 3 if SMOKE else 10  # control steps (40 ms) per trace
SEEDS = [0] if SMOKE else [0, 1, 2]  # traces per point
PAPER, BETTER = CHANNEL_PRESETS["paper"], CHANNEL_PRESETS["better"]
for name in CHANNEL_PRESETS:
    print(f"{name}: {describe_channel(name)}")

# %% [markdown]
# ## 1. The channel's arithmetic
#
# A tick of 1 ms holds one channel access, the DL exchange when state frames wait (an HE MU
# PPDU, its block acks and two SIFS) and a trigger-based UL exchange; the UL PPDU gets every
# data symbol left. How much of the whole band's time does one camera frame take, and how
# many robots at reliability $q$ (a frame is queued with probability $q/q_0$, `eq_drop`)
# fill the 40-tick period? Roughly $N_{\max}(q) \approx 40 / ((q/q_0)(w_{UL} + w_{DL}))$
# with $w_{UL}$ the frame's ticks of whole band and $w_{DL}$ the share of a tick its DL
# exchange takes from the uplink.


# %%
def frame_ticks(config, mcs):
    """Whole-band UL ticks of one camera frame at ``mcs``, and the UL share a DL exchange costs."""
    mac, phy = config.mac, config.phy
    n_ul = mac.max_ul_data_symbols(phy, with_dl=False)
    n_ul_dl = mac.max_ul_data_symbols(phy, with_dl=True)
    bits = mac.psdu_bits(config.traffic.ul_frame_bytes)
    per_tick = phy.plan.full_band_data_subcarriers * phy.bits_per_subcarrier_symbol(mcs) * n_ul
    return float(bits / per_tick), (n_ul - n_ul_dl) / n_ul


rows = []
for name, config in (("paper", PAPER), ("better", BETTER)):
    for mcs in (0, 1, 3, 5, 7, 9, 11):
        w_ul, w_dl = frame_ticks(config, mcs)
        q0 = config.channel.q0
        rows.append(
            {
                "channel": name,
                "mcs": mcs,
                "484-RU rate Mb/s": round(data_rate_mbps(484, mcs), 1),
                "UL ticks/frame": round(w_ul, 2),
                "DL exchange share": round(w_dl, 2),
                "N_max(q=1)": int(40 / ((1 / q0) * (w_ul + w_dl))),
                "N_max(q=0.2)": int(40 / ((0.2 / q0) * (w_ul + w_dl))),
            }
        )
arithmetic = pd.DataFrame(rows)
arithmetic

# %% [markdown]
# In the paper cell (MCS 1 for everyone, the long 3.2 us guard interval) a camera frame
# needs about 5.5 ticks of the whole band and its DL exchange takes 0.4 of a tick from the
# uplink, so static QoS ($q = 1$) runs out at about 6 robots even with a perfect scheduler;
# a co-design policy that asks for $q \approx 0.2$ on average could carry about five times
# as many.
#
# ## 2. Greedy, convex and the offline optimum
#
# The same traces (static QoS, $\tau = 1$, staggered capture) for a growing number of robots
# in the paper cell; each scheduler's frames delivered in time, as a share of the frames the
# channel does not lose anyway.

# %%
robots_grid = [4, 8, 12] if SMOKE else [2, 4, 6, 8, 10, 12, 14, 16]
rows = []
for n in robots_grid:
    for seed in SEEDS:
        trace = generate_trace(PAPER, n, steps=STEPS, seed=seed)
        ok = int(((trace.frames.ul_ok == 1) & (trace.frames.dl_ok == 1)).sum())
        bound = offline_optimum(trace).optimum
        row = {"robots": n, "seed": seed, "deliverable": ok, "optimum": bound}
        for scheduler in ("greedy", "convex"):
            row[scheduler] = replay(trace, scheduler).delivered
        rows.append(row)
compare = pd.DataFrame(rows).groupby("robots")[["deliverable", "optimum", "greedy", "convex"]].sum()
for col in ("optimum", "greedy", "convex"):
    compare[f"{col} share"] = compare[col] / compare["deliverable"]
compare["convex gap to optimum"] = 1 - compare["convex"] / compare["optimum"]
compare["greedy gap to optimum"] = 1 - compare["greedy"] / compare["optimum"]
compare.round(3)

# %%
fig, ax = plt.subplots(figsize=(5.5, 3.6))
for col, style in (("optimum share", "k-"), ("convex share", "C1s--"), ("greedy share", "C0o-")):
    ax.plot(compare.index, compare[col], style, label=col.replace(" share", ""))
ax.set_xlabel("robots (q = 1, tau = 1)")
ax.set_ylabel("frames delivered in time / deliverable")
ax.set_ylim(0, 1.05)
ax.grid(alpha=0.3)
ax.legend()
ax.set_title("paper cell: " + describe_channel("paper"), fontsize=8)
plt.show()

# %% [markdown]
# Past the channel's capacity, greedy collapses: in deadline order every station is given
# the least bandwidth that would finish its frame *if it got it every tick*, the frames all
# fall behind together and most miss their deadlines (EDF's domino effect under overload).
# The convex allocator admits only what earliest-deadline-first can finish and serves the
# admitted frames in deadline order, so it delivers about what the channel can carry; the
# gap left to the LP is what an online scheduler cannot have: the LP batches state frames
# into few DL exchanges, knows the future fading and delivers fractions of frames.
#
# ## 3. Dual prices: the value of airtime
#
# A congested trace in the better cell: link adaptation gives each station its own MCS, so
# frames cost different amounts of airtime.

# %%
n_congested = 60 if SMOKE else 80
trace = generate_trace(BETTER, n_congested, steps=STEPS, seed=1)
prices = airtime_prices(trace)
print(f"LP optimum {prices.optimum:.1f} of {len(prices.frames)} deliverable frames")
ticks = prices.ticks
print(
    f"UL price per whole-band tick: mean {ticks.ul_price.mean():.3f}, "
    f"max {ticks.ul_price.max():.3f} frames; DL price max {ticks.dl_price.max():.3f}"
)

# %%
frames = prices.frames
fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
axes[0].step(ticks["tick"], ticks["ul_price"], where="post")
axes[0].set_xlabel("tick (1 ms)")
axes[0].set_ylabel("UL price [frames per whole-band tick]")
axes[0].set_title("value of one more tick of uplink airtime")
axes[0].grid(alpha=0.3)
axes[1].scatter(frames["ul_bill"], frames["delivered"], s=10, alpha=0.6)
axes[1].axvline(1.0, color="k", lw=0.8, ls=":")
axes[1].set_xlabel("frame's cheapest UL airtime at the prices [frames]")
axes[1].set_ylabel("delivered in the LP optimum")
axes[1].set_title("a frame is sent iff its airtime costs < 1 frame")
axes[1].grid(alpha=0.3)
plt.tight_layout()
plt.show()

# %% [markdown]
# Complementary slackness, read economically: a tick's price is positive only where the
# channel is full; then it equals the value of the marginal frame per tick of airtime it
# needs. Each frame is worth one delivery, so the optimum sends a frame exactly when its
# airtime at these prices costs less than one frame: the cheap frames (good MCS, short
# frames) first. Per station this is the value of its airtime: the price it pays per frame
# grows as its MCS falls.

# %%
per_station = frames.groupby("station").agg(
    ul_work=("ul_work", "mean"), ul_bill=("ul_bill", "mean"), delivered=("delivered", "mean")
)
per_station["mcs bits/sc/sym"] = trace.ul_bpss[per_station.index].mean(axis=1).round(2)
per_station.sort_values("ul_work").round(3)

# %%
print(
    "correlation of a station's airtime per frame with its LP delivery:",
    round(float(np.corrcoef(per_station["ul_work"], per_station["delivered"])[0, 1]), 3)
    if per_station["delivered"].std() > 0
    else "no congestion",
)

# %% [markdown]
# ## 4. The capacity region: how many robots at which $(q, \tau)$
#
# For a grid of reliabilities $q$ and latencies $\tau$, the largest number of robots whose
# frames the convex allocator still delivers in time (95 % of those the channel does not
# lose), next to the arithmetic estimate of section 1 and the LP's verdict (an upper bound:
# above the LP's boundary no scheduler can make it).

# %%
TARGET = 0.95
q_grid = [0.5, 1.0] if SMOKE else [0.1, 0.2, 0.3, 0.5, 0.7, 1.0]
tau_grid = [1] if SMOKE else [1, 2]
w_ul, w_dl = frame_ticks(PAPER, PAPER.channel.fixed_mcs)
q0 = PAPER.channel.q0


def shares(n, q, tau):
    """Delivered share of the convex allocator and of the LP, over SEEDS traces."""
    got = opt = total = 0.0
    for seed in SEEDS:
        tr = generate_trace(PAPER, n, steps=STEPS, reliability=q, latency_steps=tau, seed=seed)
        total += int(((tr.frames.ul_ok == 1) & (tr.frames.dl_ok == 1)).sum())
        got += replay(tr, "convex").delivered
        opt += offline_optimum(tr).optimum
    return (got / total, opt / total) if total else (1.0, 1.0)


region = []
for tau in tau_grid:
    for q in q_grid:
        estimate = 40 / ((q / q0) * (w_ul + w_dl))
        candidates = sorted({max(1, int(estimate * f)) for f in (0.7, 0.85, 1.0, 1.15, 1.3)})
        if SMOKE:
            candidates = candidates[1:4]
        best_convex = best_lp = 0
        for n in candidates:
            convex_share, lp_share = shares(n, q, tau)
            if convex_share >= TARGET:
                best_convex = max(best_convex, n)
            if lp_share >= TARGET:
                best_lp = max(best_lp, n)
        region.append(
            {
                "tau": tau,
                "q": q,
                "arithmetic N_max": int(estimate),
                "convex: most robots tested at 95%": best_convex,
                "LP: most robots tested at 95%": best_lp,
                "robots tested": candidates,
            }
        )
region = pd.DataFrame(region)
region

# %%
fig, ax = plt.subplots(figsize=(5.5, 3.6))
q_fine = np.linspace(min(q_grid), 1.0, 50)
ax.plot(q_fine, 40 / ((q_fine / q0) * (w_ul + w_dl)), "k:", label="arithmetic estimate")
for tau, part in region.groupby("tau"):
    convex_n = part["convex: most robots tested at 95%"]
    lp_n = part["LP: most robots tested at 95%"]
    ax.plot(part["q"], convex_n, "o-", label=f"convex, tau={tau}")
    ax.plot(part["q"], lp_n, "s--", alpha=0.6, label=f"LP, tau={tau}")
ax.set_xlabel("requested reliability q")
ax.set_ylabel("robots on one 40 MHz channel")
ax.set_yscale("log")
ax.grid(alpha=0.3, which="both")
ax.legend(fontsize=8)
ax.set_title("capacity region, paper cell (below the curves: >= 95 % in time)", fontsize=9)
plt.show()

# %% [markdown]
# The region is essentially a load constraint, $N\,q/q_0\,(w_{UL} + w_{DL}) \lesssim 40$
# ticks: halving the reliability a robot asks for doubles the robots the cell carries, which
# is the lever the co-design pulls (Fig. 6, `codesign wifi capacity`). A longer latency
# $\tau$ hardly moves it with staggered capture: it only helps when frames arrive in bursts
# (synchronised capture), where the deadline spreads a burst over more ticks.

# %% [markdown]
# ## 5. An hour of a 48-robot cell
#
# What a planner of a real cell asks: over an hour of traffic, how much could any scheduler
# deliver, how far are the online allocators from it, and when is airtime scarce?
# `solvers/offline_hour.sh` records an hour of co-design traffic on the paper cell (48 robots
# asking for 10 % of their packets: 90,000 steps, 3.6 M ticks) as a Parquet trace written as
# it is recorded, solves [lp] by its independent windows on two workers (the optimum is the
# monolithic LP's, exactly) and replays greedy, convex and tick-optimal on the same trace
# (`codesign solve --compare`). The results, per minute, are in
# `docs/results/offline_hour.json` (with the commands, wall times and peak memory), read here.
# A small instance recorded and solved in place (4 s of the same cell at 12 %, per second) goes
# through the same code; it is what this section shows when the stored run is missing, and
# what the test suite runs.

# %%
RESULTS = Path(codesign_mb.__file__).resolve().parents[1] / "docs/results/offline_hour.json"
HOUR = Path(os.environ.get("CODESIGN_HOUR_RESULTS", RESULTS))
KEYS = list(COMPARED_KEYS.values())
live = None
if SMOKE or not HOUR.is_file():
    with tempfile.TemporaryDirectory() as folder:
        small = Path(folder) / "small.parquet"
        write_trace(small, robots=48, steps=100, reliability=0.12, seed=0)
        record = solve_instance(small, solver="highs", compare=True)
    live = per_minute(record, bin_ticks=1000)
if HOUR.is_file():
    hour = json.loads(HOUR.read_text())
    minutes, unit = pd.DataFrame(hour["per_minute"]), "minute"
    totals = pd.Series(hour["totals"])
    print("\n".join(hour["commands"]))
    runs = pd.DataFrame(hour["runs"]).T[["wall_s", "max_rss_mb", "tree_pss_peak_mb"]]
    print(runs.round(0))
else:
    minutes, unit = live, "second"
    totals = pd.Series({k: v for k, v in record.items() if not isinstance(v, dict | list)})
frames_total = minutes["frames"].sum()
summary = pd.DataFrame(
    {
        "frames in time": [minutes["optimum"].sum()] + [minutes[k].sum() for k in KEYS],
    },
    index=["LP bound", *COMPARED],
)
summary["share of deliverable"] = summary["frames in time"] / frames_total
summary["gap to the bound"] = 1 - summary["frames in time"] / minutes["optimum"].sum()
summary.round(4)

# %%
fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
ax = axes[0]
ax.plot(minutes["minute"], minutes["optimum"] / minutes["frames"], "k-", label="LP bound")
for key, style in zip(KEYS, ("C0-", "C1-", "C2--"), strict=True):
    ax.plot(minutes["minute"], minutes[key] / minutes["frames"], style, label=key)
ax.set_xlabel(unit)
ax.set_ylabel("frames delivered in time / deliverable")
ax.set_title(f"per {unit}: the bound and the online allocators", fontsize=9)
ax.grid(alpha=0.3)
ax.legend(fontsize=8)
ax = axes[1]
ax.plot(minutes["minute"], minutes["ul_price_mean"], "C3-", label="mean UL price per tick")
ax.set_xlabel(unit)
ax.set_ylabel("frames per whole-band tick of UL")
ax.grid(alpha=0.3)
twin = ax.twinx()
twin.plot(minutes["minute"], minutes["priced_share"], "C7:", label="share of ticks priced")
twin.set_ylabel("share of ticks with a price")
ax.set_title("the price of airtime (duals of the ticks' capacity rows)", fontsize=9)
lines = ax.get_lines() + twin.get_lines()
ax.legend(lines, [line.get_label() for line in lines], fontsize=8)
plt.tight_layout()
plt.show()

# %%
per_unit = minutes.assign(
    gap_convex=1 - minutes["convex"] / minutes["optimum"],
    gap_greedy=1 - minutes["greedy"] / minutes["optimum"],
)
print(
    f"correlation over the {unit}s of the price of airtime with the convex allocator's gap: "
    f"{per_unit['ul_price_mean'].corr(per_unit['gap_convex']):.2f}, with greedy's: "
    f"{per_unit['ul_price_mean'].corr(per_unit['gap_greedy']):.2f}"
)
per_unit.sort_values("ul_price_mean", ascending=False).head(5).round(3)
