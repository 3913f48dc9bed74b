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
# # Model-based versus learned co-design, stage by stage
#
# The paper learns every stage of the co-design (A: ideal control with SAC, B: a QoS-aware
# MLP/LSTM state estimator, C: a control-aware QoS policy with SAC, D: their synthesis, then
# the WiFi 6 network). Each stage has a model-based counterpart here (MPC, a
# delay-compensating predictor / Kalman filter with lost and delayed observations, QoS
# rules, the convex RU allocator). This notebook puts the two side by side, stage by stage,
# from the result tables the commands write:
#
# | stage | table | written by |
# |---|---|---|
# | A, B: control, estimation under latency | `fig_cn` | `codesign evaluate`, `codesign table` |
# | C: QoS adaptation over an episode | `fig_lat` | `codesign evaluate`, `codesign table` |
# | C, D: Table I | `tab_p` | `codesign table`, `codesign evaluate` |
# | D: robots sharing WiFi 6 | `fig_wifi` / `wifi_capacity` | `codesign wifi capacity` |
# | sweeps | any `codesign sweep` table | `codesign sweep` |
#
# Point `CODESIGN_RESULTS` at one or more results folders (separated by `:`); the default is
# `results/paper`. Where no results exist (or with `CODESIGN_SMOKE=1`, as in the test suite)
# the notebook runs a small stand-in on the **linear** scenario of `codesign sweep`
# (a gripper tracking an object on a belt, LQG over a Bernoulli link; milliseconds per
# trial), writes it in the same table layout, and the rest of the notebook reads it exactly
# as it would read the robot's results. The column layout of every table is documented in
# `codesign_mb.studies.report`.

# %%
import json
import os
import tempfile
from pathlib import Path

import codesign_mb.models
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from IPython.display import Image, Markdown, display

from codesign_mb.core.results import ResultsDir, write_results
from codesign_mb.studies.report import (
    ReportConfig,
    build_report,
    collect,
    labels_of,
    success_summary,
)
from codesign_mb.studies.sweep import SweepConfig, run_sweep

SMOKE = os.environ.get("CODESIGN_SMOKE") == "1"
SEEDS = 3 if SMOKE else 20  # replicates per point of the stand-in experiment
pd.set_option("display.width", 160)

candidates = [
    Path(p) for p in os.environ.get("CODESIGN_RESULTS", "results/paper").split(os.pathsep) if p
]
folders = [ResultsDir(p) for p in candidates if p.is_dir() and ResultsDir(p).names]
print("results folders found:", [str(f.path) for f in folders] or "none")

# %% [markdown]
# ## Checkpoints of the learned pipeline
#
# `codesign train` writes each stage's final model with a `training.json` (command, seed,
# steps, wall time, final evaluation) under `models/checkpoints/<stage>/`.

# %%
checkpoints = Path(codesign_mb.models.__file__).resolve().parent / "checkpoints"
rows = []
for meta_path in sorted(checkpoints.glob("*/training.json")):
    meta = json.loads(meta_path.read_text())
    final = meta.get("final_evaluation") or meta.get("evaluation") or {}
    rows.append(
        {
            "stage": meta_path.parent.name,
            "files": ", ".join(sorted(p.name for p in meta_path.parent.iterdir())),
            "env_steps": meta.get("env_steps", meta.get("steps")),
            "wall_time_s": meta.get("wall_time_s"),
            "seed": meta.get("seed"),
            **{f"final {k}": v for k, v in final.items() if np.ndim(v) == 0},
        }
    )
if rows:
    display(pd.DataFrame(rows))
else:
    print(f"no trained checkpoints under {checkpoints}: run `codesign train` to produce them")

# %% [markdown]
# ## The stand-in experiment (only when no results were found, or under `CODESIGN_SMOKE=1`)
#
# Same tables, same columns, on the linear scenario: the model-based estimators are the
# `predictor` (the held observation extrapolated over its age) and the `kalman` filter, the
# baseline `none` uses the stale observation as is, and `ideal` sees the true state.
# There is no learned pipeline in the stand-in, so only the model-based side is filled.


# %%
def linear_points(**params: float) -> pd.DataFrame:
    """One sweep of the linear scenario with ``params``; one row per trial."""
    config = SweepConfig(
        name="points",
        n_seeds=SEEDS,
        belt_speeds_mps=(0.2, 0.6),
        robot_counts=(1,),
        pipelines=("none", "predictor", "kalman"),
        params={"horizon_steps": 60 if SMOKE else 100, **params},
    )
    scratch = Path(tempfile.mkdtemp(prefix="codesign-nb03-"))
    return run_sweep(config, scratch, backend="serial").table


if SMOKE or not folders:
    standin = Path("results/notebook03")
    # Fig. 4 counterpart: success versus a fixed latency, every packet delivered (q = 1).
    cn = pd.concat(
        [
            linear_points(latency_steps=tau, reliability=1.0).assign(latency_steps=tau)
            for tau in (range(0, 7, 2) if SMOKE else range(9))
        ]
    )
    cn = cn.rename(columns={"pipeline": "estimator"}).assign(
        pipeline="model_based", success=lambda d: d["success_rate"] >= 0.5
    )
    write_results(standin, table=cn, config={"scenario": "linear"}, name="fig_cn")
    # Table I counterpart: static QoS at two reliabilities, with and without estimation.
    tab = []
    for q in (1.0, 0.3):
        points = linear_points(reliability=q, latency_steps=1)
        points = points[points["belt_speed_mps"] == 0.6]
        for est, name in (("kalman", "Kalman filter"), ("none", "no state est.")):
            part = points[points["pipeline"] == est]
            tab.append(
                part.assign(
                    pipeline="model_based",
                    policy=f"{name}, static q = {q:g}",
                    success=part["success_rate"] >= 0.5,
                    mean_requested_reliability=part["mean_reliability"],
                )
            )
    write_results(standin, table=pd.concat(tab), config={"scenario": "linear"}, name="tab_p")
    # Stage D counterpart: robots sharing a channel (capacity 2 robots at q = 0.8).
    run_sweep(
        SweepConfig(
            name="robots",
            n_seeds=SEEDS,
            belt_speeds_mps=(0.6,),
            robot_counts=(1, 2, 4, 8),
            pipelines=("none", "predictor", "kalman"),
            params={"horizon_steps": 60 if SMOKE else 100},
        ),
        standin,
        backend="serial",
    )
    folders = [ResultsDir(standin)]
    print("stand-in results written to", standin.resolve(), ":", folders[0].names)


# %%
def table(name: str) -> pd.DataFrame | None:
    """The table ``name`` gathered over every results folder (``None`` if absent)."""
    parts = [frame for frame in (collect(f, name) for f in folders) if frame is not None]
    return pd.concat(parts, ignore_index=True) if parts else None


# %% [markdown]
# ## Stages A and B: the ideal controller and the state estimators under latency
#
# At zero latency every estimator sees the current state: the success rate there is the
# ideal controller's (stage A, SAC versus MPC). As the latency grows, the stale observation
# drives the ideal controller wrong; a QoS-aware estimator (stage B: MLP/LSTM versus the
# predictor and the Kalman filter) hides the latency from it. A useful single number per
# estimator is the largest latency at which it still succeeds in at least 90 % of the trials.

# %%
cn = table("fig_cn")
if cn is None:
    print("no fig_cn table: run `codesign evaluate fig-cn` (model-based) / `codesign table`")
else:
    if "sweep" in cn.columns:
        cn = cn[cn["sweep"].astype(str) != "reliability"]
    if "belt_speed_mps" not in cn.columns:
        cn = cn.assign(belt_speed_mps=np.nan)
    labels = labels_of(cn)
    cn_summary = success_summary(cn, [*labels, "belt_speed_mps", "latency_steps"])
    stage_a = cn_summary[cn_summary["latency_steps"] == cn_summary["latency_steps"].min()]
    display(Markdown("**Stage A**: success at the smallest latency (ideal controller)"))
    display(stage_a[[*labels, "belt_speed_mps", "latency_steps", "trials", "success_rate"]])
    tolerated = (
        cn_summary[cn_summary["success_rate"] >= 0.9]
        .groupby([*labels, "belt_speed_mps"], sort=False)["latency_steps"]
        .max()
        .rename("max latency with >= 90 % success (steps)")
        .reset_index()
    )
    display(Markdown("**Stage B**: latency each estimator tolerates"))
    display(tolerated)
    speeds = sorted(cn_summary["belt_speed_mps"].unique())
    fig, axes = plt.subplots(1, len(speeds), figsize=(5 * len(speeds), 3.4), squeeze=False)
    for ax, speed in zip(axes[0], speeds, strict=True):
        at = cn_summary[cn_summary["belt_speed_mps"] == speed]
        for key, line in at.groupby(labels, sort=False):
            key = tuple(np.atleast_1d(key))
            style = "--" if "model_based" in key else "-"
            label = ", ".join(map(str, key))
            ax.plot(line["latency_steps"], line["success_rate"], style, marker="o", label=label)
        ax.set_title(f"belt speed {speed:g} m/s")
        ax.set_xlabel("latency (steps of 40 ms)")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.05)
        ax.legend(fontsize=7)
    plt.show()
    plt.close(fig)

# %% [markdown]
# ## Stage C: what each pipeline asks of the network
#
# Table I trades success against the average requested reliability (PDR). The learned QoS
# policy of the paper reaches 98 % success at 13 % PDR; the model-based side answers with
# estimation-error-triggered rules on top of the predictor.

# %%
tab = table("tab_p")
if tab is None:
    print("no tab_p table: run `codesign table` (learned) / `codesign evaluate` (model-based)")
else:
    tab_summary = success_summary(tab, labels_of(tab))
    display(tab_summary)
lat = table("fig_lat")
if lat is None:
    print("no fig_lat table (one episode's QoS trace): `codesign evaluate` with a QoS policy")
else:
    print(
        lat.groupby(labels_of(lat), sort=False)["qos_reliability"]
        .mean()
        .rename("average PDR over the trace")
    )

# %% [markdown]
# ## Stage D: sharing the network
#
# Robots on one channel split its capacity; fewer requested packets (stage C) and a better
# use of stale ones (stage B) let more robots succeed. With WiFi 6 results this is Fig. 6;
# in the stand-in, a channel that serves two robots at the requested reliability.

# %%
wifi = table("fig_wifi")
if wifi is not None:
    wifi_labels = labels_of(wifi)
    display(success_summary(wifi, [*wifi_labels, "n_robots"]))
sweeps = [
    (f, n) for f in folders for n in f.names if f.meta(n).get("extra", {}).get("kind") == "sweep"
]
for folder, name in sweeps:
    frame = folder.table(name)
    pivot = frame.pivot_table(
        index=["pipeline", "belt_speed_mps"], columns="n_robots", values="success_rate"
    )
    display(Markdown(f"**sweep `{name}`** in `{folder.path}`: success rate by robots"))
    display(pivot.round(2))
if wifi is None and not sweeps:
    print("no fig_wifi / sweep table: run `codesign wifi capacity` or `codesign sweep`")

# %% [markdown]
# ## The report
#
# `codesign report RESULTS_DIR` renders all of the above as PNG figures and a Markdown
# summary; here for the first results folder.

# %%
report = build_report(
    folders[0].path, Path(tempfile.mkdtemp(prefix="codesign-report-")), ReportConfig(dpi=80)
)
print("report:", report.markdown)
for name, reason in report.skipped.items():
    print(f"skipped {name}: {reason}")
for name, figure in report.figures.items():
    display(Markdown(f"**{name}**"))
    display(Image(filename=str(figure)))
