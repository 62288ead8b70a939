"""One episode's bookkeeping from its snapshots: the row `episodes.csv` gets, and trajectories for plots.

Contract:
- `guide_av(snap)` is the AV nearest (centre to centre) to the merging vehicle, or None.
- `EpisodeTracker(zone, chainage)` is fed every snapshot of an episode (`observe(snap, actions, status)`,
  the reset snapshot first) and gives the episode's row (`row()`): its length in decision steps, crash
  (any, by class and by cause), merge success (`cosim.environment.episode.merge_status`, the env's definition)
  and time to merge, distance [m] and mean speed [m/s] by class (over every vehicle seen), the merging
  vehicle's distance, the guide AV (nearest the merging vehicle when it merges, else at its last appearance)
  and the guide's actions, and hard braking: a vehicle whose speed fell between two snapshots by more than
  `hard_braking` [m/s^2] times the decision `period` [s] brakes hard (the same drop where a collision cut the last
  period short, so that every period is judged alike); consecutive such periods are one event, and the row counts
  the events of all vehicles and by class (a vehicle's stop in its own collision is none: the env stops a wreck at
  once). At this resolution a braking shorter than a period counts only if it drops the speed that much: the
  env's AVs, which brake at `av.decel` for half a second per decelerate action, never do.
  `MergeEnv` owns one (its `infos["episode"]` summary is its row); with
  `record=True` it also keeps per-step trajectories (`trajectory()`) for plots.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from cosim.environment.collisions import CAUSES, CLASS_NAMES, Attributed, LaneChangeClock, attribute
from cosim.environment.episode import MergeStatus, MergeZone, merge_status
from cosim.sumo.net import Chainage
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER, Snapshot


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

    def __init__(self, zone: MergeZone, chainage: Chainage, record: bool = False, cut_in_window: float = 2.0,
                 hard_braking: float = 4.0, period: float = 1.0) -> None:
        self.zone = zone
        self.chainage = chainage
        self.record = record
        self.cut_in_window = cut_in_window  # [s] see cosim.environment.collisions.attribute
        self.hard_braking = hard_braking  # [m/s^2] see cosim.config.SafetyConfig.hard_braking
        self.period = period  # [s] between two decisions (sim.decision_period)
        self.hard_brakes: dict[str, int] = {}  # hard-braking events per vehicle
        self._speed: dict[str, float] = {}  # [m/s] each vehicle's speed in the last snapshot
        self._braking: set[str] = set()  # vehicles braking hard between the last two snapshots
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
        self._count_hard_braking(ids, snap.speed.tolist())
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

    def _count_hard_braking(self, ids: tuple[str, ...], speeds: list[float]) -> None:
        """Speed drops since the last snapshot beyond `hard_braking` x `period`; wrecks (`crashed`, updated first)
        and vehicles new in this snapshot excluded."""
        braking = set()
        drop = self.hard_braking * self.period
        for vid, v in zip(ids, speeds, strict=True):
            if self._speed.get(vid, v) - v > drop and vid not in self.crashed:
                braking.add(vid)
                if vid not in self._braking:
                    self.hard_brakes[vid] = self.hard_brakes.get(vid, 0) + 1
        self._braking = braking
        self._speed = dict(zip(ids, speeds, strict=True))

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
            # By cause (cosim.environment.collisions): whether a collision of that cause happened in the episode.
            **{f"cause_{cause}": cause in causes for cause in CAUSES},
            "crash_kind": first.kind if first else "",  # of the first collision
            "n_crashed": len(self.crashed),
            # Every collision: "time collider>victim kind fault=ID cause", ";"-separated.
            "collisions": ";".join(f"{c.time:.1f} {c.collider}>{c.victim} {c.kind} fault={c.at_fault} {c.cause}"
                                   for c in self.collisions),
            "merged": self.merged_at is not None,
            "time_to_merge": math.nan if self.merged_at is None else self.merged_at,
            "hard_brakes": sum(self.hard_brakes.values()),
            **{f"hard_brakes_{name}": sum(n for v, n in self.hard_brakes.items() if self.kind[v] == k)
               for k, name in CLASS_NAMES.items()},
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


