"""When the merge succeeded or failed, and which agents are done (pure functions of a snapshot).

Contract: `MergeZone.from_net(net)` turns the net description into edge indices once;
`merge_status(snap, zone, stuck_speed, stuck_distance)` says whether the merging vehicle is on a through
lane of the highway (merged), stuck at the end of the acceleration lane (SUMO would hold it there forever:
a failed merge), crashed, or gone. `ENDINGS` is the registry of the conditions that end an episode for every
agent (the paper's first collision, the merging vehicle crashed, stuck or gone, the horizon), each a named
function of an `EndCheck`; `episode_end(check)` names the first that holds (None: the episode goes on).
Adding a condition is one function and one line: `@ending("name")` above it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cosim.sumo.net import Net
from cosim.sumo.snapshot import KIND_MERGER, Snapshot


@dataclass(frozen=True, eq=False)
class MergeZone:
    merge_edge: int  # edge index
    accel_lanes: frozenset[int]
    accel_end: float  # [m] length of the acceleration lane
    # Both indexed by the snapshot's (edge, lane), one row per RoadNet.index_of entry and a last row for edge
    # -1, so that indexing with the snapshot's columns needs no special case.
    # (E + 1, max lanes) bool: lane is a through lane of the highway (never inside a junction: no lane
    # changes there).
    through: np.ndarray
    # (E + 1, max lanes) int: rank of a through lane among its edge's through lanes (0 = rightmost), the same
    # lane of the highway from edge to edge; a junction-internal lane has the rank of the lane it leaves;
    # -1 elsewhere (ramp, acceleration lane).
    rank: np.ndarray
    target_rank: int  # the rank the merging vehicle must enter (beside the acceleration lane)

    @classmethod
    def from_net(cls, net: Net) -> MergeZone:
        desc, road = net.desc, net.road
        index = road.index_of
        shape = (len(index) + 1, road.max_lanes)
        through, rank = np.zeros(shape, dtype=bool), np.full(shape, -1, dtype=np.int64)
        for e in desc.highway:
            lanes = list(net.through_lanes(e))
            through[index[e], lanes] = True
            rank[index[e], lanes] = np.arange(len(lanes))
        for e, lanes in road.internal.items():
            for i, lane in enumerate(lanes):
                rank[index[e], i] = rank[index[lane.from_edge], lane.from_lane]
        return cls(
            merge_edge=index[desc.merge_edge],
            accel_lanes=frozenset(desc.accel_lanes),
            accel_end=min(road.lane(desc.merge_edge, i).length for i in desc.accel_lanes),
            through=through,
            rank=rank,
            target_rank=net.target_rank(),
        )

    def lane_rank(self, snap: Snapshot) -> np.ndarray:
        """(V,) each vehicle's through-lane rank, -1 off the through lanes."""
        return self.rank[snap.edge, snap.lane]

    def on_through_lane(self, edge: np.ndarray, lane: np.ndarray) -> np.ndarray:
        """(V,) bool: on a highway edge, and not on its acceleration lane."""
        return self.through[edge, lane]


@dataclass(frozen=True)
class MergeStatus:
    row: int  # merging vehicle's row, -1 if gone
    merged: bool  # on a through lane, not crashed
    stuck: bool  # stopped at the end of the acceleration lane
    crashed: bool


def merge_status(snap: Snapshot, zone: MergeZone, stuck_speed: float, stuck_distance: float) -> MergeStatus:
    rows = np.flatnonzero(snap.kind == KIND_MERGER)
    if rows.size == 0:
        return MergeStatus(row=-1, merged=False, stuck=False, crashed=False)
    r = int(rows[0])
    crashed = bool(snap.crashed[r])
    merged = bool(zone.on_through_lane(snap.edge[r:r + 1], snap.lane[r:r + 1])[0]) and not crashed
    stuck = (snap.edge[r] == zone.merge_edge and int(snap.lane[r]) in zone.accel_lanes
             and snap.lane_pos[r] >= zone.accel_end - stuck_distance and snap.speed[r] < stuck_speed)
    return MergeStatus(row=r, merged=merged, stuck=bool(stuck), crashed=crashed)


@dataclass(frozen=True)
class EndCheck:
    """What the episode-end conditions look at after a decision step."""

    snap: Snapshot
    status: MergeStatus
    merged: bool  # the merging vehicle has merged in this episode
    steps: int  # decision steps so far
    max_steps: int
    stop_on: frozenset[int]  # KIND_* whose collisions end the episode (sim.on_collision: end); empty: none do
    end_on_stuck: bool  # sim.end_on_stuck


ENDINGS: dict[str, Callable[[EndCheck], bool]] = {}  # checked in registration order


def ending(name: str) -> Callable[[Callable[[EndCheck], bool]], Callable[[EndCheck], bool]]:
    """Register a condition that ends the episode for every agent."""
    def register(fn: Callable[[EndCheck], bool]) -> Callable[[EndCheck], bool]:
        ENDINGS[name] = fn
        return fn

    return register


@ending("collision")  # the paper's rule: the first collision that involves an AV or the merging vehicle
def _collision(c: EndCheck) -> bool:
    return any(x.collider_kind in c.stop_on or x.victim_kind in c.stop_on for x in c.snap.collisions)


@ending("merger_crashed")
def _merger_crashed(c: EndCheck) -> bool:
    return c.status.crashed


@ending("merger_stuck")
def _merger_stuck(c: EndCheck) -> bool:
    return c.status.stuck and c.end_on_stuck


@ending("merger_gone")  # off the road without merging: it can only have been taken off (a removed collider)
def _merger_gone(c: EndCheck) -> bool:
    return c.status.row < 0 and not c.merged


@ending("horizon")
def _horizon(c: EndCheck) -> bool:
    return c.steps >= c.max_steps


def episode_end(check: EndCheck) -> str | None:
    """The name of the first ending that holds; None while the episode goes on."""
    return next((name for name, holds in ENDINGS.items() if holds(check)), None)
