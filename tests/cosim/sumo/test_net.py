"""The chainage axis of a real net: junctions included, as SUMO's odometer counts."""

from __future__ import annotations

from pathlib import Path

import pytest

from cosim.sumo.net import load_net

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)


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
