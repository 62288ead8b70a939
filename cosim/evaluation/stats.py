"""Statistics of evaluations: intervals, summaries and tables over per-episode rows (pure; scipy does the math).

Contract:
- `mean_ci(values, confidence)` is the mean with a two-sided Student-t interval over the finite values
  (NaNs, e.g. the time to merge of an episode without a merge, are left out); with one value the interval
  is NaN, with none the mean is NaN too. `rate_ci(values, confidence)` is the proportion of 0/1 values with
  the Wilson score interval, which stays inside [0, 1] and has a width even at 0 or 1 (a t-interval would
  collapse to [0, 0] when no episode crashed); it is defined from one value on. `summarize(rows)` applies
  `rate_ci` to the rates of `RATE_METRICS` (crash %, merge success %) and `mean_ci` to every other metric
  of `SUMMARY_METRICS`, over per-episode rows (dicts, as written to `episodes.csv`); where the rows mix the
  polite and the alternative merging driver (their `merger_alt`), `by_merger` adds crash and merge success per
  driver (`crash [%], merger_alt`, ...).
- `rate(rows, column)` is one 0/1 column as a percentage with its Wilson interval; `finite(rows, column)` and
  `median(rows, column)` read one numeric column; `format_table` prints summaries side by side.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.stats

from cosim.files import column as column_of

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
    # Surrogate safety while the agents drove (cosim.sumo.outputs.conflict_counts: SUMO's SSM device, the thresholds
    # of the config's `safety:`) and hard braking (cosim.environment.tracker), counts per episode.
    "conflicts [per episode]": ("conflicts", 1.0),
    "conflicts, TTC [per episode]": ("conflicts_ttc", 1.0),
    "conflicts, DRAC [per episode]": ("conflicts_drac", 1.0),
    "conflicts, PET [per episode]": ("conflicts_pet", 1.0),
    "conflicts with an AV [per episode]": ("conflicts_av", 1.0),
    "conflicts with the merging vehicle [per episode]": ("conflicts_merger", 1.0),
    "hard braking [events per episode]": ("hard_brakes", 1.0),
    "hard braking, HVs [events per episode]": ("hard_brakes_hv", 1.0),
    "hard braking, AVs [events per episode]": ("hard_brakes_av", 1.0),
    "hard braking, merging vehicle [events per episode]": ("hard_brakes_merger", 1.0),
}
# A demand run's window (cosim.environment.flow_metrics.window_metrics), one row per seed: t-intervals over the seeds.
FLOW_METRICS: dict[str, tuple[str, float]] = {
    "throughput, total [veh/h]": ("throughput_total_vph", 1.0),
    "throughput, mainline [veh/h]": ("throughput_mainline_vph", 1.0),
    "throughput, ramp [veh/h]": ("throughput_ramp_vph", 1.0),
    "ramp queue, mean [veh]": ("ramp_queue_mean_veh", 1.0),
    "ramp queue, max [veh]": ("ramp_queue_max_veh", 1.0),
    "ramp queue, mean [m]": ("ramp_queue_mean_m", 1.0),
    "ramp queue, max [m]": ("ramp_queue_max_m", 1.0),
    "delay per vehicle [s]": ("delay_mean_s", 1.0),
    "delay, ramp vehicles [s]": ("delay_ramp_s", 1.0),
    "total delay [veh h]": ("delay_total_vehh", 1.0),
    "total time spent [veh h]": ("time_spent_vehh", 1.0),
    "distance per vehicle [m]": ("distance_mean_m", 1.0),
    "density, merge influence area [veh/km/ln]": ("density_vkmln", 1.0),
    "merge success, per merging vehicle [%]": ("merge_rate_pct", 1.0),
    "crash, per merging vehicle [%]": ("crash_rate_pct", 1.0),
    "collisions [per window]": ("collisions_window", 1.0),
    "conflicts [per window]": ("conflicts_window", 1.0),
    "conflicts with a ramp vehicle [per window]": ("conflicts_merger_window", 1.0),
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


# A scenario that draws the merging driver per episode (`scenario.merger_alt_share`) is also read per driver: the
# pooled rates mix two populations in the share the config sets. The config's section -> the rows' `merger_alt`.
MERGER_DRIVERS: dict[str, float] = {"merger": 0.0, "merger_alt": 1.0}
SPLIT_RATES = ("crash [%]", "merge success [%]")


def by_merger(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95) -> dict[str, dict[str, float | int]]:
    """`<rate>, <driver>` for each of `SPLIT_RATES` over each merging driver's episodes (`MERGER_DRIVERS`), where
    the rows hold episodes of both; else nothing."""
    alt = column_of(rows, "merger_alt")
    if not (np.any(alt == 1.0) and np.any(alt == 0.0)):
        return {}
    out = {}
    for driver, flag in MERGER_DRIVERS.items():
        picked = [r for r, a in zip(rows, alt, strict=True) if a == flag]
        for label, got in summarize(picked, confidence, {k: SUMMARY_METRICS[k] for k in SPLIT_RATES}).items():
            out[f"{label}, {driver}"] = got
    return out


def summarize(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95,
              metrics: Mapping[str, tuple[str, float]] | None = None) -> dict[str, dict[str, float | int]]:
    """Metric label -> {mean, ci_low, ci_high, n} over the episodes (or a demand run's seeds); metrics missing from
    the rows are left out (`metrics`: SUMMARY_METRICS and FLOW_METRICS by default).

    Rates (`RATE_METRICS`) get Wilson score intervals, every other metric a t-interval (module doc); every metric
    here is a count, distance, time, speed or share, so a t-interval over few values is cut at 0 (and a share's
    at 100%), what the quantity can take. The default metrics add `by_merger`'s where the rows mix merging
    drivers."""
    out = {}
    for label, (column, scale) in (metrics or {**SUMMARY_METRICS, **FLOW_METRICS}).items():
        if not any(column in r for r in rows):
            continue
        values = column_of(rows, column)
        ci = rate_ci(values, confidence) if label in RATE_METRICS else mean_ci(values, confidence)
        low, high = ci.low * scale, ci.high * scale
        low, high = max(low, 0.0), min(high, 100.0) if "[%]" in label else high
        out[label] = Interval(ci.mean * scale, low, high, ci.n).as_dict()
    return out if metrics else {**out, **by_merger(rows, confidence)}


def rate(rows: Sequence[Mapping[str, Any]], column: str, confidence: float = 0.95) -> dict[str, float | int]:
    """A 0/1 column as a percentage with its Wilson interval: {mean, ci_low, ci_high, n}."""
    ci = rate_ci(column_of(rows, column), confidence)
    return Interval(100 * ci.mean, 100 * ci.low, 100 * ci.high, ci.n).as_dict()


def finite(rows: Sequence[Mapping[str, Any]], column: str) -> np.ndarray:
    """A column's values in the rows that have one."""
    x = column_of(rows, column)
    return x[np.isfinite(x)]


def median(rows: Sequence[Mapping[str, Any]], column: str) -> float:
    got = finite(rows, column)
    return float(np.median(got)) if got.size else math.nan


def interval_text(stats: Mapping[str, float] | None) -> str:
    """`mean [low, high]` of a summary's figure, with digits by its size; the mean alone without an interval."""
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
    known = [split for label in {**SUMMARY_METRICS, **FLOW_METRICS}
             for split in (label, *(f"{label}, {d}" for d in MERGER_DRIVERS if label in SPLIT_RATES))]
    labels = [label for label in known if any(label in s for s in summaries.values())]
    header = [f"metric (mean [{confidence:.0%} CI])", *(f"{run} (n={episodes[run]})" for run in summaries)]
    rows = [[label, *(interval_text(s.get(label)) for s in summaries.values())] for label in labels]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return "\n".join([fmt.format(*header), "  ".join("-" * w for w in widths), *(fmt.format(*r) for r in rows)])
