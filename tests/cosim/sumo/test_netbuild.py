"""The merge-net builder against real netconvert output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.errors import NetError
from cosim.sumo.netdesc import load_net_description
from cosim.sumo.roadnet import load_roadnet
from sumo_net.build import build_merge_net, run_netconvert

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

DEFAULT_NET = Path(__file__).resolve().parents[3] / "sumo_net" / "merge" / "merge.net.xml"


def test_two_lane_variant_has_expected_lanes_and_lengths(two_lane_net: Path) -> None:
    net = load_roadnet(two_lane_net)
    assert net.edge_ids == ("hw_in", "hw_merge", "hw_out", "ramp")
    assert {e: net.num_lanes(e) for e in net.edge_ids} == {"hw_in": 2, "hw_merge": 3, "hw_out": 2, "ramp": 1}
    # Junctions take a little of each edge's length.
    for edge, length in {"hw_in": 100, "hw_merge": 80, "hw_out": 500, "ramp": 120}.items():
        assert net.edge_length(edge) == pytest.approx(length, abs=2.0), edge
    for name in ("merge.nod.xml", "merge.edg.xml", "merge.con.xml", "merge.yaml"):
        assert (two_lane_net.parent / name).is_file()
    desc = load_net_description(net, None)
    assert desc.source == str(two_lane_net.with_name("merge.yaml"))
    assert desc.accel_lanes == (0,)


def test_lanes_line_up_and_ramp_joins_accel_lane(two_lane_net: Path) -> None:
    net = load_roadnet(two_lane_net)
    w = 3.2
    # Highway lanes hang right (-y) of y = 0: hw_in lane i continues as hw_merge lane i+1 and hw_out lane i.
    for i in range(2):
        y = net.lane("hw_in", i).shape[:, 1]
        assert np.allclose(y, -(2 - i - 0.5) * w)
        assert np.allclose(net.lane("hw_merge", i + 1).shape[:, 1], y[0])
        assert np.allclose(net.lane("hw_out", i).shape[:, 1], y[0])
        assert net.lane("hw_in", i).successors == (("hw_merge", i + 1),)
        assert net.lane("hw_merge", i + 1).successors == (("hw_out", i),)
    accel = net.lane("hw_merge", 0)
    assert np.allclose(accel.shape[:, 1], -2.5 * w)
    assert accel.successors == ()  # lane drop
    assert net.lane("ramp", 0).successors == (("hw_merge", 0),)
    ramp_end, accel_start = net.lane("ramp", 0).shape[-1], accel.shape[0]
    assert np.linalg.norm(ramp_end - accel_start) < 2.0  # only the short junction between them
    # Positions match the node file (no offset normalisation): the highway starts at x = 0.
    assert net.lane("hw_in", 0).shape[0, 0] == pytest.approx(0.0)
    assert net.lane("hw_out", 0).shape[-1, 0] == pytest.approx(100 + 80 + 500)


def test_committed_default_net_matches_fresh_build(tmp_path: Path) -> None:
    fresh = load_roadnet(build_merge_net(tmp_path))
    committed = load_roadnet(DEFAULT_NET)
    assert committed.edge_ids == fresh.edge_ids
    for e in fresh.edge_ids:
        a, b = committed.edges[e], fresh.edges[e]
        assert a.length == pytest.approx(b.length, abs=0.01)
        assert [lane.successors for lane in a.lanes] == [lane.successors for lane in b.lanes]
        for la, lb in zip(a.lanes, b.lanes, strict=True):
            assert np.allclose(la.shape, lb.shape, atol=0.01) and la.speed == lb.speed
    for name in ("nod", "edg", "con"):
        committed_src = (DEFAULT_NET.parent / f"merge.{name}.xml").read_text()
        assert committed_src == (tmp_path / f"merge.{name}.xml").read_text()
    assert (DEFAULT_NET.parent / "merge.yaml").read_text() == (tmp_path / "merge.yaml").read_text()


def test_main_builds_with_flags(tmp_path: Path) -> None:
    out = tmp_path / "my_merge"
    assert main(["build-net", "--lanes", "1", "--accel-length", "60", "--name", "m1", "--out", str(out)]) == 0
    net = load_roadnet(out / "m1.net.xml")
    assert net.num_lanes("hw_merge") == 2
    assert net.edge_length("hw_merge") == pytest.approx(60, abs=2.0)
    assert (out / "m1.yaml").read_text().startswith("# Net description for m1.net.xml")


def test_flags_beside_a_shape_replace_its_values(tmp_path: Path) -> None:
    assert main(["build-net", "--shape", "one_lane", "--lanes", "3", "--accel-length", "80",
                 "--out", str(tmp_path)]) == 0
    net = load_roadnet(tmp_path / "one_lane.net.xml")
    assert net.num_lanes("hw_in") == 3  # the flag, not the shape's 1
    assert net.edge_length("hw_merge") == pytest.approx(80, abs=2.0)


@pytest.mark.parametrize(
    ("argv", "key"),
    [
        (["--shape", "curved", "--lanes", "0"], "lanes must be an integer >= 1"),
        (["--shape", "two_lane_ramp", "--accel-length", "-1"], "accel_length must be a positive number"),
        (["--shape", "curved", "--curve-radius", "-100"], "curve_radius must be 0"),
    ],
)
def test_flags_beside_a_shape_are_checked(tmp_path: Path, argv: list[str], key: str,
                                          caplog: pytest.LogCaptureFixture) -> None:
    assert main(["build-net", *argv, "--out", str(tmp_path)]) == 2
    assert key in caplog.text
    assert not list(tmp_path.iterdir())  # refused before anything is written


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"lanes": 0}, "lanes"),
        ({"accel_length": 0.0}, "accel_length"),
        ({"ramp_length": -5.0}, "ramp_length"),
        ({"upstream_length": float("nan")}, "upstream_length"),
        ({"highway_speed": 0}, "highway_speed"),
        ({"name": "a/b"}, "name"),
    ],
)
def test_bad_parameters_raise_net_error(tmp_path: Path, kwargs: dict, key: str) -> None:
    with pytest.raises(NetError, match=key):
        build_merge_net(tmp_path, **kwargs)
    assert not list(tmp_path.iterdir())  # validated before anything is written


def test_netconvert_failure_reports_its_stderr(tmp_path: Path) -> None:
    build_merge_net(tmp_path, name="bad")
    (tmp_path / "bad.edg.xml").write_text('<edges><edge id="x" from="nowhere" to="merge"/></edges>')
    with pytest.raises(NetError, match=r"netconvert failed on .*bad(.|\n)*nowhere"):
        run_netconvert(tmp_path, "bad")
