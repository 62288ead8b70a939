"""A demand run's traffic-engineering metrics over its measurement window, from SUMO's outputs and the run's record.

Contract: `window_metrics(out, rec, demand, sites, ...)` returns one row (a dict, as `episodes.csv` holds one per seed
in demand mode; a `DemandEnv`'s run summary carries it), every figure over the window
[warmup, horizon] only:
- throughput [veh/h]: vehicles leaving the merge area (the instant loops past the acceleration lane), in total and
  by origin (`merger_*` came up the ramp, the rest along the highway);
- the ramp queue [veh, m]: per detector interval, SUMO's jam length along each ramp lane into its acceleration lane
  (lane-area detectors: the interval's mean of the jam length, its maximum), plus the ramp's insertion backlog
  (vehicles waiting to enter, each taking its length and minimum gap); the window's mean of the interval means
  and the largest interval's maximum;
- delay [s, veh h]: per vehicle that wanted to enter in the window, the time it waited to enter plus its time
  lost in the network (tripinfo's departDelay + timeLoss; a vehicle still waiting at the end counts the time it
  waited; an unfinished trip its loss so far), its mean and total, and the ramp vehicles' mean;
- total time spent [veh h]: vehicle-seconds in the network (edgeData) plus the backlog's waiting;
- distance per vehicle [m]: the mean distance driven by the vehicles that wanted to enter in the window (tripinfo
  routeLength; one still waiting drove none): the paper's flow metric;
- density in the merge influence area [veh/km/ln] (the lane-area detectors' mean vehicle number over their
  length) and its HCM level of service: A to E by density (10, 20, 28, 35 pc/mi/ln), F where the demand exceeds
  the capacity (`los`);
- per merging vehicle (a ramp vehicle that reached the merge edge in the window): the share that reached a
  through lane by the horizon and the share involved in a collision; and the collisions in the window;
- with a `safety` section and the SSM device's conflicts in `out` (evaluation: `sim.outputs`), the conflicts whose
  worst value passed its threshold in the window (`cosim.sumo.outputs.conflict_counts`): in all, with an AV, with
  a ramp vehicle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

import numpy as np

from cosim.config import SafetyConfig
from cosim.sumo.demand import Demand
from cosim.sumo.flow_outputs import FlowOutputs, FlowSites
from cosim.sumo.outputs import conflict_counts
from cosim.sumo.scenario import kind_of
from cosim.sumo.setting import Setting
from cosim.sumo.snapshot import KIND_MERGER

PER_MILE = 1.609344  # [km/mi]
# HCM ramp junctions: the highest density [pc/mi/ln] of levels A to D; E above; F by demand over capacity.
LOS_BOUNDS = (("A", 10.0), ("B", 20.0), ("C", 28.0), ("D", 35.0))
MERGE_AREA_MAX = 4600.0  # [pc/h] entering the merge influence area, at most (HCM)


def level_of_service(density: float, over_capacity: bool) -> str:
    """The HCM level of service of a merge influence area: `density` [veh/km/ln]."""
    if over_capacity:
        return "F"
    if not math.isfinite(density):
        return "-"
    per_mile = density * PER_MILE
    return next((letter for letter, bound in LOS_BOUNDS if per_mile <= bound), "E")


def over_capacity(demand: Demand, lanes_after: int) -> tuple[bool, str]:
    """Whether the demand exceeds what the merge can carry, and the capacity judged against, in words."""
    downstream = demand.mainline_total + demand.ramp_vph
    cap = lanes_after * demand.freeway_capacity
    entering = demand.ramp_vph + demand.mainline_vph * min(2, demand.mainline_lanes)
    why = (f"downstream demand {downstream:.0f} veh/h against {lanes_after} x {demand.freeway_capacity:.0f} = "
           f"{cap:.0f} pc/h; entering the influence area {entering:.0f} against {MERGE_AREA_MAX:.0f} pc/h")
    return downstream > cap or entering > MERGE_AREA_MAX, why


def _intervals(out: FlowOutputs, dids: list[str], key: str) -> np.ndarray:
    """(I,) `key` summed over the detectors `dids`, per window interval."""
    series = [np.asarray([iv[key] for iv in out.intervals.get(d, [])]) for d in dids]
    n = min((len(x) for x in series), default=0)
    return np.sum([x[:n] for x in series], axis=0) if series and n else np.zeros(0)


def window_metrics(out: FlowOutputs, rec: Mapping[str, np.ndarray], demand: Demand, sites: FlowSites,
                   lanes_after: int, vehicle_gap: float, interval: float,
                   safety: SafetyConfig | None = None) -> dict[str, Any]:
    """`rec`: the run's `FlowRecorder.arrays()`; `lanes_after`: lanes of the highway past the merge (capacity);
    `vehicle_gap`: a waiting ramp vehicle's length plus minimum gap [m]; `interval`: the detectors' [s]; `safety`:
    the conflicts' thresholds."""
    w0, w1 = demand.warmup, demand.horizon
    hours = demand.window / 3600.0
    from_ramp = sum(kind_of(v) == KIND_MERGER for _, v in out.passages)
    row: dict[str, Any] = {
        "throughput_total_vph": len(out.passages) / hours, "throughput_ramp_vph": from_ramp / hours,
        "throughput_mainline_vph": (len(out.passages) - from_ramp) / hours,
    }
    # The ramp's backlog per interval (its mean and largest), aligned with the detectors' intervals.
    times, backlog = rec["time"], rec["backlog"][:, 0] if len(rec["backlog"]) else np.zeros(0)
    n_int = int(round(demand.window / interval))
    idx = ((times - w0) // interval).astype(np.int64)
    inside = (times >= w0) & (times < w1) & (idx < n_int)
    b_mean = np.array([backlog[inside & (idx == k)].mean() if np.any(inside & (idx == k)) else 0.0
                       for k in range(n_int)])
    b_max = np.array([backlog[inside & (idx == k)].max() if np.any(inside & (idx == k)) else 0.0
                      for k in range(n_int)])
    queues = [a.did for a in sites.queues]
    jam_veh, jam_m = _intervals(out, queues, "meanMaxJamLengthInVehicles"), _intervals(out, queues,
                                                                                        "meanMaxJamLengthInMeters")
    max_veh, max_m = _intervals(out, queues, "maxJamLengthInVehicles"), _intervals(out, queues, "maxJamLengthInMeters")
    k = min(len(jam_veh), n_int)
    row.update({"ramp_queue_mean_veh": float(np.mean(jam_veh[:k] + b_mean[:k])) if k else math.nan,
                "ramp_queue_mean_m": float(np.mean(jam_m[:k] + b_mean[:k] * vehicle_gap)) if k else math.nan,
                "ramp_queue_max_veh": float(np.max(max_veh[:k] + b_max[:k])) if k else math.nan,
                "ramp_queue_max_m": float(np.max(max_m[:k] + b_max[:k] * vehicle_gap)) if k else math.nan,
                "ramp_backlog_mean_veh": float(np.mean(b_mean)) if n_int else math.nan})
    trips = [t for t in out.trips if w0 <= t.intended < w1]
    delays = np.array([t.depart_delay + t.time_loss for t in trips])
    ramp_delays = np.array([t.depart_delay + t.time_loss for t in trips if kind_of(t.vid) == KIND_MERGER])
    waiting = rec["backlog"].sum(axis=1)[inside].sum() * (np.diff(times).mean() if len(times) > 1 else 0.0)
    row.update({"vehicles": len(trips), "delay_mean_s": float(delays.mean()) if len(delays) else math.nan,
                "delay_ramp_s": float(ramp_delays.mean()) if len(ramp_delays) else math.nan,
                "delay_total_vehh": float(delays.sum()) / 3600.0,
                "time_spent_vehh": (out.time_spent + float(waiting)) / 3600.0,
                "distance_mean_m": float(np.mean([t.distance for t in trips])) if trips else math.nan})
    areas = [a.did for a in sites.influence]
    number = _intervals(out, areas, "meanVehicleNumber")
    length_km = sum(a.length for a in sites.influence) / 1000.0
    density = float(np.mean(number)) / length_km if len(number) else math.nan
    over, why = over_capacity(demand, lanes_after)
    row.update({"density_vkmln": density, "los": level_of_service(density, over), "over_capacity": over,
                "capacity": why})
    reached, merged = rec["ramp_reached"], rec["ramp_merged"]
    merging = (reached >= w0) & (reached < w1)
    crashed = np.isin(rec["ramp_ids"], rec["crashed"])
    row.update({"merging_vehicles": int(merging.sum()),
                "merge_rate_pct": 100.0 * float(np.mean(np.isfinite(merged[merging]))) if merging.any() else math.nan,
                "crash_rate_pct": 100.0 * float(np.mean(crashed[merging])) if merging.any() else math.nan,
                "collisions_window": int(np.count_nonzero((rec["collision_times"] >= w0)
                                                          & (rec["collision_times"] < w1))),
                "avs_present_max": int(rec["avs_present"].max()) if len(rec["avs_present"]) else 0})
    if safety is not None and out.conflicts is not None:
        counts = conflict_counts(out.conflicts, safety, until=w1, since=w0)
        row.update({"conflicts_window": counts["conflicts"], "conflicts_av_window": counts["conflicts_av"],
                    "conflicts_merger_window": counts["conflicts_merger"]})
    return row


def demand_summary(rows: list[Mapping[str, Any]], metrics: Mapping[str, Mapping[str, float]]) -> dict[str, Any]:
    """The level of service of the runs' mean density (F where the demand exceeds the capacity), with the capacity
    it was judged against."""
    density = metrics.get("density, merge influence area [veh/km/ln]", {}).get("mean", math.nan)
    over = any(str(r.get("over_capacity")) in ("True", "true", "1") for r in rows)
    return {"level_of_service": level_of_service(density, over), "over_capacity": over,
            "capacity": str(rows[0].get("capacity", "")) if rows else ""}


def demand_setting(on_net: Setting) -> dict[str, Any]:
    """The demand of a demand setting (veh/h, the AVs, the times, the capacities), JSON-ready."""
    assert on_net.demand is not None, "a demand config's setting"
    return {**asdict(on_net.demand), "interval": on_net.config.demand.interval}
