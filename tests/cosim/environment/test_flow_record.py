"""The demand run's record (pure numpy, hand-built snapshots on the dilemma net): where each collision happened."""

from __future__ import annotations

import numpy as np

from cosim.config import load_config
from cosim.environment.episode import MergeZone
from cosim.environment.flow_record import FlowRecorder
from cosim.sumo.net import load_net
from cosim.sumo.snapshot import KIND_HV, KIND_MERGER, Collision, Snapshot


def test_a_collision_is_recorded_where_its_collider_was_else_its_victim() -> None:
    net = load_net(load_config("configs/default.yaml").net.file)
    merge = net.road.index_of[net.desc.merge_edge]
    start = float(net.chainage.offsets[merge])
    record = FlowRecorder(MergeZone.from_net(net), net.chainage, (120.0, 720.0))
    both = Collision(300.0, "hv_1", "merger_0", KIND_HV, KIND_MERGER, "collision", f"{net.desc.merge_edge}_1")
    gone = Collision(300.0, "hv_9", "merger_0", KIND_HV, KIND_MERGER, "collision", f"{net.desc.merge_edge}_1")
    for collision in (both, gone):  # hv_9 has left the net: its victim's place
        record.observe(Snapshot.build(300.0, ids=["hv_1", "merger_0"], kind=[KIND_HV, KIND_MERGER],
                                      edge=[merge, merge], lane=[1, 0], lane_pos=[50.0, 44.0],
                                      collisions=[collision]), ())
    rec = record.arrays()
    assert rec["collision_times"].tolist() == [300.0, 300.0]
    np.testing.assert_allclose(rec["collision_chainage"], [start + 50.0, start + 44.0])
