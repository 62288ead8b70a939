"""The episode tracker on hand-built snapshots: known episodes give known rows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.environment.episode import MergeStatus, MergeZone
from cosim.environment.tracker import EpisodeTracker, guide_av
from cosim.sumo.net import Chainage
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot


def _snap(t: float, ids: list[str], kinds: list[int], x: list[float], edge: list[int], lane: list[int],
          dist: list[float], speed: list[float] | None = None, crashed: list[bool] | None = None,
          y: list[float] | None = None) -> Snapshot:
    n = len(ids)
    return Snapshot.build(time=t, ids=ids, kind=kinds, x=x, y=y or [0.0] * n, lane_pos=x, edge=edge, lane=lane,
                          distance=dist, speed=speed or [10.0] * n, crashed=crashed or [False] * n)


# Edges 0 (upstream), 1 (merge edge, lane 0 is the acceleration lane), 2 (downstream), 3 (ramp), on one axis.
_THROUGH = np.zeros((5, 3), dtype=bool)  # (edges + 1, lanes): the last row is junction internals
_THROUGH[[0, 2], :] = True
_THROUGH[1, 1:] = True
_RANK = np.where(_THROUGH, np.cumsum(_THROUGH, axis=1) - 1, -1)
ZONE = MergeZone(merge_edge=1, accel_lanes=frozenset({0}), accel_end=100.0, through=_THROUGH, rank=_RANK,
                 target_rank=0)
CHAIN = Chainage(offsets=np.array([0.0, 100.0, 200.0, 50.0]), merge_start=100.0, merge_end=200.0,
                 highway_end=1000.0)


def test_guide_av_is_the_nearest_av() -> None:
    s = _snap(0, ["av_0", "av_1", "hv_0", "merger"], [KIND_AV, KIND_AV, KIND_HV, KIND_MERGER],
              [0, 30, 21, 20], [0, 0, 0, 3], [0, 0, 0, 0], [0] * 4)
    assert guide_av(s) == "av_1"  # 10 m away; the HV at 1 m does not count
    assert guide_av(_snap(0, ["hv_0"], [KIND_HV], [0], [0], [0], [0])) is None


def test_tracker_crash_merge_distance_guide() -> None:
    ids = ["av_0", "av_1", "hv_0", "merger"]
    kinds = [KIND_AV, KIND_AV, KIND_HV, KIND_MERGER]
    tr = EpisodeTracker(ZONE, CHAIN, record=True)
    # reset: the merger on the ramp (edge 3); av_1 nearest
    tr.observe(_snap(0.1, ids, kinds, [0, 40, 10, 30], [0, 0, 0, 3], [1, 1, 2, 0], [0, 0, 0, 0]))
    # step 1: on the acceleration lane, av_0 nearest now
    tr.observe(_snap(1.1, ids, kinds, [60, 80, 30, 55], [0, 0, 0, 1], [1, 1, 2, 0], [60, 40, 20, 25],
                     speed=[20, 20, 10, 15]), {"av_0": 3, "av_1": 1})
    # step 2: merged onto lane 1 (a through lane); av_1 and hv_0 collide; guide fixed as av_0
    tr.observe(_snap(2.1, ids, kinds, [90, 95, 50, 80], [0, 0, 0, 1], [1, 1, 2, 1], [90, 55, 40, 50],
                     speed=[20, 0, 0, 15], crashed=[False, True, True, False]), {"av_0": 4, "av_1": 1})
    # step 3: av_1 and hv_0 removed; av_1 would be nearest, but the guide stays av_0
    tr.observe(_snap(3.1, ["av_0", "merger"], [KIND_AV, KIND_MERGER], [100, 98], [1, 1], [1, 1], [100, 68]),
               {"av_0": 1})
    row = tr.row()
    assert row["length"] == 3 and row["crashed"] and row["crash_av"] and row["crash_hv"]
    assert not row["crash_merger"] and row["n_crashed"] == 2
    assert row["merged"] and row["time_to_merge"] == pytest.approx(2.1)
    assert row["av_distance"] == pytest.approx((100 + 55) / 2) and row["hv_distance"] == 40
    assert row["merger_distance"] == 68 and row["mean_distance"] == pytest.approx((100 + 55 + 40 + 68) / 4)
    assert row["hv_speed"] == pytest.approx((10 + 10 + 0) / 3)
    assert row["guide_av"] == "av_0" and row["guide_actions"] == "3 4 1"
    traj = tr.trajectory()
    assert list(traj["time"]) == [0.1, 1.1, 2.1, 3.1] and str(traj["guide"]) == "av_0"
    assert list(traj["guide_actions"]) == [3, 4, 1]
    merger = traj["vehicle"] == list(traj["ids"]).index("merger")
    assert list(traj["s"][merger]) == [80.0, 155.0, 180.0, 198.0]  # ramp offset 50 + 30, then edge 1


def test_tracker_without_merge() -> None:
    tr = EpisodeTracker(ZONE, CHAIN)
    tr.observe(_snap(0.1, ["av_0", "merger"], [KIND_AV, KIND_MERGER], [0, 10], [0, 1], [1, 0], [0, 0]))
    tr.observe(_snap(1.1, ["av_0", "merger"], [KIND_AV, KIND_MERGER], [20, 99], [0, 1], [1, 0], [20, 9],
                     crashed=[False, True]), {"av_0": 1})
    row = tr.row()
    assert not row["merged"] and math.isnan(row["time_to_merge"]) and row["crash_merger"] and not row["crash_av"]
    assert row["guide_av"] == "av_0"


def test_tracker_merge_is_the_envs_merge_status() -> None:
    ids, kinds = ["av_0", "merger"], [KIND_AV, KIND_MERGER]
    # On a through lane but crashed: `merge_status` says not merged, and so does the tracker.
    tr = EpisodeTracker(ZONE, CHAIN)
    tr.observe(_snap(0.1, ids, kinds, [0, 10], [0, 1], [1, 0], [0, 0]))
    tr.observe(_snap(1.1, ids, kinds, [20, 150], [0, 1], [1, 1], [20, 9], crashed=[False, True]), {"av_0": 1})
    assert not tr.row()["merged"]
    # A status handed in (the env's, computed once per step) is what counts.
    tr = EpisodeTracker(ZONE, CHAIN)
    tr.observe(_snap(0.1, ids, kinds, [0, 10], [0, 1], [1, 0], [0, 0]))
    tr.observe(_snap(1.1, ids, kinds, [20, 50], [0, 1], [1, 0], [20, 9]), {"av_0": 1},
               MergeStatus(row=1, merged=True, stuck=False, crashed=False))
    assert tr.row()["merged"] and tr.row()["time_to_merge"] == pytest.approx(1.1)


def test_hard_braking_events_by_vehicle_and_class() -> None:
    """Speeds per decision period of 1 s against the 4 m/s^2 threshold: the HV brakes hard for two periods (one
    event), eases, then again (a second); the AV's drops stay at 4 m/s and below; the merging vehicle's one hard
    drop is the stop of its own crash, no braking; the late HV brakes hard from its first period on. The last
    period, cut to 0.3 s (a collision ends the episode there), is judged by the same drop: the AV's 1.5 m/s (5 m/s^2
    for 0.3 s) is not hard braking, the late HV's 4.5 m/s is."""
    ids, kinds = ["av_0", "hv_0", "merger", "hv_1"], [KIND_AV, KIND_HV, KIND_MERGER, KIND_HV]
    speeds = {"av_0": [20, 16, 12, 12, 8, 8, 6.5], "hv_0": [20, 15, 10, 9.5, 3, 3, 3],
              "merger": [15, 15, 14, 0, 0, 0, 0], "hv_1": [None, None, None, 20, 10, 10, 5.5]}
    times = [0.1, 1.1, 2.1, 3.1, 4.1, 5.1, 5.4]
    tr = EpisodeTracker(ZONE, CHAIN, hard_braking=4.0, period=1.0)
    for k, t in enumerate(times):
        here = [i for i, v in enumerate(ids) if speeds[v][k] is not None]
        tr.observe(_snap(t, [ids[i] for i in here], [kinds[i] for i in here], [10.0 * k] * len(here),
                         [0] * len(here), [1] * len(here), [10.0 * k] * len(here),
                         speed=[float(speeds[ids[i]][k]) for i in here],
                         crashed=[k == 3 and ids[i] == "merger" for i in here]), {})
    row = tr.row()
    assert tr.hard_brakes == {"hv_0": 2, "hv_1": 2}
    assert (row["hard_brakes"], row["hard_brakes_hv"], row["hard_brakes_av"], row["hard_brakes_merger"]) == (4, 4, 0, 0)
    # A lower threshold: the AV's 4 m/s drops too, in two events (a steady period between them).
    low = EpisodeTracker(ZONE, CHAIN, hard_braking=3.9)
    for k in range(6):
        low.observe(_snap(times[k], ["av_0"], [KIND_AV], [0.0], [0], [1], [0.0], speed=[float(speeds["av_0"][k])]))
    assert low.hard_brakes == {"av_0": 2}
