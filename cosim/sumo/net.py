"""The net a scenario runs on, in one object: its lanes (`RoadNet`), what its edges mean (`NetDescription`)
and positions along the route (`Chainage`).

Contract: `load_net(net_file, description_file)` parses the `.net.xml` once and describes it
(`cosim.sumo.netdesc.load_net_description`: the YAML beside the net, or inferred); every question the rest of
the toolkit asks of the net's geometry goes through `Net`: highway chainage of each edge, the edge and
position at a chainage, the through lanes of an edge, the merging vehicle's target lane, and `Chainage`, one
longitudinal axis [m] through the highway and the ramp (junctions included, as SUMO's odometer counts):
highway edges at their start's distance from the first highway edge's start, ramp edges so that the ramp's
end meets the merge edge's start. `Chainage.of(snap)` is each vehicle's front bumper on that axis (NaN on
junction-internal and foreign edges). Problems raise `NetError` naming the file.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from functools import cached_property
from itertools import accumulate
from pathlib import Path

import numpy as np

from cosim.sumo.netdesc import NetDescription, load_net_description
from cosim.sumo.roadnet import RoadNet, load_roadnet
from cosim.sumo.snapshot import Snapshot


def load_net(net_file: str | Path, description_file: str | Path | None = None) -> Net:
    road = load_roadnet(net_file)
    return Net(road, load_net_description(road, description_file))


class Net:
    """A loaded net with its description; geometry is computed once per net."""

    def __init__(self, road: RoadNet, desc: NetDescription) -> None:
        self.road = road
        self.desc = desc

    @cached_property
    def chainage(self) -> Chainage:
        return Chainage.from_net(self)

    @property
    def ramp_to_accel_end(self) -> float:
        """[m] from the ramp's start to the acceleration lane's end, as a merging vehicle's odometer counts."""
        return self.chainage.merge_end - float(self.chainage.offsets[self.road.index_of[self.desc.ramp[0]]])

    @cached_property
    def highway_offsets(self) -> dict[str, float]:
        """Chainage [m] of each highway edge's start: the lengths of the edges before it and of the ways
        through the junctions between them (as SUMO's odometer counts them)."""
        steps = [self.road.edge_length(a) + self.road.junction_length(a, b)
                 for a, b in zip(self.desc.highway, self.desc.highway[1:], strict=False)]
        return dict(zip(self.desc.highway, [0.0, *accumulate(steps)], strict=True))

    @cached_property
    def highway_length(self) -> float:
        """[m] chainage of the end of the last highway edge."""
        return self.highway_offsets[self.desc.highway[-1]] + self.road.edge_length(self.desc.highway[-1])

    def highway_position(self, s: float) -> tuple[str, float]:
        """The highway edge and position on it [m] at chainage `s` [m]; ValueError outside the highway."""
        offsets = self.highway_offsets
        total = self.highway_length
        if not 0.0 <= s <= total:
            raise ValueError(f"chainage {s} m is outside the highway [0, {total:.2f}] m")
        starts = list(offsets.values())
        i = bisect.bisect_right(starts, s) - 1
        edge = self.desc.highway[i]
        return edge, min(s - starts[i], self.road.edge_length(edge))  # in a junction: the end of the edge before

    def through_lanes(self, edge: str) -> tuple[int, ...]:
        """Lane indices of `edge` that carry through traffic (all lanes but the acceleration lanes)."""
        skip = set(self.desc.accel_lanes) if edge == self.desc.merge_edge else set()
        return tuple(i for i in range(self.road.num_lanes(edge)) if i not in skip)

    def target_rank(self) -> int:
        """Rank among the merge edge's through lanes (0 = rightmost) of the lane the merging vehicle must enter:
        the through lane beside the acceleration lanes."""
        through = self.through_lanes(self.desc.merge_edge)
        beside = max(self.desc.accel_lanes) + 1
        return through.index(beside if beside in through else min(self.desc.accel_lanes) - 1)

@dataclass(frozen=True)
class Chainage:
    """Longitudinal position [m] of each edge's start on one axis through the highway and the ramp, junctions
    included (a junction-internal lane starts where the lane it leaves ends), as SUMO's odometer counts."""

    offsets: np.ndarray  # (E,) by RoadNet.index_of; NaN for edges not on the axis
    merge_start: float  # [m] chainage of the merge edge's start (where the acceleration lane begins)
    merge_end: float  # [m] ... and end
    highway_end: float  # [m] end of the last highway edge: where every route ends

    @classmethod
    def from_net(cls, net: Net) -> Chainage:
        road, desc = net.road, net.desc
        index = road.index_of
        offsets = np.full(len(index), np.nan)
        hw = net.highway_offsets
        for edge, s in hw.items():
            offsets[index[edge]] = s
        merge_start = hw[desc.merge_edge]
        s = merge_start - road.junction_length(desc.ramp[-1], desc.merge_edge)
        for i in reversed(range(len(desc.ramp))):
            edge = desc.ramp[i]
            s -= road.edge_length(edge)
            offsets[index[edge]] = s
            if i:
                s -= road.junction_length(desc.ramp[i - 1], edge)
        for edge, lanes in road.internal.items():
            before = lanes[0].from_edge
            offsets[index[edge]] = offsets[index[before]] + road.edge_length(before)
        return cls(offsets, merge_start, merge_start + road.edge_length(desc.merge_edge),
                   net.highway_length)

    def of(self, snap: Snapshot) -> np.ndarray:
        """(V,) front-bumper chainage [m] (SUMO's lane position is the front bumper's)."""
        edge = snap.edge
        known = edge >= 0
        out = np.full(len(snap), np.nan)
        out[known] = self.offsets[edge[known]] + snap.lane_pos[known]
        return out


