"""Figures of evaluations and training runs, as PNG files (matplotlib's Agg canvas, no pyplot state).

Contract: every function takes plain data (summaries, per-episode columns, a trajectory dict as written by
`cosim.environment.tracker.EpisodeTracker.trajectory`, training log CSVs) and a path, writes one PNG there and
returns the path (or None when there is nothing to draw, e.g. training logs without known columns). Every
figure has a title, axis labels with units, legends outside the axes (they cover no data) and, given
`caption` (`caption_text`: the net, config and policy its data came from), that line at its foot.
- `bars`: crash %, merge %, mean distance, throughput and time loss with 95% intervals, runs side by side.
- `over_phi`: the trade-off over the SVO angle, one panel per metric, error bars, references dashed.
- `distance_histogram`: the merging vehicle's distance travelled, overlaid per run, with the acceleration
  lane's start and end marked (`accel_lane_marks`: where a merging vehicle reaches them, by its start).
- `training_curves`: return, crash rate, merge rate, distance over training episodes: per group (an SVO
  angle, or a run) the mean over its runs (seeds) of each run's rolling mean, with a band from the lowest to
  the highest run, and a marker where the group's crash rate first falls to `CRASH_TARGET` or below; beside
  them, where a run has a `validation.csv` (`train.eval_every`), the greedy validation's crash and merge rates
  (mean over the group's runs, dashed, with their band) and a star where each run first met a given criterion.
- `time_space`: time-space diagram of the merge area (each vehicle's first moment in a collision marked, the
  legend's "crashed" only where there is one), and the guide AV's speed profile and actions.
- `top_views`: a few top-view snapshots around the merge.
- `plot_evaluation`: one evaluation folder's figures (`cosim evaluate` and `cosim compare` draw through it).
"""

from __future__ import annotations

import json
import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import MaxNLocator

from cosim.config import load_config
from cosim.environment.control import Action
from cosim.environment.render import COLOURS as TOP_VIEW_COLOURS
from cosim.environment.render import lane_markings, top_view
from cosim.environment.velocity_map import RoadRaster, rasterize_road
from cosim.evaluation.store import load_trajectory, trajectory_files
from cosim.files import VALIDATION_LOG, atomic_path, column, read_csv
from cosim.sumo.roadnet import load_roadnet
from cosim.sumo.setting import Setting
from cosim.sumo.snapshot import KIND_HV, KIND_MERGER

GUIDE_RGB = (255, 150, 20)
CRASHED_RGB = (230, 30, 30)
# One palette for every figure: the renderer's class colours.
COLORS = {kind: tuple(c / 255 for c in rgb) for kind, rgb in TOP_VIEW_COLOURS.items()}
GUIDE_COLOR = tuple(c / 255 for c in GUIDE_RGB)
CRASH_COLOR = tuple(c / 255 for c in CRASHED_RGB)
BAR_METRICS = ("crash [%]", "merge success [%]", "mean distance [m]", "throughput [veh/h]", "time loss [s]")
# Training-log columns, first match wins: panel (y label with unit) -> (scale, candidate column names).
TRAINING_COLUMNS: dict[str, tuple[float, tuple[str, ...]]] = {
    "return per AV and episode": (1.0, ("return_mean", "return", "episode_return", "mean_return")),
    "crash rate [% of episodes]": (100.0, ("crashed", "crash", "crash_rate")),
    "merge rate [% of episodes]": (100.0, ("merged", "merge", "merge_rate")),
    "mean distance [m]": (1.0, ("mean_distance", "distance")),
}
CRASH_TARGET = 2.0  # [%] the crash rate a trained policy should get below (training curves mark it)
# Training panels that a run's validation (`VALIDATION_LOG`, already in %) draws on too: panel -> its column.
VALIDATION_COLUMNS = {"crash rate [% of episodes]": "crash", "merge rate [% of episodes]": "merge"}


def save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:  # the temporary keeps the suffix that tells matplotlib the format
        fig.savefig(tmp, dpi=110)
    return path


# -- captions ------------------------------------------------------------------------------------------
def caption_text(net: str | Sequence[str], config: str | Sequence[str], policy: str | Sequence[str]) -> str:
    """The caption line of a figure: the net, config and policy (each a value, or one per run: repeated
    values are named once) that its data came from."""
    def joined(value: str | Sequence[str]) -> str:
        return ", ".join(dict.fromkeys([value] if isinstance(value, str) else value))

    return f"net: {joined(net)}; config: {joined(config)}; policy: {joined(policy)}"


def evaluation_caption(summaries: Sequence[Mapping[str, Any]]) -> str:
    """`caption_text` of evaluations, from their summary.json (or evaluation.json) records."""
    def policy(s: Mapping[str, Any]) -> str:
        checkpoint = s.get("checkpoint")
        return str(s.get("policy", "?")) + (f" ({short_path(checkpoint)})" if checkpoint else "")

    # Folders from before the config's file was recorded: their own copy of the resolved config.
    configs = [short_path(s["config"]) if s.get("config") else "the evaluation folder's config.yaml" for s in summaries]
    return caption_text([short_path(s.get("net") or "?") for s in summaries], configs, [policy(s) for s in summaries])


def short_path(path: str | Path) -> str:
    """A path as a reader knows it: relative to the working directory where it is inside it."""
    p = Path(path)
    try:
        return str(p.resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(p)


def add_caption(fig: Figure, text: str) -> None:
    """`text` (`caption_text`) in small print at the foot of `fig`, wrapped to its width."""
    if text:
        width = int(fig.get_figwidth() * 17)  # characters of 7-point text across the figure
        fig.supxlabel("\n".join(textwrap.wrap(text, width)), x=0.01, ha="left", fontsize=7, color="0.3")


def bars(summaries: Mapping[str, Mapping[str, Mapping[str, float]]], path: Path,
         metrics: Sequence[str] = BAR_METRICS, caption: str = "",
         title: str = "Evaluation: mean per episode with its 95% interval") -> Path:
    """One panel per metric (safety, merging, distance and the flow metrics), one bar per run, error bars =
    the confidence interval; the runs are named under the bars."""
    fig = Figure(figsize=(2.6 * len(metrics), 3.6), layout="constrained")
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
        ax.set_title(metric.split(" [")[0])
        ax.set_ylabel(metric)
        if "%" in metric:
            ax.set_ylim(0, 105)
    fig.suptitle(title)
    add_caption(fig, caption)
    return save(fig, path)


def _panel_grid(n: int, most_columns: int, panel: tuple[float, float], title_room: float
                ) -> tuple[Figure, np.ndarray, int]:
    """A figure of `n` panels, `most_columns` a row at most, each `panel` (width, height) inches, `title_room` more
    inches for the title and caption: the figure, its `n` axes first (the rest of the last row hidden), and how many
    columns it has (the legend goes right of the first row)."""
    ncols = min(most_columns, n)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(panel[0] * ncols, panel[1] * nrows + title_room), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    return fig, axes, ncols


def over_phi(tables: Mapping[float, Mapping[str, Mapping[str, float]]], metrics: Sequence[str], path: Path,
             references: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None, caption: str = "",
             title: str = "Trained AVs over the SVO angle: mean with its 95% interval") -> Path:
    """The trade-off over the SVO angle: one panel per metric, the trained AVs' mean at each angle (`tables`: phi
    [rad] -> a summary's metrics) with its interval as error bars, joined by a line, and each of `references`
    (name -> metrics, e.g. a rule's) as a dashed line across."""
    fig, axes, ncols = _panel_grid(len(metrics), 4, (3.4, 3.0), 0.8)
    phis = sorted(tables)
    for ax, metric in zip(axes, metrics, strict=False):
        stats = [tables[p].get(metric, {}) for p in phis]
        mean = np.array([s.get("mean", math.nan) for s in stats], dtype=float)
        err = np.nan_to_num(np.array([[s.get("mean", math.nan) - s.get("ci_low", math.nan) for s in stats],
                                      [s.get("ci_high", math.nan) - s.get("mean", math.nan) for s in stats]]))
        ax.errorbar(phis, mean, yerr=err, marker="o", capsize=3, color="C0", label="trained AVs")
        for j, (name, ref) in enumerate((references or {}).items()):
            if metric in ref:
                ax.axhline(ref[metric]["mean"], ls=(0, (4, 2)), lw=1, color=f"C{j + 1}", label=name)
        ax.set_xticks(phis, [f"{p:.2f}" for p in phis])
        ax.set_xlabel("SVO angle phi [rad]")
        ax.set_ylabel(metric)
        ax.set_title(metric.split(" [")[0])
    axes[ncols - 1].legend(*axes[0].get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(1.02, 1.0),
                           fontsize=8, frameon=False)
    fig.suptitle(title)
    add_caption(fig, caption)
    return save(fig, path)


def accel_lane_marks(on_net: Setting) -> dict[str, tuple[float, float]]:
    """[m] where a merging vehicle's odometer reads at the acceleration lane's start and at its end: spans, since
    its start on the ramp is drawn per episode (`scenario.merger_time` at its speed, `merger_distance` or
    `merger_pos`, resolved on the net and capped at the ramp's start)."""
    net, sc = on_net.net, on_net.config.scenario
    ramp = net.chainage.merge_start - net.ramp_offsets[net.desc.ramp[0]]  # [m] the ramp's start to the lane's
    if sc.merger_pos is not None:
        lo, hi = ramp - sc.merger_pos[1], ramp - sc.merger_pos[0]
    elif sc.merger_distance is not None:
        lo, hi = sc.merger_distance
    else:
        lo, hi = sc.merger_time[0] * sc.merger_speed[0], sc.merger_time[1] * sc.merger_speed[1]
    lo, hi = min(lo, ramp), min(hi, ramp)
    length = net.chainage.merge_end - net.chainage.merge_start
    return {"acceleration lane starts": (lo, hi), "acceleration lane ends": (lo + length, hi + length)}


def distance_histogram(samples: Mapping[str, Sequence[float]], path: Path, bins: int = 30,
                       xlabel: str = "distance travelled by the merging vehicle [m]",
                       marks: Mapping[str, tuple[float, float]] | None = None, caption: str = "") -> Path:
    """Histograms of the merging vehicle's distance per run, overlaid; `marks` (`accel_lane_marks`): name ->
    (low, high) [m], drawn as a shaded span between two lines (one line where low == high)."""
    fig = Figure(figsize=(8.5, 3.8), layout="constrained")
    ax = fig.subplots()
    finite = {k: np.asarray(v, dtype=float)[np.isfinite(np.asarray(v, dtype=float))] for k, v in samples.items()}
    # Bins over the data and the marks: the marks are on the axis anyway, and bars keep one width per figure.
    every = np.concatenate([*finite.values(), np.ravel(list((marks or {}).values()))])
    edges = np.histogram_bin_edges(every if every.size else np.zeros(1), bins=bins)
    for i, (label, values) in enumerate(finite.items()):
        ax.hist(values, bins=edges, alpha=0.5, color=f"C{i}", label=f"{label} (n={values.size})", density=False)
    for (name, (lo, hi)), style in zip((marks or {}).items(), ("--", ":", "-."), strict=False):
        for x in sorted({lo, hi}):
            ax.axvline(x, color="k", ls=style, lw=1)
        ax.axvspan(lo, hi, color="k", alpha=0.08, lw=0)
        ax.plot([], [], color="k", ls=style, lw=1, label=f"{name}: {lo:.0f} m" if lo == hi else
                f"{name}: {lo:.0f}-{hi:.0f} m")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # episodes come whole
    ax.set_xlabel(xlabel)
    ax.set_ylabel("episodes")
    ax.set_title("How far the merging vehicle got")
    spans = any(lo != hi for lo, hi in (marks or {}).values())
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
              title="shaded: from its farthest to its\nnearest start on the ramp" if spans else None,
              title_fontsize=7, alignment="left")
    add_caption(fig, caption)
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


def training_curves(groups: Mapping[str, Sequence[Path]], path: Path, window: int = 100,
                    caption: str = "", criterion_met: Mapping[Path, float] | None = None) -> Path | None:
    """Per group (label -> the training logs of its runs, e.g. an SVO angle's seeds) the mean over its runs of
    each run's rolling mean over `window` episodes (shorter for short logs), up to the shortest run's length,
    with a band from the lowest to the highest run; a marker where the group's crash rate first falls to
    `CRASH_TARGET` or below. The validations logged beside a run's log (`VALIDATION_LOG`) are drawn on the crash
    and merge panels: the group's mean over its runs at the episodes all of them validated at, dashed with dots,
    and the band over the runs; `criterion_met` (a training log -> the episodes at which its run first met
    a criterion, e.g. `agents.validation.meets_criterion`) puts a star on that run's validation. None if no log
    has a known column."""
    data = {label: [read_training_log(p) for p in paths if p.is_file()] for label, paths in groups.items()}
    data = {label: logs for label, logs in data.items() if logs}
    validated = {label: [(p, rows) for p in paths if p.is_file() and (rows := read_csv(p.with_name(VALIDATION_LOG)))]
                 for label, paths in groups.items() if label in data}
    validations = {label: [rows for _, rows in runs] for label, runs in validated.items()}
    met = {label: [(criterion_met[p], rows) for p, rows in runs if p in (criterion_met or {})]
           for label, runs in validated.items()}
    panels = [(title, scale, names) for title, (scale, names) in TRAINING_COLUMNS.items()
              if any(n in cols for logs in data.values() for cols in logs for n in names)]
    if not panels:
        return None
    fig, axes, ncols = _panel_grid(len(panels), 2, (5.5, 3.2), 0.6)
    smallest = min(len(next(iter(cols.values()))) for logs in data.values() for cols in logs)
    window = min(window, max(1, smallest // 5))  # a short log gets a short window, so its curve is more than a point
    handles = []
    for i, (label, logs) in enumerate(data.items()):
        # Past ten groups (a tuning table's settings) the default cycle repeats: 20 distinct colours instead.
        color = f"C{i}" if len(data) <= 10 else colormaps["tab20"](i % 20)
        for ax, (title, scale, names) in zip(axes, panels, strict=False):
            curves = [scale * _rolling(cols[name], window) for cols in logs
                      if (name := next((n for n in names if n in cols), None)) is not None]
            if not curves:
                continue
            n = min(c.size for c in curves)
            stack = np.stack([c[:n] for c in curves])  # (runs, n)
            x = np.arange(n) + window  # the episode that closes each window
            mean = np.nanmean(stack, axis=0)
            ax.plot(x, mean, color=color, lw=1.6)
            if len(curves) > 1:
                ax.fill_between(x, np.nanmin(stack, axis=0), np.nanmax(stack, axis=0), color=color, alpha=0.18,
                                lw=0)
            if title.startswith("crash"):
                below = np.flatnonzero(mean <= CRASH_TARGET + 1e-9)  # 2.0000000000000004 is 2%
                if below.size:
                    ax.plot(x[below[0]], mean[below[0]], marker="v", ms=9, color=color, mec="k", zorder=5)
            if title in VALIDATION_COLUMNS and validations[label]:
                _validation_curve(ax, validations[label], met[label], VALIDATION_COLUMNS[title], color)
        runs = f"{len(logs)} runs" if len(logs) > 1 else "1 run"
        handles.append(Line2D([], [], color=color, lw=1.6, label=f"{label} ({runs})"))
    for ax, (title, _, _) in zip(axes, panels, strict=False):
        ax.set_title(title.split(" [")[0])
        ax.set_xlabel("training episode")
        ax.set_ylabel(title)
        if title.startswith("crash"):
            ax.axhline(CRASH_TARGET, color="0.4", ls=":", lw=1)
    if any(len(logs) > 1 for logs in data.values()):
        handles.append(Patch(color="0.6", alpha=0.4, label="range over the runs (seeds)"))
    handles.append(Line2D([], [], ls="none", marker="v", ms=8, color="0.5", mec="k",
                          label=f"crash rate first <= {CRASH_TARGET:g}% (dotted line)"))
    if any(validations.values()):
        handles.append(Line2D([], [], color="0.4", ls="--", marker="o", ms=4, lw=1.2,
                              label="validation: greedy episodes on the validation seeds"))
    if any(met.values()):
        handles.append(Line2D([], [], ls="none", marker="*", ms=12, color="0.5", mec="k",
                              label="a run's validation first meeting the criterion"))
    axes[ncols - 1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    fig.suptitle(f"Training: rolling mean over {window} episode{'s' if window > 1 else ''}, mean over runs")
    add_caption(fig, caption)
    return save(fig, path)


def _validation_curve(ax: Any, runs: Sequence[Sequence[Mapping[str, str]]],
                      met: Sequence[tuple[float, Sequence[Mapping[str, str]]]], name: str, color: Any) -> None:
    """One group's validations on `ax`: the mean over its runs of column `name` at the episodes every run
    validated at (runs validating every 500 and every 1,000 episodes meet at each 1,000th), the band over the
    runs, and a star on each run's validation at the episodes it first met the criterion."""
    curves = [dict(zip(column(rows, "episodes"), column(rows, name), strict=True)) for rows in runs]
    x = np.array(sorted(set.intersection(*(set(c) for c in curves))))
    if not x.size:
        return
    stack = np.array([[c[e] for e in x] for c in curves])
    ax.plot(x, np.nanmean(stack, axis=0), color=color, ls="--", marker="o", ms=4, lw=1.2, zorder=4)
    if len(runs) > 1:
        ax.fill_between(x, np.nanmin(stack, axis=0), np.nanmax(stack, axis=0), color=color, alpha=0.08, lw=0)
    for episodes, rows in met:
        at = np.flatnonzero(column(rows, "episodes") == episodes)
        if at.size:
            ax.plot(episodes, column(rows, name)[at[0]], marker="*", ms=13, color=color, mec="k", zorder=6)


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
               downstream: float = 250.0, caption: str = "") -> Path:
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
    crashes = _crash_points(traj)
    if len(crashes):
        ax.scatter(crashes[:, 0], crashes[:, 1], s=50, marker="x", lw=1.8, color=CRASH_COLOR, zorder=4)
    for y, name in ((m0, "acceleration lane starts"), (m1, "acceleration lane ends")):
        ax.axhline(y, color="k", ls="--", lw=0.8)
        ax.annotate(name, (1.0, y), xycoords=("axes fraction", "data"), xytext=(4, 0), textcoords="offset points",
                    va="center", fontsize=8)
    if math.isfinite(merge_t):
        for a in (ax, ax_v, ax_a):
            a.axvline(merge_t, color="grey", ls=":", lw=1)
    ax.set_ylim(m0 - upstream, m1 + downstream)
    ax.set_ylabel("position along the highway [m]")
    ax.legend(*class_legend(crashed=len(crashes) > 0), loc="upper left", bbox_to_anchor=(1.0, 0.9), fontsize=8,
              frameon=False)
    ax.set_title("Time-space diagram of the merge area: position of every vehicle over time")
    ax_v.set_ylabel("speed [m/s]")
    ax_v.set_title("speeds of the guide AV and the merging vehicle", fontsize=9)
    if ax_v.lines:
        ax_v.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    actions = np.asarray(traj["guide_actions"])
    times = np.asarray(traj["time"])
    if actions.size:
        ax_a.step(times[: actions.size], actions, where="post", color=GUIDE_COLOR)
    ax_a.set_yticks([int(a) for a in Action], [a.name.lower().replace("_", " ") for a in Action], fontsize=7)
    ax_a.set_ylim(-0.5, len(Action) - 0.5)
    ax_a.set_ylabel("action")
    ax_a.set_title("the guide AV's actions", fontsize=9)
    ax_a.set_xlabel("time [s] (dotted: the merge)" if math.isfinite(merge_t) else "time [s]")
    if title:
        fig.suptitle(title)
    add_caption(fig, caption)
    return save(fig, path)


def _crash_points(traj: Mapping[str, np.ndarray]) -> np.ndarray:
    """(K, 2) time [s] and chainage [m] where each vehicle of a collision was first seen in one (rows are in step
    order); none off the highway's axis, where the diagram has no place for it."""
    rows = np.flatnonzero(np.asarray(traj["crashed"], dtype=bool))
    _, first = np.unique(traj["vehicle"][rows], return_index=True)
    rows = rows[first]
    points = np.stack([np.asarray(traj["time"])[traj["step"][rows]], traj["s"][rows]], axis=1).reshape(-1, 2)
    return points[np.isfinite(points[:, 1])]


def class_legend(guide: bool = True, crashed: bool = True) -> tuple[list[Rectangle], list[str]]:
    """Legend handles and labels of the top views' colours (the guide AV's and the crashed vehicles' only where
    they are drawn)."""
    shown = [*zip(TOP_VIEW_COLOURS.values(), ["AV", "HV", "merging vehicle"], strict=True),
             *([(GUIDE_RGB, "guide AV")] if guide else []), *([(CRASHED_RGB, "crashed")] if crashed else [])]
    return [Rectangle((0, 0), 1, 1, color=np.asarray(c) / 255) for c, _ in shown], [label for _, label in shown]


def top_views(traj: Mapping[str, np.ndarray], road: RoadRaster, path: Path, title: str = "",
              offsets: Sequence[float] = (-3.0, 0.0, 3.0), half_window: float = 110.0, caption: str = "",
              markings: np.ndarray | None = None) -> Path:
    """Top views at the merge time plus `offsets` [s] (episode end when there was no merge), centred on the
    merging vehicle (or its last place), vehicles drawn to scale and coloured by class, the guide AV orange,
    crashed vehicles red, the road with `markings` (`cosim.environment.render.lane_markings`) where given;
    drawn by the env's renderer (`cosim.environment.render.top_view`)."""
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
                               traj["width"][rows], colours, (cx - half_window, cx + half_window), markings)
        ax.imshow(img, extent=extent, interpolation="nearest")
        ax.set_title(f"t = {times[k]:.1f} s", fontsize=9)
        ax.set_ylabel("y [m]", fontsize=8)
        ax.set_xlabel("x [m]", fontsize=8, labelpad=1)  # each view has its own window along x
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("x [m] (SUMO network coordinates)", fontsize=8)
    axes[0].legend(*class_legend(), loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    when = f"merge at {merge_t:.1f} s" if math.isfinite(merge_t) else "no merge: around the episode's end"
    fig.suptitle(f"{title + ': ' if title else ''}top views around the merge ({when})", fontsize=10)
    add_caption(fig, caption)
    return save(fig, path)


def plot_evaluation(eval_dir: Path, plots_dir: Path, label: str,
                    rows: Sequence[Mapping[str, str]] | None = None) -> list[Path]:
    """One evaluation's figures: the merger distance histogram over `rows` (none without them), and per
    recorded episode a time-space diagram with the guide AV's speed profile and top views around the merge;
    each captioned with the evaluation's net, config and policy (its evaluation.json)."""
    cfg = load_config(eval_dir / "config.yaml")
    record = eval_dir / "evaluation.json"
    caption = evaluation_caption([json.loads(record.read_text(encoding="utf-8")) if record.is_file() else {}])
    out = [distance_histogram({label: column(rows, "merger_distance")}, plots_dir / "merger_distance.png",
                              marks=accel_lane_marks(Setting.of(cfg)), caption=caption)] if rows is not None else []
    files = trajectory_files(eval_dir)
    if files:
        roadnet = load_roadnet(cfg.net.file)
        road, markings = rasterize_road(roadnet.lane_shapes()), lane_markings(roadnet)
        for f in files:
            traj = load_trajectory(f)
            seed = f.stem.split("_")[1]
            out.append(time_space(traj, plots_dir / f"timespace_seed_{seed}.png",
                                  title=f"{label}: episode seed {seed}, guide AV {traj['guide']}", caption=caption))
            out.append(top_views(traj, road, plots_dir / f"topview_seed_{seed}.png",
                                 title=f"{label}: episode seed {seed}", caption=caption, markings=markings))
    return out
