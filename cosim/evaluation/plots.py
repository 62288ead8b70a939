"""Figures of evaluations and training runs, as PNG files (matplotlib's Agg canvas, no pyplot state).

Contract: every function takes plain data (summaries, per-episode columns, a trajectory dict as written by
`cosim.environment.tracker.EpisodeTracker.trajectory`, a training log CSV) and a path, writes one PNG there and
returns the path (or None when there is nothing to draw, e.g. a training log without known columns).
- `bars`: crash %, merge %, mean distance with 95% intervals, runs side by side (the paper's bar plot).
- `distance_histogram`: the merging vehicle's distance travelled, overlaid per run.
- `training_curves`: return, crash rate, merge rate, distance over training episodes (rolling means),
  for the columns the log has (the trainer's `episodes.csv`: return_mean, crashed, merged, mean_distance).
- `time_space`: time-space diagram of the merge area, and the guide AV's speed profile and actions.
- `top_views`: a few top-view snapshots around the merge.
- `plot_evaluation`: one evaluation folder's figures (`cosim evaluate` and `cosim compare` draw through it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from cosim.config import load_config
from cosim.environment.control import Action
from cosim.environment.render import COLOURS as TOP_VIEW_COLOURS
from cosim.environment.render import top_view
from cosim.environment.velocity_map import RoadRaster, rasterize_road
from cosim.evaluation.store import load_trajectory, trajectory_files
from cosim.files import column, read_csv
from cosim.sumo.roadnet import load_roadnet
from cosim.sumo.snapshot import KIND_HV, KIND_MERGER

GUIDE_RGB = (255, 150, 20)
CRASHED_RGB = (230, 30, 30)
# One palette for every figure: the renderer's class colours.
COLORS = {kind: tuple(c / 255 for c in rgb) for kind, rgb in TOP_VIEW_COLOURS.items()}
GUIDE_COLOR = tuple(c / 255 for c in GUIDE_RGB)
BAR_METRICS = ("crash [%]", "merge success [%]", "mean distance [m]")
# Training-log columns, first match wins: what to plot -> candidate column names.
TRAINING_COLUMNS: dict[str, tuple[str, ...]] = {
    "return": ("return_mean", "return", "episode_return", "mean_return"),
    "crash rate": ("crashed", "crash", "crash_rate"),
    "merge rate": ("merged", "merge", "merge_rate"),
    "mean distance [m]": ("mean_distance", "distance"),
}


def save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return path


def bars(summaries: Mapping[str, Mapping[str, Mapping[str, float]]], path: Path,
         metrics: Sequence[str] = BAR_METRICS) -> Path:
    """One panel per metric, one bar per run, error bars = the confidence interval."""
    fig = Figure(figsize=(3.2 * len(metrics), 3.4), layout="constrained")
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    labels = list(summaries)
    colors = [f"C{i}" for i in range(len(labels))]
    for ax, metric in zip(axes, metrics, strict=True):
        stats = [summaries[run].get(metric, {}) for run in labels]
        means = np.array([s.get("mean", math.nan) for s in stats], dtype=float)
        low = np.array([s.get("ci_low", math.nan) for s in stats], dtype=float)
        high = np.array([s.get("ci_high", math.nan) for s in stats], dtype=float)
        err = np.nan_to_num(np.vstack([means - low, high - means]), nan=0.0)
        ax.bar(range(len(labels)), np.nan_to_num(means), yerr=err, color=colors, capsize=4)
        ax.set_xticks(range(len(labels)), labels, rotation=20, ha="right")
        ax.set_title(metric)
        if "%" in metric:
            ax.set_ylim(0, 105)
    return save(fig, path)


def distance_histogram(samples: Mapping[str, Sequence[float]], path: Path, bins: int = 30,
                       xlabel: str = "distance travelled by the merging vehicle [m]") -> Path:
    fig = Figure(figsize=(6, 3.6), layout="constrained")
    ax = fig.subplots()
    finite = {k: np.asarray(v, dtype=float)[np.isfinite(np.asarray(v, dtype=float))] for k, v in samples.items()}
    every = np.concatenate([v for v in finite.values()] or [np.zeros(0)])
    edges = np.histogram_bin_edges(every if every.size else np.zeros(1), bins=bins)
    for i, (label, values) in enumerate(finite.items()):
        ax.hist(values, bins=edges, alpha=0.5, color=f"C{i}", label=f"{label} (n={values.size})", density=False)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("episodes")
    ax.legend()
    return save(fig, path)


def read_training_log(path: Path) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV log (unparsable cells become NaN)."""
    rows = read_csv(path)
    return {key: column(rows, key) for key in (rows[0] if rows else [])}


def _rolling(y: np.ndarray, window: int) -> np.ndarray:
    if y.size == 0:
        return y
    window = max(1, min(window, y.size))
    ok = np.isfinite(y)
    sums = np.convolve(np.where(ok, y, 0.0), np.ones(window), mode="valid")
    counts = np.convolve(ok.astype(float), np.ones(window), mode="valid")
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts


def training_curves(logs: Mapping[str, Path], path: Path, window: int = 100) -> Path | None:
    """Rolling means of the known columns of each run's training log; None if no log has any."""
    data = {label: read_training_log(p) for label, p in logs.items() if p.is_file()}
    panels = [(title, names) for title, names in TRAINING_COLUMNS.items()
              if any(n in cols for cols in data.values() for n in names)]
    if not panels:
        return None
    ncols = min(2, len(panels))
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(5 * ncols, 3.2 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    for ax, (title, names) in zip(axes, panels, strict=False):
        for i, (label, cols) in enumerate(data.items()):
            name = next((n for n in names if n in cols), None)
            if name is None:
                continue
            y = cols[name]
            x = cols.get("episode", np.arange(y.size, dtype=float))
            ax.plot(x, y, color=f"C{i}", alpha=0.2, lw=0.6)
            # A short log gets a short window, so its curve is more than a point.
            smooth = _rolling(y, min(window, max(1, y.size // 5)))
            ax.plot(x[len(x) - smooth.size:], smooth, color=f"C{i}", label=label)
        ax.set_title(f"{title} (rolling mean)")
        ax.set_xlabel("episode")
    axes[0].legend()
    return save(fig, path)


def _vehicle_paths(traj: Mapping[str, np.ndarray]) -> list[tuple[str, int, np.ndarray, np.ndarray, np.ndarray]]:
    """(id, kind, time, chainage, speed) per vehicle, in step order."""
    times = traj["time"]
    out = []
    for v in np.unique(traj["vehicle"]):
        mine = np.flatnonzero(traj["vehicle"] == v)
        mine = mine[np.argsort(traj["step"][mine], kind="stable")]
        out.append((str(traj["ids"][v]), int(traj["kind"][mine[0]]), times[traj["step"][mine]],
                    traj["s"][mine], traj["speed"][mine]))
    return out


def time_space(traj: Mapping[str, np.ndarray], path: Path, title: str = "", upstream: float = 150.0,
               downstream: float = 250.0) -> Path:
    """Top: chainage over time of every vehicle around the merge; bottom: the guide AV's speed and actions."""
    guide = str(traj["guide"])
    merge_t = float(traj["merge_time"])
    m0, m1 = float(traj["merge_start"]), float(traj["merge_end"])
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax, ax_v, ax_a = fig.subplots(3, 1, sharex=True, height_ratios=[3, 1.4, 0.8])
    for vid, kind, t, s, v in _vehicle_paths(traj):
        is_guide = vid == guide
        color = GUIDE_COLOR if is_guide else COLORS.get(kind, "grey")
        width = 2.2 if is_guide or kind == KIND_MERGER else 0.9
        ax.plot(t, s, color=color, lw=width, zorder=3 if is_guide or kind == KIND_MERGER else 2)
        if is_guide or kind == KIND_MERGER:
            ax_v.plot(t, v, color=color, lw=1.8, label="guide AV " + vid if is_guide else "merging vehicle")
    for y in (m0, m1):
        ax.axhline(y, color="k", ls="--", lw=0.8)
    ax.text(float(traj["time"][0]), m0, " acceleration lane", va="bottom", fontsize=8)
    if math.isfinite(merge_t):
        for a in (ax, ax_v, ax_a):
            a.axvline(merge_t, color="grey", ls=":", lw=1)
    ax.set_ylim(m0 - upstream, m1 + downstream)
    ax.set_ylabel("position along the highway [m]")
    ax.legend(*_class_legend(), loc="upper left", fontsize=8)
    ax.set_title(title or "time-space diagram of the merge area")
    ax_v.set_ylabel("speed [m/s]")
    if ax_v.lines:
        ax_v.legend(fontsize=8)
    actions = np.asarray(traj["guide_actions"])
    times = np.asarray(traj["time"])
    if actions.size:
        ax_a.step(times[: actions.size], actions, where="post", color=GUIDE_COLOR)
    ax_a.set_yticks([int(a) for a in Action], [a.name.lower().replace("_", " ") for a in Action], fontsize=7)
    ax_a.set_ylim(-0.5, len(Action) - 0.5)
    ax_a.set_xlabel("time [s]")
    return save(fig, path)


def _class_legend() -> tuple[list[Rectangle], list[str]]:
    colors = [np.asarray(c) / 255 for c in (*TOP_VIEW_COLOURS.values(), GUIDE_RGB, CRASHED_RGB)]
    return [Rectangle((0, 0), 1, 1, color=c) for c in colors], ["AV", "HV", "merging vehicle", "guide AV", "crashed"]


def top_views(traj: Mapping[str, np.ndarray], road: RoadRaster, path: Path, title: str = "",
              offsets: Sequence[float] = (-3.0, 0.0, 3.0), half_window: float = 110.0) -> Path:
    """Top views at the merge time plus `offsets` [s] (episode end when there was no merge), centred on the
    merging vehicle (or its last place), vehicles drawn to scale and coloured by class, the guide AV orange,
    crashed vehicles red; drawn by the env's renderer (`cosim.environment.render.top_view`)."""
    times = np.asarray(traj["time"])
    merge_t = float(traj["merge_time"])
    anchor = merge_t if math.isfinite(merge_t) else float(times[-1])
    steps = sorted({int(np.argmin(np.abs(times - (anchor + o)))) for o in offsets})
    guide = str(traj["guide"])
    fig = Figure(figsize=(9, 1.9 * len(steps) + 0.4), layout="constrained")
    axes = fig.subplots(len(steps), 1, squeeze=False)[:, 0]
    merger_rows = np.flatnonzero(traj["kind"] == KIND_MERGER)
    for ax, k in zip(axes, steps, strict=True):
        rows = np.flatnonzero(traj["step"] == k)
        here = merger_rows[traj["step"][merger_rows] <= k]
        cx = traj["x"][here[-1]] if here.size else traj["x"][rows].mean()
        ids = traj["ids"][traj["vehicle"][rows]]
        colours = np.array([CRASHED_RGB if traj["crashed"][r] else GUIDE_RGB if str(v) == guide
                            else TOP_VIEW_COLOURS.get(int(traj["kind"][r]), TOP_VIEW_COLOURS[KIND_HV])
                            for r, v in zip(rows, ids, strict=True)], dtype=np.uint8).reshape(-1, 3)
        img, extent = top_view(road, traj["x"][rows], traj["y"][rows], traj["heading"][rows], traj["length"][rows],
                               traj["width"][rows], colours, (cx - half_window, cx + half_window))
        ax.imshow(img, extent=extent, interpolation="nearest")
        ax.set_title(f"t = {times[k]:.1f} s", fontsize=9)
        ax.set_ylabel("y [m]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("x [m] (SUMO network coordinates)", fontsize=8)
    axes[0].legend(*_class_legend(), loc="upper left", fontsize=7, ncols=5)
    when = f"merge at {merge_t:.1f} s" if math.isfinite(merge_t) else "no merge: around the episode's end"
    fig.suptitle(f"{title + ': ' if title else ''}top views around the merge ({when})", fontsize=10)
    return save(fig, path)


def plot_evaluation(eval_dir: Path, plots_dir: Path, label: str,
                    rows: Sequence[Mapping[str, str]] | None = None) -> list[Path]:
    """One evaluation's figures: the merger distance histogram over `rows` (none without them), and per
    recorded episode a time-space diagram with the guide AV's speed profile and top views around the merge."""
    out = [distance_histogram({label: column(rows, "merger_distance")},
                              plots_dir / "merger_distance.png")] if rows is not None else []
    files = trajectory_files(eval_dir)
    if files:
        cfg = load_config(eval_dir / "config.yaml")
        road = rasterize_road(load_roadnet(cfg.net.file).lane_shapes())
        for f in files:
            traj = load_trajectory(f)
            seed = f.stem.split("_")[1]
            out.append(time_space(traj, plots_dir / f"timespace_seed_{seed}.png",
                                  title=f"{label}: episode seed {seed}, guide AV {traj['guide']}"))
            out.append(top_views(traj, road, plots_dir / f"topview_seed_{seed}.png",
                                 title=f"{label}: episode seed {seed}"))
    return out
