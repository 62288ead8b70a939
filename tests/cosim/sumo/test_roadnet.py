"""RoadNet read from a real netconvert output, and its errors on bad files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import NetError
from cosim.sumo.roadnet import load_roadnet

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

def test_reads_edges_lanes_and_shapes(two_lane_net: Path) -> None:
    net = load_roadnet(two_lane_net)
    assert net.net_file == two_lane_net
    assert net.edge_ids == tuple(sorted(net.edge_ids)) and not any(e.startswith(":") for e in net.edge_ids)
    assert [net.edge_index[e] for e in net.edge_ids] == list(range(len(net.edge_ids)))
    lane = net.lane("hw_merge", 1)
    assert lane.id == "hw_merge_1" and lane.index == 1
    assert lane.shape.dtype == np.float64 and lane.shape.ndim == 2 and lane.shape.shape[1] == 2
    assert not lane.shape.flags.writeable
    assert lane.width == pytest.approx(3.2)
    assert lane.speed == pytest.approx(33.33)
    assert net.lane("ramp", 0).speed == pytest.approx(22.22)
    assert lane.length == pytest.approx(np.linalg.norm(np.diff(lane.shape, axis=0), axis=1).sum(), abs=0.05)
    assert net.successors("hw_in") == ("hw_merge",)
    assert net.predecessors("hw_merge") == ("hw_in", "ramp")
    assert net.connections("ramp", "hw_merge") == ((0, 0),)
    with pytest.raises(NetError, match="no lane 3"):
        net.lane("hw_merge", 3)
    with pytest.raises(NetError, match="no edge 'nope'"):
        net.edge("nope")


def test_lane_shapes_and_junction_internal_lanes(two_lane_net: Path) -> None:
    net = load_roadnet(two_lane_net)
    shapes = net.lane_shapes()
    assert len(shapes) == sum(net.num_lanes(e) for e in net.edge_ids) == 8
    pts = np.concatenate([s for s, _ in shapes])
    assert pts[:, 1].max() == pytest.approx(-1.6)  # the highway's left border (y = 0) minus half a lane
    assert pts[:, 0].max() == pytest.approx(680.0)  # the highway's end
    # Internal lanes: indexed after the normal edges, each with the normal lane it leaves.
    n = len(net.edge_ids)
    assert sorted(net.index_of[e] for e in net.internal_ids) == list(range(n, n + len(net.internal)))
    leaving = {(lane.from_edge, lane.to_edge) for lanes in net.internal.values() for lane in lanes}
    assert leaving == {("hw_in", "hw_merge"), ("ramp", "hw_merge"), ("hw_merge", "hw_out")}
    assert all(lane.length > 0 for lanes in net.internal.values() for lane in lanes)


def test_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.net.xml"
    with pytest.raises(NetError, match=f"net file {re.escape(str(missing))}: not found"):
        load_roadnet(missing)


def test_truncated_file(two_lane_net: Path, tmp_path: Path) -> None:
    bad = tmp_path / "cut.net.xml"
    bad.write_text(two_lane_net.read_text()[:4000])
    msg = rf"net file {re.escape(str(bad))}: not a readable SUMO network.*\.net\.xml"
    with pytest.raises(NetError, match=msg):
        load_roadnet(bad)


def test_xml_that_is_not_a_net(tmp_path: Path) -> None:
    bad = tmp_path / "routes.xml"
    bad.write_text('<routes><vehicle id="a" depart="0"/></routes>')
    msg = rf"net file {re.escape(str(bad))}: no edges found; expected a SUMO network"
    with pytest.raises(NetError, match=msg):
        load_roadnet(bad)
