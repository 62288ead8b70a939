"""The figures a traffic engineer expects of a demand run, as PNG files (the style of `cosim.evaluation.plots`).

Contract: `plot_demand(eval_dir, plots_dir, label, seeds)` draws, from a demand evaluation's folder (its
`summary.json`, and per seed `sumo/run_S/`: SUMO's detector files and the run's `record.npz`):
- `speed_heatmap.png`: the mean speed along the highway (chainage [m]) over time [s] of the first seed's run, the
  warm-up shaded and the acceleration lane marked;
- `merge_time_space.png`: the merge area's vehicles over the window of the first seed's run (chainage against
  time, coloured by speed), the acceleration lane's start and end labelled, and its collisions marked (a legend
  entry only where there is one);
- `flow_density.png`: per detector interval of every seed, the flow leaving the merge area [veh/h/ln] against the
  density in the merge influence area [veh/km/ln], with the HCM level-of-service bounds;
and returns their paths. `flow_bars(summaries, path, caption)` draws the flow metrics of several policies side by
side (`cosim compare`, `cosim sweep`); `penetration_curves(cells, path)` draws delay and throughput against the AV
penetration per demand level, a line and band per player (`scripts/demand_headline.py`). Every figure is titled
and captioned with the policy, the demand and the net.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from cosim.environment.flow_metrics import LOS_BOUNDS, PER_MILE
from cosim.evaluation.plots import CRASH_COLOR, add_caption, bars, save
from cosim.evaluation.store import read_summary
from cosim.sumo.flow_outputs import read_flow_outputs

FLOW_BARS = ("throughput, total [veh/h]", "throughput, ramp [veh/h]", "ramp queue, mean [veh]",
             "delay per vehicle [s]", "total time spent [veh h]", "distance per vehicle [m]",
             "density, merge influence area [veh/km/ln]", "merge success, per merging vehicle [%]")


def demand_caption(summary: Mapping[str, Any], label: str) -> str:
    d = summary.get("demand", {})
    net = Path(str(summary.get("net", "?"))).name
    avs = (f"{100 * d['av_penetration']:.0f}% AVs" if d.get("av_penetration") is not None
           else f"{d.get('av_count')} AVs")
    return (f"policy: {label}; demand: {d.get('mainline_vph', float('nan')):.0f} veh/h per highway lane x "
            f"{d.get('mainline_lanes', '?')}, ramp {d.get('ramp_vph', float('nan')):.0f} veh/h, {avs}; "
            f"warm-up {d.get('warmup', 0):g} s, window {d.get('window', 0):g} s; net: {net}")


def plot_demand(eval_dir: Path, plots_dir: Path, label: str, seeds: Sequence[int]) -> list[Path]:
    summary = read_summary(eval_dir / "summary.json")
    caption = demand_caption(summary, label)
    runs = [eval_dir / "sumo" / f"run_{s}" for s in seeds if (eval_dir / "sumo" / f"run_{s}" / "record.npz").is_file()]
    if not runs:
        return []
    with np.load(runs[0] / "record.npz") as data:
        rec = {k: data[k] for k in data.files}
    return [speed_heatmap(rec, plots_dir / "speed_heatmap.png", f"{label}, seed {runs[0].name[4:]}", caption),
            merge_time_space(rec, plots_dir / "merge_time_space.png", f"{label}, seed {runs[0].name[4:]}", caption),
            flow_density(runs, summary, plots_dir / "flow_density.png", label, caption)]


def _accel_lines(ax: Any, rec: Mapping[str, np.ndarray], horizontal: bool) -> None:
    for name, s in (("acceleration lane starts", float(rec["merge_start"])),
                    ("acceleration lane ends", float(rec["merge_end"]))):
        (ax.axhline if horizontal else ax.axvline)(s, color="k", ls="--" if "starts" in name else ":", lw=1,
                                                   label=f"{name} ({s:.0f} m)")


def speed_heatmap(rec: Mapping[str, np.ndarray], path: Path, title: str, caption: str) -> Path:
    heat = rec["heatmap"]  # (T, S) mean speed per (time, chainage) cell
    dt, ds = (float(b) for b in rec["heat_bins"])
    fig = Figure(figsize=(9.0, 4.6), layout="constrained")
    ax = fig.subplots()
    image = ax.imshow(heat.T, origin="lower", aspect="auto", cmap="RdYlGn", vmin=0.0,
                      extent=(0.0, heat.shape[0] * dt, 0.0, heat.shape[1] * ds), interpolation="nearest")
    fig.colorbar(image, ax=ax, label="mean speed [m/s]")
    ax.axvspan(0.0, float(rec["window"][0]), color="k", alpha=0.15, lw=0, label="warm-up (not measured)")
    _accel_lines(ax, rec, horizontal=True)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position along the highway [m]")
    fig.suptitle(f"Speed along the highway over time: {title}")
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.01), ncols=3, fontsize=8, frameon=False, borderaxespad=0)
    add_caption(fig, caption)
    return save(fig, path)


def merge_time_space(rec: Mapping[str, np.ndarray], path: Path, title: str, caption: str) -> Path:
    pts = rec["points"]  # (K, 4): time, chainage, speed, class
    fig = Figure(figsize=(9.0, 4.6), layout="constrained")
    ax = fig.subplots()
    dots = ax.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], s=1.0, cmap="RdYlGn", vmin=0.0, marker="s", lw=0)
    fig.colorbar(dots, ax=ax, label="speed [m/s]")
    _accel_lines(ax, rec, horizontal=True)
    w0, w1 = (float(x) for x in rec["window"])
    # Records from before the collisions' places were kept have none to draw.
    t, s = rec["collision_times"], rec.get("collision_chainage", np.full(len(rec["collision_times"]), np.nan))
    seen = (t >= w0) & (t <= w1) & np.isfinite(s)
    if seen.any():  # the legend names a collision only where one is drawn
        ax.scatter(t[seen], s[seen], s=40, marker="x", lw=1.5, color=CRASH_COLOR, zorder=3,
                   label=f"collision ({int(seen.sum())})")
    ax.set_xlim(w0, w1)
    ax.set_xlabel("time [s] (the measurement window)")
    ax.set_ylabel("position along the highway [m]")
    fig.suptitle(f"Time-space diagram of the merge area: {title}")
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.01), ncols=3, fontsize=8, frameon=False, borderaxespad=0)
    add_caption(fig, caption)
    return save(fig, path)


def interval_flow_density(run: Path, warmup: float, horizon: float, interval: float) -> tuple[np.ndarray, np.ndarray]:
    """Per detector interval of one run: (flow leaving the merge area [veh/h/ln], influence-area density
    [veh/km/ln]), from SUMO's instant loops and lane-area detectors (their lanes and lengths in record.npz)."""
    out = read_flow_outputs(run, warmup, horizon)
    with np.load(run / "record.npz") as data:
        areas = dict(zip(data["area_ids"].tolist(), data["area_lengths"].tolist(), strict=True))
        exit_lanes = int(data["exit_lanes"])
    n = min((len(out.intervals.get(d, [])) for d in areas), default=0)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    number = np.sum([[iv["meanVehicleNumber"] for iv in out.intervals[d][:n]] for d in areas], axis=0)
    density = number / (sum(areas.values()) / 1000.0)
    counts = np.histogram([t for t, _ in out.passages], bins=warmup + interval * np.arange(n + 1))[0]
    return counts * 3600.0 / interval / max(exit_lanes, 1), density


def flow_density(runs: Sequence[Path], summary: Mapping[str, Any], path: Path, label: str, caption: str) -> Path:
    d = summary.get("demand", {})
    warmup, horizon = float(d.get("warmup", 0.0)), float(d.get("horizon", 0.0))
    interval = float(d.get("interval", 30.0))
    fig = Figure(figsize=(7.5, 4.6), layout="constrained")
    ax = fig.subplots()
    for i, run in enumerate(runs):
        q, k = interval_flow_density(run, warmup, horizon, interval)
        ax.scatter(k, q, s=12, color=f"C{i % 10}", alpha=0.7, label=f"seed {run.name[4:]}")
    for letter, bound in LOS_BOUNDS:
        ax.axvline(bound / PER_MILE, color="0.6", lw=0.8, ls=":")
        ax.text(bound / PER_MILE, 0.02, f"{letter} ", transform=ax.get_xaxis_transform(), fontsize=8,
                va="bottom", ha="right", color="0.4")
    ax.set_xlabel("density in the merge influence area [veh/km/ln]")
    ax.set_ylabel("flow leaving the merge area [veh/h/ln]")
    ax.set_title(f"Flow against density, one point per {interval:g} s interval: {label}")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, title="run")
    add_caption(fig, caption + "; dotted: the HCM level-of-service bounds (A to D left of each, E beyond D's)")
    return save(fig, path)


def flow_bars(summaries: Mapping[str, Mapping[str, Mapping[str, float]]], path: Path, caption: str = "") -> Path:
    """The flow metrics of several runs side by side, with their intervals over seeds."""
    present = [m for m in FLOW_BARS if any(m in s for s in summaries.values())]
    return bars(summaries, path, metrics=present, caption=caption,
                title="Traffic flow over the measurement window: mean over seeds with its 95% interval")


def penetration_curves(cells: Mapping[str, Mapping[float, Mapping[str, Mapping[str, Mapping[str, float]]]]],
                       path: Path, metrics: Sequence[str] = ("delay per vehicle [s]", "throughput, total [veh/h]"),
                       caption: str = "") -> Path:
    """One column per demand level, one row per metric: each player's mean against the AV penetration [%], its
    95% interval over seeds as a band. `cells[level][penetration][player]` is a summary's metrics."""
    levels = list(cells)
    fig = Figure(figsize=(4.2 * len(levels) + 2.0, 3.0 * len(metrics)), layout="constrained")  # + the legend
    axes = fig.subplots(len(metrics), len(levels), squeeze=False)
    players = list(dict.fromkeys(p for level in cells.values() for cell in level.values() for p in cell))
    for col, level in enumerate(levels):
        shares = sorted(cells[level])
        for row, metric in enumerate(metrics):
            ax = axes[row][col]
            for i, player in enumerate(players):
                stats = [cells[level][s].get(player, {}).get(metric, {}) for s in shares]
                mean, low, high = (np.array([st.get(k, np.nan) for st in stats], dtype=float)
                                   for k in ("mean", "ci_low", "ci_high"))
                x = 100 * np.asarray(shares)
                ax.plot(x, mean, marker="o", color=f"C{i}", label=player)
                ax.fill_between(x, low, high, color=f"C{i}", alpha=0.2, linewidth=0)
            ax.set_xlabel("AV penetration [% of mainline vehicles]")
            ax.set_ylabel(metric)
            ax.set_title(f"{level}: {metric.split(' [')[0]}", fontsize=10)
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    fig.suptitle("Flow against AV penetration (band: 95% interval over seeds)")
    add_caption(fig, caption)
    return save(fig, path)
