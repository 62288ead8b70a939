"""What a demand run's snapshots tell beyond SUMO's detectors: the insertion backlog over time, each ramp vehicle's
merge, the collisions, and the pictures' data (pure numpy; fed every decision).

Contract: `FlowRecorder(zone, chainage, window, bins)` is fed each decision's snapshot and SUMO's insertion backlog
(`observe(snap, pending)`, by vehicle id). It keeps: per decision the backlog on the ramp and on the highway and
the AVs present; per ramp vehicle when it first reached the merge edge (its front past the acceleration lane's
start: on the acceleration lane, or straight onto a through lane) and when it first reached a through lane
(merged); every collision (each vehicle of it is counted once) and where it happened (the chainage of its
collider, else of its victim; NaN off the highway); a speed heatmap, the mean speed in
cells of `bins` = (time [s], chainage [m]) over the whole run; and, within the window, the merge area's points
(time, chainage, speed, class) for a time-space diagram. `arrays()` gives all of it as numpy arrays (what
`record.npz` holds, a few hundred kB for a 12-minute run).
"""

from __future__ import annotations

import numpy as np

from cosim.environment.episode import MergeZone
from cosim.sumo.net import Chainage
from cosim.sumo.scenario import kind_of
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER, Snapshot

MERGE_AREA = (300.0, 500.0)  # [m] the time-space diagram's reach before the acceleration lane and after its end


class FlowRecorder:
    def __init__(self, zone: MergeZone, chainage: Chainage, window: tuple[float, float],
                 bins: tuple[float, float] = (10.0, 25.0)) -> None:
        self.zone, self.chainage, self.window, self.bins = zone, chainage, window, bins
        n_t = int(np.ceil(window[1] / bins[0]))
        n_s = int(np.ceil(chainage.highway_end / bins[1])) + 1
        self.speed_sum = np.zeros((n_t, n_s))  # [m/s] summed per (time, chainage) cell
        self.speed_n = np.zeros((n_t, n_s), dtype=np.int64)
        self.times: list[float] = []
        self.backlog: list[tuple[int, int]] = []  # (ramp, highway) vehicles waiting to enter, per decision
        self.avs_present: list[int] = []
        self.reached: dict[str, float] = {}  # ramp vehicle -> when its front first passed the acceleration lane's start
        self.merged: dict[str, float] = {}  # ramp vehicle -> when it first reached a through lane [s]
        self.collisions: list[tuple[float, str, str, float]] = []  # (time, collider, victim, chainage [m])
        self.crashed: set[str] = set()
        self._points: list[np.ndarray] = []  # (K, 4) float32: time, chainage, speed, class

    def observe(self, snap: Snapshot, pending: tuple[str, ...]) -> None:
        t = float(snap.time)
        self.times.append(t)
        ramp = sum(1 for v in pending if kind_of(v) == KIND_MERGER)
        self.backlog.append((ramp, len(pending) - ramp))
        self.avs_present.append(int(np.count_nonzero(snap.kind == KIND_AV)))
        s = self.chainage.of(snap)  # (V,) NaN off the axis
        for c in snap.collisions:
            # The collider's place; its victim's where the collider has left the net since (or is off the axis).
            where = [s[r] for r in snap.rows_of([c.collider, c.victim]) if r >= 0 and np.isfinite(s[r])]
            self.collisions.append((c.time, c.collider, c.victim, float(where[0]) if where else np.nan))
            self.crashed.update((c.collider, c.victim))
        through = self.zone.on_through_lane(snap.edge, snap.lane)
        accel = (snap.edge == self.zone.merge_edge) & np.isin(snap.lane, list(self.zone.accel_lanes))
        for r in np.flatnonzero(snap.kind == KIND_MERGER):
            vid = snap.ids[r]
            if s[r] >= self.chainage.merge_start:
                self.reached.setdefault(vid, t)
            if through[r] and vid not in self.merged:
                self.merged[vid] = t
        road = np.isfinite(s) & (through | accel)
        ti = min(int(t // self.bins[0]), self.speed_sum.shape[0] - 1)
        si = np.clip((s[road] // self.bins[1]).astype(np.int64), 0, self.speed_sum.shape[1] - 1)
        np.add.at(self.speed_sum[ti], si, snap.speed[road])
        np.add.at(self.speed_n[ti], si, 1)
        if self.window[0] <= t <= self.window[1]:
            near = road & (s >= self.chainage.merge_start - MERGE_AREA[0]) & (s <= self.chainage.merge_end
                                                                               + MERGE_AREA[1])
            self._points.append(np.stack([np.full(int(near.sum()), t), s[near], snap.speed[near],
                                          snap.kind[near].astype(float)], axis=1).astype(np.float32))

    def arrays(self) -> dict[str, np.ndarray]:
        merge_ids = sorted(self.reached.keys() | self.merged.keys())
        with np.errstate(invalid="ignore", divide="ignore"):
            heat = np.where(self.speed_n > 0, self.speed_sum / np.maximum(self.speed_n, 1), np.nan)
        return {
            "time": np.asarray(self.times), "backlog": np.asarray(self.backlog, dtype=np.int32).reshape(-1, 2),
            "avs_present": np.asarray(self.avs_present, dtype=np.int32),
            "ramp_ids": np.asarray(merge_ids, dtype=str),
            "ramp_reached": np.asarray([self.reached.get(v, np.nan) for v in merge_ids]),
            "ramp_merged": np.asarray([self.merged.get(v, np.nan) for v in merge_ids]),
            "crashed": np.asarray(sorted(self.crashed), dtype=str),
            "collision_times": np.asarray([c[0] for c in self.collisions]),
            "collision_chainage": np.asarray([c[3] for c in self.collisions], dtype=np.float64),
            "heatmap": heat.astype(np.float32), "heat_bins": np.asarray(self.bins),
            "points": np.concatenate(self._points) if self._points else np.zeros((0, 4), np.float32),
            "window": np.asarray(self.window), "merge_start": np.asarray(self.chainage.merge_start),
            "merge_end": np.asarray(self.chainage.merge_end),
        }
