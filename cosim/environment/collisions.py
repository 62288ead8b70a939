"""Who crashed into whom, how, and whose fault it was: crash attribution from SUMO's collision records (pure).

Contract:
- `LaneChangeClock` is fed every snapshot with the vehicles' through-lane ranks (`MergeZone.lane_rank`) and
  remembers when each vehicle last entered another lane (the time of the snapshot *before* the one that
  shows it there: the earliest it can have happened). Leaving the ramp or the acceleration lane for a
  through lane counts; a junction-internal lane keeps the rank of the lane it comes from.
- `attribute(c, clock, window)` classifies one `Collision`: kind `junction` when SUMO found it inside a
  junction; `lane_change` when one of the two entered its lane within `window` [s] before the collision,
  that vehicle at fault (the more recent one if both did); else `rear_end`, the follower at fault (SUMO's
  collider is the vehicle behind). The cause is the class of the party at fault: `av` (an AV at fault),
  `hv_into_av` (an HV at fault, the other an AV), `merger` (the merging vehicle involved, no AV at fault),
  `hv` (HVs only).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Collision, Snapshot

KINDS = ("rear_end", "lane_change", "junction")
CAUSES = ("av", "hv_into_av", "merger", "hv")
CLASS_NAMES: dict[int, str] = {KIND_AV: "av", KIND_HV: "hv", KIND_MERGER: "merger"}


class LaneChangeClock:
    """When each vehicle last entered another lane, from the snapshots of one episode."""

    def __init__(self) -> None:
        self.rank: dict[str, int] = {}
        self.changed_at: dict[str, float] = {}
        self._time = 0.0

    def observe(self, snap: Snapshot, rank: np.ndarray) -> None:
        """`rank` (V,): each vehicle's through-lane rank, -1 off the through lanes."""
        for vid, r in zip(snap.ids, rank.tolist(), strict=True):
            old = self.rank.get(vid)
            if old is not None and old != r:
                self.changed_at[vid] = self._time
            self.rank[vid] = r
        self._time = float(snap.time)

    def since_change(self, vid: str, now: float) -> float:
        """[s] since `vid` last entered another lane (inf if it never did)."""
        return now - self.changed_at.get(vid, -np.inf)


@dataclass(frozen=True)
class Attributed:
    time: float  # [s]
    collider: str
    victim: str
    collider_class: str  # av | hv | merger
    victim_class: str
    kind: str  # one of KINDS
    at_fault: str  # vehicle id
    cause: str  # one of CAUSES

    def as_dict(self) -> dict[str, str | float]:
        return asdict(self)


def attribute(c: Collision, clock: LaneChangeClock, window: float) -> Attributed:
    kinds = {c.collider: c.collider_kind, c.victim: c.victim_kind}
    if c.sumo_type == "junction" or c.lane.startswith(":"):
        kind, fault = "junction", c.collider
    else:
        recent = {v: clock.since_change(v, c.time) for v in (c.collider, c.victim)}
        changed = [v for v, dt in recent.items() if dt <= window]
        if changed:
            kind, fault = "lane_change", min(changed, key=recent.__getitem__)
        else:
            kind, fault = "rear_end", c.collider
    other = c.victim if fault == c.collider else c.collider
    if kinds[fault] == KIND_AV:
        cause = "av"
    elif kinds[fault] == KIND_HV and kinds[other] == KIND_AV:
        cause = "hv_into_av"
    elif KIND_MERGER in kinds.values():
        cause = "merger"
    else:
        cause = "hv"
    return Attributed(c.time, c.collider, c.victim, CLASS_NAMES[c.collider_kind], CLASS_NAMES[c.victim_kind],
                      kind, fault, cause)


def involves(c: Collision, kinds: frozenset[int]) -> bool:
    """Whether one of the two vehicles is of one of `kinds`."""
    return c.collider_kind in kinds or c.victim_kind in kinds
