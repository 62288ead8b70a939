"""Evaluation metrics: per-episode bookkeeping from snapshots, and summaries with confidence intervals (pure).

Contract:
- `mean_ci(values, confidence)` is the mean with a two-sided Student-t interval over the finite values
  (NaNs, e.g. the time to merge of an episode without a merge, are left out); with one value the interval
  is NaN, with none the mean is NaN too. `rate_ci(values, confidence)` is the proportion of 0/1 values with
  the Wilson score interval, which stays inside [0, 1] and has a width even at 0 or 1 (a t-interval would
  collapse to [0, 0] when no episode crashed); it is defined from one value on. `summarize(rows)` applies
  `rate_ci` to the rates of `RATE_METRICS` (crash %, merge success %) and `mean_ci` to every other metric
  of `SUMMARY_METRICS`, over per-episode rows (dicts, as written to `episodes.csv`).
- `Chainage.from_net(desc, road)` places every highway and ramp edge on one longitudinal axis [m]: highway
  edges at their start's distance from the first highway edge's start, ramp edges so that the ramp's end
  meets the merge edge's start. `Chainage.of(snap)` is each vehicle's front bumper on that axis (NaN on
  junction-internal and foreign edges).
- `guide_av(snap)` is the AV nearest (centre to centre) to the merging vehicle, or None.
- `EpisodeTracker(zone, chainage)` is fed every snapshot of an episode (`observe(snap, actions, status)`,
  the reset snapshot first) and gives the episode's row (`row()`): its length in decision steps, crash
  (any, and by class), merge success (`cosim.episode.merge_status`, the env's definition) and time to
  merge, distance [m] and mean speed [m/s] by class (over every vehicle seen), the merging vehicle's
  distance, the guide AV (nearest the merging vehicle when it merges, else at its last appearance) and the
  guide's actions. `MergeEnv` owns one (its `infos["episode"]` summary is its row); with `record=True` it
  also keeps per-step trajectories (`trajectory()`) for plots.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.stats

from cosim.collisions import CAUSES, CLASS_NAMES, Attributed, LaneChangeClock, attribute
from cosim.episode import MergeStatus, MergeZone, merge_status
from cosim.netdesc import NetDescription
from cosim.roadnet import RoadNet
from cosim.snapshot import KIND_AV, KIND_MERGER, Snapshot

# Summary label -> (episodes.csv column, scale). Booleans become percentages by the x100 scale.
SUMMARY_METRICS: dict[str, tuple[str, float]] = {
    "crash [%]": ("crashed", 100.0),
    "crash, AV at fault [%]": ("cause_av", 100.0),
    "crash, HV into AV [%]": ("cause_hv_into_av", 100.0),
    "crash, merging vehicle [%]": ("cause_merger", 100.0),
    "merge success [%]": ("merged", 100.0),
    "time to merge [s]": ("time_to_merge", 1.0),
    "mean distance [m]": ("mean_distance", 1.0),
    "AV distance [m]": ("av_distance", 1.0),
    "HV distance [m]": ("hv_distance", 1.0),
    "merger distance [m]": ("merger_distance", 1.0),
    # Over the flow window from SUMO's tripinfo: a crash that ends the episode early cannot raise it. No mean
    # travel time: every trip is cut at the window's end, so it would equal the window for every policy.
    "mean speed [m/s]": ("window_speed", 1.0),
    "throughput [veh/h]": ("throughput_vph", 1.0),
    "time loss [s]": ("time_loss", 1.0),
}
# Labels of SUMMARY_METRICS whose column is 0/1 per episode: Wilson score intervals, not t-intervals.
RATE_METRICS: frozenset[str] = frozenset(label for label, (_, scale) in SUMMARY_METRICS.items() if scale == 100.0)


# -- statistics ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Interval:
    mean: float
    low: float  # NaN with fewer than two values (a t-interval) or none (a rate's)
    high: float
    n: int  # finite values used

    def as_dict(self) -> dict[str, float | int]:
        return {"mean": self.mean, "ci_low": self.low, "ci_high": self.high, "n": self.n}


def mean_ci(values: Iterable[float], confidence: float = 0.95) -> Interval:
    """Mean and two-sided t-interval of the finite values."""
    x = np.asarray([float(v) for v in values], dtype=np.float64)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n == 1:
        return Interval(mean, math.nan, math.nan, 1)
    half = float(scipy.stats.t.ppf(0.5 + confidence / 2.0, n - 1)) * float(x.std(ddof=1)) / math.sqrt(n)
    return Interval(mean, mean - half, mean + half, n)


def rate_ci(values: Iterable[float], confidence: float = 0.95) -> Interval:
    """Proportion of ones among the finite 0/1 values, with its two-sided Wilson score interval.

    Unlike a t-interval it is never zero-width at a rate of 0 or 1 and never leaves [0, 1]."""
    x = np.asarray([float(v) for v in values], dtype=np.float64)
    x = x[np.isfinite(x)]
    if not np.all((x == 0.0) | (x == 1.0)):
        raise ValueError(f"rate_ci: expected 0/1 values, got {sorted(set(x.tolist()) - {0.0, 1.0})[:3]}")
    n = int(x.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    k = int(x.sum())
    ci = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=confidence, method="wilson")
    return Interval(k / n, float(ci.low), float(ci.high), n)


def _number(value: Any) -> float:
    """A CSV cell or a Python value as a float: booleans as 0/1, empty or unparsable as NaN."""
    if isinstance(value, bool | np.bool_):
        return float(value)
    if isinstance(value, str):
        v = value.strip().lower()
        if v in ("true", "false"):
            return float(v == "true")
        try:
            return float(v) if v else math.nan
        except ValueError:
            return math.nan
    try:
        return math.nan if value is None else float(value)
    except (TypeError, ValueError):
        return math.nan


def summarize(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95,
              metrics: Mapping[str, tuple[str, float]] = SUMMARY_METRICS) -> dict[str, dict[str, float | int]]:
    """Metric label -> {mean, ci_low, ci_high, n} over the episodes; metrics missing from the rows are left out.

    Rates (`RATE_METRICS`) get Wilson score intervals, every other metric a t-interval (module doc)."""
    out = {}
    for label, (column, scale) in metrics.items():
        if not any(column in r for r in rows):
            continue
        values = [_number(r.get(column)) for r in rows]
        ci = rate_ci(values, confidence) if label in RATE_METRICS else mean_ci(values, confidence)
        out[label] = Interval(ci.mean * scale, ci.low * scale, ci.high * scale, ci.n).as_dict()
    return out


# -- geometry ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Chainage:
    """Longitudinal position [m] of each edge's start on one axis through the highway and the ramp, junctions
    included (a junction-internal lane starts where the lane it leaves ends), as SUMO's odometer counts."""

    offsets: np.ndarray  # (E,) by RoadNet.index_of; NaN for edges not on the axis
    merge_start: float  # [m] chainage of the merge edge's start (where the acceleration lane begins)
    merge_end: float  # [m] ... and end
    highway_end: float  # [m] end of the last highway edge: where every route ends

    @classmethod
    def from_net(cls, desc: NetDescription, road: RoadNet) -> Chainage:
        index = road.index_of
        offsets = np.full(len(index), np.nan)
        hw = desc.highway_offsets(road)
        for edge, s in hw.items():
            offsets[index[edge]] = s
        merge_start = hw[desc.merge_edge]
        s = merge_start - road.junction_length(desc.ramp[-1], desc.merge_edge)
        for i in reversed(range(len(desc.ramp))):
            edge = desc.ramp[i]
            s -= road.edge_length(edge)
            offsets[index[edge]] = s
            if i:
                s -= road.junction_length(desc.ramp[i - 1], edge)
        for edge, lanes in road.internal.items():
            before = lanes[0].from_edge
            offsets[index[edge]] = offsets[index[before]] + road.edge_length(before)
        return cls(offsets, merge_start, merge_start + road.edge_length(desc.merge_edge),
                   desc.highway_length(road))

    def of(self, snap: Snapshot) -> np.ndarray:
        """(V,) front-bumper chainage [m] (SUMO's lane position is the front bumper's)."""
        edge = snap.edge
        known = edge >= 0
        out = np.full(len(snap), np.nan)
        out[known] = self.offsets[edge[known]] + snap.lane_pos[known]
        return out


def guide_av(snap: Snapshot) -> str | None:
    """The AV whose centre is nearest the merging vehicle's, or None without an AV or a merging vehicle."""
    merger = np.flatnonzero(snap.kind == KIND_MERGER)
    avs = np.flatnonzero(snap.kind == KIND_AV)
    if merger.size == 0 or avs.size == 0:
        return None
    m = merger[0]
    d2 = (snap.x[avs] - snap.x[m]) ** 2 + (snap.y[avs] - snap.y[m]) ** 2
    return snap.ids[int(avs[np.argmin(d2)])]


# -- one episode's bookkeeping -------------------------------------------------------------------------
TRAJECTORY_COLUMNS = ("step", "vehicle", "kind", "s", "x", "y", "heading", "speed", "edge", "lane", "length",
                      "width", "crashed")


class EpisodeTracker:
    """Feed it each snapshot of one episode (reset first); read the episode's row at the end."""

    def __init__(self, zone: MergeZone, chainage: Chainage, record: bool = False, cut_in_window: float = 2.0) -> None:
        self.zone = zone
        self.chainage = chainage
        self.record = record
        self.cut_in_window = cut_in_window  # [s] see cosim.collisions.attribute
        self.clock = LaneChangeClock()
        self.collisions: list[Attributed] = []
        self.distance: dict[str, float] = {}  # [m] last odometer reading per vehicle
        self.position: dict[str, float] = {}  # [m] last chainage per vehicle
        self.speed_sum: dict[str, float] = {}
        self.speed_n: dict[str, int] = {}
        self.kind: dict[str, int] = {}
        self.crashed: set[str] = set()
        self.actions: dict[str, list[int]] = {}
        self.merged_at: float | None = None
        self.guide: str | None = None
        self.steps = -1  # decision steps after the reset snapshot
        self.time = 0.0
        self.times: list[float] = []
        self._columns: dict[str, list[np.ndarray]] = {c: [] for c in TRAJECTORY_COLUMNS}
        self._vid_index: dict[str, int] = {}

    def observe(self, snap: Snapshot, actions: Mapping[str, int] | None = None,
                status: MergeStatus | None = None) -> None:
        """`actions`: what each AV was told in the decision step that led to `snap` (None at reset);
        `status`: `merge_status` of `snap` where the caller has it (the env does), else it is computed here.

        One pass over the snapshot's vehicles: the env feeds every step through this."""
        self.steps += 1
        self.time = float(snap.time)
        for agent, a in (actions or {}).items():
            self.actions.setdefault(agent, []).append(int(a))
        ids = snap.ids
        chain = self.chainage.of(snap)
        # A vehicle that left the net since the last snapshot drove on to the end of its route (the axis' end).
        for vid in snap.arrived:
            if vid in self.position and vid not in self.crashed and np.isfinite(self.position[vid]):
                self.distance[vid] += self.chainage.highway_end - self.position[vid]
        self.distance.update(zip(ids, snap.distance.tolist(), strict=True))
        self.position.update(zip(ids, chain.tolist(), strict=True))
        self.kind.update(zip(ids, snap.kind.tolist(), strict=True))
        self.clock.observe(snap, self.zone.lane_rank(snap))
        self.collisions.extend(attribute(c, self.clock, self.cut_in_window) for c in snap.collisions)
        speed_sum, speed_n = self.speed_sum, self.speed_n
        for vid, v in zip(ids, snap.speed.tolist(), strict=True):
            speed_sum[vid] = speed_sum.get(vid, 0.0) + v
            speed_n[vid] = speed_n.get(vid, 0) + 1
        if snap.crashed.any():
            self.crashed.update(ids[i] for i in np.flatnonzero(snap.crashed))
        if self.merged_at is None:
            if status is None:  # the stuck test's thresholds do not matter here: only `merged` is read
                status = merge_status(snap, self.zone, stuck_speed=0.0, stuck_distance=0.0)
            if status.row >= 0:
                if status.merged:
                    self.merged_at = float(snap.time)
                # The guide is fixed at the merge; until then it follows the merging vehicle's nearest AV.
                self.guide = guide_av(snap) or self.guide
        if self.record:
            self._record(snap, chain)

    def _record(self, snap: Snapshot, chain: np.ndarray) -> None:
        n = len(snap)
        self.times.append(float(snap.time))
        idx = np.array([self._vid_index.setdefault(v, len(self._vid_index)) for v in snap.ids], dtype=np.int32)
        cols = self._columns
        cols["step"].append(np.full(n, len(self.times) - 1, dtype=np.int32))
        cols["vehicle"].append(idx)
        cols["s"].append(chain)
        for name in ("kind", "x", "y", "heading", "speed", "edge", "lane", "length", "width", "crashed"):
            cols[name].append(getattr(snap, name))

    def _by_class(self, values: Mapping[str, float], kind: int | None) -> float:
        picked = [v for vid, v in values.items() if kind is None or self.kind[vid] == kind]
        return float(np.mean(picked)) if picked else math.nan

    def row(self) -> dict[str, Any]:
        """The episode's metrics, one flat dict (a row of episodes.csv)."""
        mean_speed = {v: self.speed_sum[v] / self.speed_n[v] for v in self.speed_sum}
        crashed_kinds = {self.kind[v] for v in self.crashed}
        causes = {c.cause for c in self.collisions}
        first = self.collisions[0] if self.collisions else None
        row: dict[str, Any] = {
            "length": self.steps,  # decision steps (the env's name)
            "time": self.time,
            "crashed": bool(self.crashed),
            **{f"crash_{name}": k in crashed_kinds for k, name in CLASS_NAMES.items()},
            # By cause (cosim.collisions): whether a collision of that cause happened in the episode.
            **{f"cause_{cause}": cause in causes for cause in CAUSES},
            "crash_kind": first.kind if first else "",  # of the first collision
            "n_crashed": len(self.crashed),
            # Every collision: "time collider>victim kind fault=ID cause", ";"-separated.
            "collisions": ";".join(f"{c.time:.1f} {c.collider}>{c.victim} {c.kind} fault={c.at_fault} {c.cause}"
                                   for c in self.collisions),
            "merged": self.merged_at is not None,
            "time_to_merge": math.nan if self.merged_at is None else self.merged_at,
            "n_vehicles": len(self.distance),
            "mean_distance": self._by_class(self.distance, None),
            "mean_speed": self._by_class(mean_speed, None),
        }
        for k, name in CLASS_NAMES.items():
            row[f"{name}_distance"] = self._by_class(self.distance, k)
            row[f"{name}_speed"] = self._by_class(mean_speed, k)
        row["guide_av"] = self.guide or ""
        row["guide_actions"] = " ".join(str(a) for a in self.actions.get(self.guide or "", []))
        return row

    def trajectory(self) -> dict[str, np.ndarray]:
        """Per-step vehicle states, flat over (step, vehicle) rows; `ids[vehicle]` names a row's vehicle."""
        out = {name: (np.concatenate(parts) if parts else np.zeros(0)) for name, parts in self._columns.items()}
        out["time"] = np.asarray(self.times)
        out["ids"] = np.asarray(sorted(self._vid_index, key=self._vid_index.__getitem__), dtype=str)
        out["merge_time"] = np.asarray(math.nan if self.merged_at is None else self.merged_at)
        out["guide"] = np.asarray(self.guide or "")
        # The guide's action at step k was applied between times[k] and times[k + 1].
        out["guide_actions"] = np.asarray(self.actions.get(self.guide or "", []), dtype=np.int64)
        out["merge_start"] = np.asarray(self.chainage.merge_start)
        out["merge_end"] = np.asarray(self.chainage.merge_end)
        return out


def _cell(stats: Mapping[str, float] | None) -> str:
    if not stats or not math.isfinite(stats["mean"]):
        return "-"
    mean, low, high = stats["mean"], stats["ci_low"], stats["ci_high"]
    digits = 0 if abs(mean) >= 100 else 1 if abs(mean) >= 10 else 2
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def format_table(summaries: Mapping[str, Mapping[str, Mapping[str, float]]], episodes: Mapping[str, int],
                 markdown: bool = False, confidence: float = 0.95) -> str:
    """One row per metric, one column per run: 'mean [CI low, CI high]' (plain text or Markdown)."""
    labels = [label for label in SUMMARY_METRICS if any(label in s for s in summaries.values())]
    header = [f"metric (mean [{confidence:.0%} CI])", *(f"{run} (n={episodes[run]})" for run in summaries)]
    rows = [[label, *(_cell(s.get(label)) for s in summaries.values())] for label in labels]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return "\n".join([fmt.format(*header), "  ".join("-" * w for w in widths), *(fmt.format(*r) for r in rows)])
