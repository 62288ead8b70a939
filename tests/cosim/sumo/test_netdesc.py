"""Net descriptions: loading, inference, chainage helpers, and every validation error."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
import yaml

from cosim.errors import NetError
from cosim.sumo.net import Net
from cosim.sumo.netdesc import NetDescription, infer_net_description, load_net_description
from cosim.sumo.roadnet import RoadNet, load_roadnet
from sumo_net.build import build_merge_net

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

GOOD = "highway: [hw_in, hw_merge, hw_out]\nramp: [ramp]\nmerge_edge: hw_merge\naccel_lanes: [0]\n"


@pytest.fixture(scope="module")
def net(two_lane_net: Path) -> RoadNet:
    return load_roadnet(two_lane_net)


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "desc.yaml"
    path.write_text(text)
    return path


def test_loads_the_yaml_beside_the_net(net: RoadNet, two_lane_net: Path) -> None:
    desc = load_net_description(net, None)
    assert desc == NetDescription(("hw_in", "hw_merge", "hw_out"), ("ramp",), "hw_merge", (0,),
                                  str(two_lane_net.with_name("merge.yaml")))


@pytest.mark.parametrize("lanes", [1, 2, 3])
def test_inference_matches_the_builders_yaml(tmp_path: Path, lanes: int) -> None:
    net_file = build_merge_net(tmp_path, lanes=lanes, accel_length=90)
    from_yaml = load_net_description(load_roadnet(net_file), None)
    net_file.with_name("merge.yaml").unlink()
    inferred = load_net_description(load_roadnet(net_file), None)
    assert inferred.source == "inferred"
    for key in ("highway", "ramp", "merge_edge", "accel_lanes"):
        assert getattr(inferred, key) == getattr(from_yaml, key)


def test_an_inferred_description_is_logged_once_per_net_as_the_file_to_write(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    net_file = build_merge_net(tmp_path, lanes=2, accel_length=90)
    net_file.with_name("merge.yaml").unlink()
    caplog.set_level(logging.INFO, logger="cosim.sumo.netdesc")
    for _ in range(3):  # a run loads its net again and again: env, resolution, detectors, plots
        desc = load_net_description(load_roadnet(net_file), None)
    (record,) = [r for r in caplog.records if "no description file" in r.getMessage()]
    message = record.getMessage()
    assert len(message) < 300
    # The description as the file would hold it, and where to write it.
    written = re.search(r"inferred (\{.*\}) \(write it to merge\.yaml beside the net to make it explicit\)$",
                        message)
    assert written is not None
    assert yaml.safe_load(written[1]) == {"highway": list(desc.highway), "ramp": list(desc.ramp),
                                          "merge_edge": desc.merge_edge, "accel_lanes": list(desc.accel_lanes)}
    # Written there, it describes the same net.
    net_file.with_name("merge.yaml").write_text(written[1] + "\n")
    explicit = load_net_description(load_roadnet(net_file), None)
    assert explicit.source == str(net_file.with_name("merge.yaml"))
    assert all(getattr(explicit, k) == getattr(desc, k) for k in ("highway", "ramp", "merge_edge", "accel_lanes"))


def test_chainage_helpers(net: RoadNet) -> None:
    geo = Net(net, load_net_description(net, None))
    offsets = geo.highway_offsets
    assert offsets["hw_in"] == 0.0
    # The ways through the junctions count, as in SUMO's odometer.
    junction = net.junction_length("hw_in", "hw_merge")
    assert 0.5 < junction < 3.0 and net.junction_length("hw_in", "hw_out") == 0.0
    assert offsets["hw_merge"] == pytest.approx(net.edge_length("hw_in") + junction)
    assert offsets["hw_out"] == pytest.approx(offsets["hw_merge"] + net.edge_length("hw_merge")
                                              + net.junction_length("hw_merge", "hw_out"))
    assert geo.highway_position(0.0) == ("hw_in", 0.0)
    edge, pos = geo.highway_position(offsets["hw_merge"] + 10.0)
    assert edge == "hw_merge" and pos == pytest.approx(10.0)
    total = geo.highway_length
    assert geo.highway_position(total) == ("hw_out", pytest.approx(net.edge_length("hw_out")))
    with pytest.raises(ValueError, match="outside the highway"):
        geo.highway_position(total + 1.0)
    with pytest.raises(ValueError, match="outside the highway"):
        geo.highway_position(-1.0)
    assert geo.through_lanes("hw_merge") == (1, 2)
    assert geo.through_lanes("hw_in") == (0, 1)


def test_explicit_file_overrides_the_one_beside_the_net(net: RoadNet, tmp_path: Path) -> None:
    path = _write(tmp_path, GOOD)
    assert load_net_description(net, path).source == str(path)


def test_missing_description_file(net: RoadNet, tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    with pytest.raises(NetError, match=f"net description {re.escape(str(missing))}: not found"):
        load_net_description(net, missing)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (GOOD + "extra: 1\n", r"unknown key 'extra'"),
        (GOOD.replace("ramp: [ramp]\n", ""), r"missing key 'ramp'"),
        (GOOD.replace("hw_out]", "hw_gone]"),
         r"edge 'hw_gone' \(key highway\) does not exist in .*merge\.net\.xml; edges are: hw_in, hw_merge"),
        (GOOD.replace("ramp: [ramp]", "ramp: [onramp]"), r"edge 'onramp' \(key ramp\) does not exist"),
        (GOOD.replace("accel_lanes: [0]", "accel_lanes: [3]"), r"accel_lanes: lane 3 out of range"),
        (GOOD.replace("accel_lanes: [0]", "accel_lanes: [x]"), r"accel_lanes: expected a list of lane"),
        (GOOD.replace("merge_edge: hw_merge", "merge_edge: ramp"), r"merge_edge 'ramp' is not in highway"),
        (GOOD.replace("[hw_in, hw_merge, hw_out]", "[hw_in, hw_out]").replace("merge_edge: hw_merge",
                                                                               "merge_edge: hw_in"),
         r"key highway: edge 'hw_in' has no connection to 'hw_out'"),
        ("- a\n- b\n", r"expected a mapping with keys"),
        # PyYAML's own message spans lines, with a caret; ours is one line naming the spot.
        ("highway: [\n  hw_in\nramp: x]\n", r"not valid YAML: line 3, column 5: expected ',' or '\]', but got ':' "
                                           r"\(while parsing a flow sequence from line 1, column 10\)$"),
    ],
)
def test_bad_descriptions_name_file_and_key(net: RoadNet, tmp_path: Path, text: str, message: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(NetError, match=rf"net description {re.escape(str(path))}: [^\n]*{message}"):
        load_net_description(net, path)


def test_inference_failure_explains_the_yaml(rampless_net: Path) -> None:
    net = load_roadnet(rampless_net)
    msg = r"cannot infer the on-ramp merge: .*found none.* beside the net \(merge\.yaml\).*accel_lanes: \[0\]\}$"
    with pytest.raises(NetError, match=msg):
        infer_net_description(net)
    with pytest.raises(NetError, match="cannot infer"):
        load_net_description(net, None)


def test_empty_accel_lanes_is_refused(tmp_path: Path) -> None:
    net = build_merge_net(tmp_path, lanes=2)
    (tmp_path / "merge.yaml").write_text("highway: [hw_in, hw_merge, hw_out]\nramp: [ramp]\nmerge_edge: hw_merge\n"
                                         "accel_lanes: []\n")
    with pytest.raises(NetError, match="accel_lanes: name the acceleration lane"):
        load_net_description(load_roadnet(net))
