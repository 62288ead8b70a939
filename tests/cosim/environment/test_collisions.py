"""Crash attribution (pure, on hand-made snapshots) and the tracker's bookkeeping of collisions and arrivals."""

from __future__ import annotations

import numpy as np
import pytest

from cosim.environment.collisions import LaneChangeClock, attribute
from cosim.environment.episode import ENDINGS, EndCheck, MergeStatus, MergeZone, episode_end
from cosim.environment.tracker import EpisodeTracker
from cosim.sumo.net import Chainage
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Collision, Snapshot

# Edges 0 (upstream, 2 lanes), 1 (merge edge, lane 0 the acceleration lane), 2 (downstream), 3 (ramp).
_THROUGH = np.zeros((5, 3), dtype=bool)
_THROUGH[[0, 2], :2] = True
_THROUGH[1, 1:] = True
ZONE = MergeZone(merge_edge=1, accel_lanes=frozenset({0}), accel_end=100.0, through=_THROUGH,
                 rank=np.where(_THROUGH, np.cumsum(_THROUGH, axis=1) - 1, -1), target_rank=0)
CHAIN = Chainage(offsets=np.array([0.0, 100.0, 200.0, 50.0]), merge_start=100.0, merge_end=200.0,
                 highway_end=1000.0)


def snap(t: float, lanes: dict[str, tuple[int, int]], kinds: dict[str, int] | None = None, **extra) -> Snapshot:
    """Vehicles at (edge, lane); everyone at 10 m on their edge."""
    ids = list(lanes)
    kinds = kinds or {}
    return Snapshot.build(time=t, ids=ids, kind=[kinds.get(v, KIND_HV) for v in ids],
                          edge=[lanes[v][0] for v in ids], lane=[lanes[v][1] for v in ids],
                          lane_pos=[10.0] * len(ids), **extra)


def clock_over(*snaps: Snapshot) -> LaneChangeClock:
    clock = LaneChangeClock()
    for s in snaps:
        clock.observe(s, ZONE.lane_rank(s))
    return clock


def test_rear_end_is_the_followers_fault() -> None:
    s = snap(1.0, {"av_0": (0, 0), "hv_0": (0, 0)})
    clock = clock_over(snap(0.0, {"av_0": (0, 0), "hv_0": (0, 0)}), s)
    a = attribute(Collision(1.0, "av_0", "hv_0", KIND_AV, KIND_HV, "collision", "hw_in_0"), clock, window=2.0)
    assert (a.kind, a.at_fault, a.cause) == ("rear_end", "av_0", "av")
    b = attribute(Collision(1.0, "hv_0", "av_0", KIND_HV, KIND_AV, "collision", "hw_in_0"), clock, window=2.0)
    assert (b.kind, b.at_fault, b.cause) == ("rear_end", "hv_0", "hv_into_av")


def test_cut_in_is_the_lane_changers_fault_within_the_window() -> None:
    # av_0 moves from lane 1 into lane 0 between t=1 and t=2; hv_0 (behind, SUMO's collider) hits it at 2.5.
    before = snap(1.0, {"av_0": (0, 1), "hv_0": (0, 0)}, {"av_0": KIND_AV})
    after = snap(2.0, {"av_0": (0, 0), "hv_0": (0, 0)}, {"av_0": KIND_AV})
    clock = clock_over(snap(0.0, {"av_0": (0, 1), "hv_0": (0, 0)}), before, after)
    assert clock.since_change("av_0", 2.5) == pytest.approx(1.5) and clock.since_change("hv_0", 2.5) == np.inf
    c = Collision(2.5, "hv_0", "av_0", KIND_HV, KIND_AV, "collision", "hw_in_0")
    a = attribute(c, clock, window=2.0)
    assert (a.kind, a.at_fault, a.cause) == ("lane_change", "av_0", "av")
    # Long after the lane change it is a plain rear-end, the follower's fault.
    late = attribute(Collision(4.0, "hv_0", "av_0", KIND_HV, KIND_AV, "collision", "hw_in_0"), clock, window=2.0)
    assert (late.kind, late.at_fault, late.cause) == ("rear_end", "hv_0", "hv_into_av")


def test_merging_vehicle_and_junction_collisions() -> None:
    # The merging vehicle leaves the acceleration lane (rank -1) for the through lane (rank 0): a lane change.
    kinds = {"merger": KIND_MERGER}
    clock = clock_over(snap(0.0, {"merger": (1, 0), "hv_0": (1, 1)}, kinds),
                       snap(1.0, {"merger": (1, 1), "hv_0": (1, 1)}, kinds))
    a = attribute(Collision(1.0, "hv_0", "merger", KIND_HV, KIND_MERGER, "collision", "hw_merge_1"), clock, 2.0)
    assert (a.kind, a.at_fault, a.cause) == ("lane_change", "merger", "merger")
    # An HV into the merging vehicle that did not change lanes: HV's fault, counted under the merging vehicle.
    clock = clock_over(snap(0.0, {"merger": (1, 0), "hv_0": (1, 0)}, kinds))
    b = attribute(Collision(0.5, "hv_0", "merger", KIND_HV, KIND_MERGER, "collision", "hw_merge_0"), clock, 2.0)
    assert (b.kind, b.cause) == ("rear_end", "merger")
    j = attribute(Collision(0.5, "av_0", "hv_0", KIND_AV, KIND_HV, "junction", ":merge_1_0"), clock, 2.0)
    assert (j.kind, j.at_fault, j.cause) == ("junction", "av_0", "av")
    h = attribute(Collision(0.5, "hv_1", "hv_0", KIND_HV, KIND_HV, "collision", "hw_in_0"), clock, 2.0)
    assert h.cause == "hv"


def test_tracker_reports_causes_and_the_distance_of_vehicles_that_left() -> None:
    tr = EpisodeTracker(ZONE, CHAIN, cut_in_window=2.0)
    kinds = {"av_0": KIND_AV, "merger": KIND_MERGER}
    ids = ["av_0", "hv_0", "hv_1", "merger"]
    base = {"ids": ids, "kind": [kinds.get(v, KIND_HV) for v in ids], "edge": [0, 0, 2, 3], "lane": [0, 0, 0, 0]}
    tr.observe(Snapshot.build(time=0.0, lane_pos=[10.0, 30.0, 780.0, 5.0], distance=[0.0] * 4, **base))
    # hv_1 leaves the net (at the axis' end, 1000 m) before the next snapshot; av_0 rear-ends hv_0.
    rest = {k: v[:2] + v[3:] for k, v in base.items()}
    c = Collision(0.7, "av_0", "hv_0", KIND_AV, KIND_HV, "collision", "x_0")
    tr.observe(Snapshot.build(time=1.0, lane_pos=[25.0, 30.0, 20.0], distance=[15.0, 0.0, 15.0],
                              crashed=[True, True, False], collisions=[c], arrived=["hv_1"], **rest))
    row = tr.row()
    assert tr.distance["hv_1"] == pytest.approx(20.0)  # it drove on to the end of its route
    assert row["crashed"] and row["cause_av"] and not row["cause_hv_into_av"] and not row["cause_merger"]
    assert row["crash_kind"] == "rear_end" and row["collisions"] == "0.7 av_0>hv_0 rear_end fault=av_0 av"


def test_episode_endings_are_named_and_checked_in_order() -> None:
    assert list(ENDINGS) == ["collision", "merger_crashed", "merger_stuck", "merger_gone", "horizon"]
    hv_hits_av = Collision(1.0, "hv", "av", KIND_HV, KIND_AV, "collision", "e_0")
    snap = Snapshot.build(ids=["av", "hv"], collisions=[hv_hits_av])
    calm = Snapshot.build(ids=["av", "hv"])
    waiting, stuck, gone = (MergeStatus(0, False, False, False), MergeStatus(0, False, True, False),
                            MergeStatus(-1, False, False, False))

    def end(snap: Snapshot = calm, status: MergeStatus = waiting, merged: bool = False, steps: int = 3,
            stop_on: frozenset[int] = frozenset({KIND_AV}), end_on_stuck: bool = True) -> str | None:
        return episode_end(EndCheck(snap, status, merged, steps, 20, stop_on, end_on_stuck))

    assert end() is None
    assert end(snap) == "collision" and end(snap, stop_on=frozenset()) is None  # on_collision: remove
    assert end(status=stuck) == "merger_stuck" and end(status=stuck, end_on_stuck=False) is None
    assert end(status=gone) == "merger_gone" and end(status=gone, merged=True) is None
    assert end(steps=20) == "horizon" and end(snap, steps=20) == "collision"
