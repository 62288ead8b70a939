"""Metrics on hand-built episode records and snapshots: known inputs give known summaries and intervals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.environment.episode import MergeStatus, MergeZone
from cosim.environment.tracker import EpisodeTracker, guide_av
from cosim.evaluation.stats import format_table, mean_ci, rate_ci, summarize
from cosim.sumo.net import Chainage, load_net
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

def test_mean_ci_known_values() -> None:
    ci = mean_ci([1, 2, 3, 4, 5])
    half = 2.7764 * math.sqrt(2.5) / math.sqrt(5)
    assert (ci.mean, ci.n) == (3.0, 5)
    assert ci.low == pytest.approx(3 - half, abs=1e-3) and ci.high == pytest.approx(3 + half, abs=1e-3)
    one = mean_ci([7.0])
    assert one.mean == 7.0 and math.isnan(one.low) and math.isnan(one.high) and one.n == 1
    assert math.isnan(mean_ci([]).mean) and mean_ci([math.nan, 2.0]).n == 1  # NaNs are left out
    same = mean_ci([4.0, 4.0, 4.0])
    assert (same.low, same.high) == (4.0, 4.0)


def test_summarize_hand_built_records() -> None:
    # CSV-style cells as read back from episodes.csv: strings, booleans as "True"/"False", empty = missing.
    rows = [
        {"crashed": "True", "merged": "False", "time_to_merge": "", "mean_distance": "100"},
        {"crashed": "False", "merged": "True", "time_to_merge": "6.0", "mean_distance": "200"},
        {"crashed": "False", "merged": "True", "time_to_merge": "8.0", "mean_distance": "300"},
        {"crashed": "False", "merged": "True", "time_to_merge": "7.0", "mean_distance": "400"},
    ]
    s = summarize(rows)
    assert s["crash [%]"]["mean"] == 25.0 and s["merge success [%]"]["mean"] == 75.0
    # Rates get Wilson score intervals: 1 of 4 -> [4.56, 69.94] % (a t-interval would be clipped to [0, 100])
    assert s["crash [%]"]["ci_low"] == pytest.approx(4.56, abs=0.01)
    assert s["crash [%]"]["ci_high"] == pytest.approx(69.94, abs=0.01)
    assert s["merge success [%]"]["ci_low"] == pytest.approx(100 - 69.94, abs=0.01)
    d = s["mean distance [m]"]
    half = 3.1824 * np.std([100, 200, 300, 400], ddof=1) / 2
    assert d["mean"] == 250.0 and d["ci_high"] == pytest.approx(250 + half, abs=1e-2)
    assert s["time to merge [s]"]["n"] == 3 and s["time to merge [s]"]["mean"] == pytest.approx(7.0)
    assert "throughput [veh/h]" not in s  # not in the rows: left out
    one = summarize([{"crashed": True, "merged": True, "mean_distance": 5.0}])
    # One episode: a rate still has a Wilson interval, a continuous metric has none.
    assert one["crash [%]"]["mean"] == 100.0 and one["crash [%]"]["ci_low"] == pytest.approx(20.65, abs=0.01)
    assert math.isnan(one["mean distance [m]"]["ci_low"])
    table = format_table({"A": s, "B": one}, {"A": 4, "B": 1})
    assert "crash [%]" in table and "A (n=4)" in table and "B (n=1)" in table
    assert format_table({"A": s}, {"A": 4}, markdown=True).startswith("| metric")


@pytest.mark.parametrize(("k", "n", "low", "high"), [(0, 10, 0.0, 0.2775), (10, 10, 0.7225, 1.0),
                                                   (1, 4, 0.0456, 0.6994), (50, 100, 0.4038, 0.5962)])
def test_rate_ci_is_the_wilson_score_interval(k: int, n: int, low: float, high: float) -> None:
    ci = rate_ci([1] * k + [0] * (n - k))
    assert ci.mean == k / n and ci.n == n
    assert ci.low == pytest.approx(low, abs=1e-4) and ci.high == pytest.approx(high, abs=1e-4)
    assert rate_ci([1, 0, 1], confidence=0.99).high > rate_ci([1, 0, 1], confidence=0.9).high
    assert math.isnan(rate_ci([]).mean) and rate_ci([math.nan, 1.0]).n == 1
    with pytest.raises(ValueError, match="0/1"):
        rate_ci([0.5, 1.0])


def test_rates_of_none_or_all_episodes_keep_a_width() -> None:
    # No crash in 20 episodes is not "0 % for sure": the t-interval would be [0, 0].
    s = summarize([{"crashed": "False", "merged": "True", "mean_distance": "100"}] * 20)
    assert s["crash [%]"]["mean"] == 0.0 and s["crash [%]"]["ci_low"] == 0.0
    assert s["crash [%]"]["ci_high"] == pytest.approx(16.11, abs=0.01)
    assert s["merge success [%]"]["ci_high"] == 100.0
    assert s["merge success [%]"]["ci_low"] == pytest.approx(100 - 16.11, abs=0.01)
    assert (s["mean distance [m]"]["ci_low"], s["mean distance [m]"]["ci_high"]) == (100.0, 100.0)  # t-interval


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


def test_chainage_of_the_real_net(two_lane_net: Path) -> None:
    net = load_net(two_lane_net)
    road, desc, ch = net.road, net.desc, net.chainage
    ramp_end = ch.offsets[road.edge_index[desc.ramp[-1]]] + road.edge_length(desc.ramp[-1])
    assert ramp_end + road.junction_length(desc.ramp[-1], desc.merge_edge) == pytest.approx(ch.merge_start)
    # Through a junction the axis goes on where the lane left ends, up to where the next edge starts:
    # positions stay continuous (no NaN on junction-internal lanes).
    for edge, lanes in road.internal.items():
        k = road.index_of[edge]
        start = ch.offsets[road.index_of[lanes[0].from_edge]] + road.edge_length(lanes[0].from_edge)
        assert ch.offsets[k] == pytest.approx(start)
        if lanes[0].from_edge in desc.highway:
            assert ch.offsets[k] + lanes[0].length == pytest.approx(ch.offsets[road.index_of[lanes[0].to_edge]])
    assert ch.highway_end == pytest.approx(net.highway_length)
    assert ch.merge_end - ch.merge_start == pytest.approx(road.edge_length(desc.merge_edge))
