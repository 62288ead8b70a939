"""The state of every vehicle at one instant, as numpy arrays: what everything downstream of libsumo reads.

Contract: a `Snapshot` is produced by `cosim.sumo.session` once per decision step and never refers back to
libsumo, so observation, reward and termination are pure functions of it (and unit-testable on
hand-built snapshots, see `Snapshot.build`). Row order is arbitrary; use `row_of` to find a vehicle.
Positions are vehicle centres in SUMO's world frame [m]; headings are radians, counter-clockwise from +x.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

KIND_AV, KIND_HV, KIND_MERGER = 0, 1, 2


@dataclass(frozen=True)
class Collision:
    """One collision as SUMO reported it (`simulation.getCollisions()`), first seen at `time`."""

    time: float  # [s]
    collider: str  # SUMO's collider: the vehicle behind on the lane where they overlap
    victim: str
    collider_kind: int  # KIND_*
    victim_kind: int
    sumo_type: str  # SUMO's collision type: "collision" (on a lane), "junction", ...
    lane: str  # lane id where SUMO found it (":"-prefixed inside a junction)


@dataclass(frozen=True)
class Snapshot:
    time: float  # [s] simulation time
    ids: tuple[str, ...]  # (V,) vehicle ids
    kind: np.ndarray  # (V,) int8: KIND_AV | KIND_HV | KIND_MERGER
    x: np.ndarray  # (V,) float64 [m] centre
    y: np.ndarray  # (V,) float64 [m] centre
    heading: np.ndarray  # (V,) float64 [rad]
    speed: np.ndarray  # (V,) float64 [m/s]
    edge: np.ndarray  # (V,) int32 RoadNet.index_of: normal edges, then junction-internal ones; -1 unknown
    lane: np.ndarray  # (V,) int32 lane index on that edge (0 = rightmost)
    lane_pos: np.ndarray  # (V,) float64 [m] front bumper from the start of the lane (SUMO convention)
    distance: np.ndarray  # (V,) float64 [m] odometer since insertion
    length: np.ndarray  # (V,) float64 [m]
    width: np.ndarray  # (V,) float64 [m]
    crashed: np.ndarray  # (V,) bool: in a collision during the last decision period
    collisions: tuple[Collision, ...] = ()  # collisions first seen during the last decision period
    arrived: tuple[str, ...] = ()  # vehicles that reached the end of their route during the last period
    _rows: dict[str, int] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self._rows.update({vid: i for i, vid in enumerate(self.ids)})

    def __len__(self) -> int:
        return len(self.ids)

    def row_of(self, vid: str) -> int:
        """Row of a vehicle, or -1 if it is not in the simulation."""
        return self._rows.get(vid, -1)

    def rows_of(self, vids: Sequence[str]) -> np.ndarray:
        """(N,) int rows of several vehicles, -1 where absent."""
        return np.array([self._rows.get(v, -1) for v in vids], dtype=np.int64)

    def leader_gaps(self) -> np.ndarray:
        """(V,) [m] each vehicle's gap, bumper to bumper, to the nearest vehicle ahead on its own lane of its own
        edge; inf where none is there (a leader past the edge's end is not looked for) or the edge is unknown."""
        gaps = np.full(len(self), np.inf)
        known = np.flatnonzero(self.edge >= 0)
        if known.size < 2:
            return gaps
        key = self.edge.astype(np.int64) * 1024 + self.lane  # one number per lane of an edge
        order = known[np.lexsort((self.lane_pos[known], key[known]))]  # by lane, then from back to front
        follower, leader = order[:-1], order[1:]
        same = key[follower] == key[leader]
        gaps[follower[same]] = (self.lane_pos[leader] - self.length[leader] - self.lane_pos[follower])[same]
        return gaps

    @classmethod
    def build(cls, time: float = 0.0, **columns: Sequence) -> Snapshot:
        """A snapshot from per-vehicle lists, with defaults for omitted columns (for tests and tools)."""
        ids = tuple(columns.pop("ids"))
        events = {k: tuple(columns.pop(k)) for k in ("collisions", "arrived") if k in columns}
        n = len(ids)
        defaults = {
            "kind": (np.int8, KIND_HV), "x": (np.float64, 0.0), "y": (np.float64, 0.0),
            "heading": (np.float64, 0.0), "speed": (np.float64, 0.0), "edge": (np.int32, 0),
            "lane": (np.int32, 0), "lane_pos": (np.float64, 0.0), "distance": (np.float64, 0.0),
            "length": (np.float64, 5.0), "width": (np.float64, 1.8), "crashed": (np.bool_, False),
        }
        unknown = set(columns) - set(defaults)
        if unknown:
            raise TypeError(f"unknown snapshot columns {sorted(unknown)}")
        arrays = {
            name: (np.asarray(columns[name], dtype=dt) if name in columns else np.full(n, fill, dtype=dt))
            for name, (dt, fill) in defaults.items()
        }
        return cls(time=time, ids=ids, **arrays, **events)
