"""Merge nets of the usual shapes, for the tests and for trying a policy on nets it never saw (scripts/transfer.py).

Contract: `SHAPES` maps a name to `sumo_net.build.build_merge_net`'s shape parameters (the highway and the ramp in
several edges, a curve, a 2-lane ramp, a lane drop after the merge, 60 to 130 km/h highways with 40 to 80 km/h
ramps, OSM-style ids, a 1-lane highway); `build_shape(name, out_dir)` builds one with netconvert (node, edge and
connection files, then the net and its description YAML) and returns the `.net.xml` path.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cosim.errors import NetError
from sumo_net.build import build_merge_net

SHAPES: dict[str, dict[str, Any]] = {
    # the approach in 3 edges, a ramp of 2 edges, 2 edges after the merge; 120 / 80 km/h
    "multi_edge": dict(lanes=2, upstream_length=500, upstream_edges=3, ramp_length=240, ramp_edges=2,
                       downstream_edges=2, downstream_length=600),
    # a 3-lane highway bending left on a 600 m radius, names of one's own; 100 / 60 km/h
    "curved": dict(lanes=3, upstream_length=400, curve_radius=600, highway_speed=27.78, ramp_speed=16.67,
                   ids={"ramp": "slip_road", "hw_in": "main_a", "hw_merge": "main_b", "hw_out": "main_c"}),
    # a 2-lane ramp into two acceleration lanes; 130 / 80 km/h
    "two_lane_ramp": dict(lanes=2, upstream_length=450, ramp_lanes=2, highway_speed=36.11, ramp_speed=22.22),
    # 3 lanes, the left one ending after the merge; 60 / 40 km/h
    "lane_drop": dict(lanes=3, upstream_length=300, downstream_edges=2, lane_drop=True, highway_speed=16.67,
                      ramp_speed=11.11),
    # OSM's ids (way -4711 in pieces, way 88 for the ramp), a 1-lane highway; 80 / 50 km/h
    "osm_ids": dict(lanes=1, upstream_length=350, upstream_edges=2, highway_speed=22.22, ramp_speed=13.89,
                    ids={"hw_in_0": "-4711#0", "hw_in_1": "-4711#1", "hw_merge": "-4711#2", "hw_out": "-4711#3",
                         "ramp": "88#1"}),
    # what `cosim build-net --lanes 1` builds: a 1-lane highway with a 120 m approach
    "one_lane": dict(lanes=1),
}


def build_shape(name: str, out_dir: Path) -> Path:
    if name not in SHAPES:
        raise NetError(f"net shape {name!r}: unknown; expected one of {sorted(SHAPES)}")
    return build_merge_net(out_dir, name=name, **SHAPES[name])
