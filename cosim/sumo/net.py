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
from typing import Any

import numpy as np

from cosim.files import file_sha256
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
        """Lane indices of highway edge `edge` that carry through traffic: all lanes but the acceleration lanes
        and lanes that end there (a lane drop: no connection onward to the next highway edge)."""
        return self._through[edge]

    @cached_property
    def _through(self) -> dict[str, tuple[int, ...]]:
        hw, road = self.desc.highway, self.road
        out = {}
        for k, edge in enumerate(hw):
            skip = set(self.desc.accel_lanes) if edge == self.desc.merge_edge else set()
            onward = {i for i, _ in road.connections(edge, hw[k + 1])} if k + 1 < len(hw) else None
            out[edge] = tuple(i for i in range(road.num_lanes(edge))
                              if i not in skip and (onward is None or i in onward))
        return out

    @cached_property
    def speed_limit(self) -> float:
        """[m/s] the highway's speed limit where it matters: that of the lane the merging vehicle must enter, on
        the merge edge (net-relative speeds are factors of it, cosim.sumo.resolve)."""
        edge = self.desc.merge_edge
        return self.road.lane(edge, self.through_lanes(edge)[self.target_rank()]).speed

    @cached_property
    def ramp_speed_limit(self) -> float:
        """[m/s] the lowest speed limit along the ramp (the merging vehicle's speeds are factors of it)."""
        return min(lane.speed for e in self.desc.ramp for lane in self.road.edge(e).lanes)

    @cached_property
    def accel_length(self) -> float:
        """[m] length of the acceleration lane (the shortest, where there are several)."""
        return min(self.road.lane(self.desc.merge_edge, i).length for i in self.desc.accel_lanes)

    @cached_property
    def ramp_offsets(self) -> dict[str, float]:
        """Chainage [m] of each ramp edge's start on the axis of `chainage` (negative far up a long ramp)."""
        index = self.road.index_of
        return {e: float(self.chainage.offsets[index[e]]) for e in self.desc.ramp}

    def ramp_position(self, before: float) -> tuple[int, float, float]:
        """Where a vehicle `before` [m] ahead of the acceleration lane's start is on the ramp: (index into
        desc.ramp, position on that edge [m], the distance actually left [m]), capped at the ramp's start; a
        point inside a junction between two ramp edges is taken at the end of the edge before it."""
        s = self.chainage.merge_start - before
        starts = list(self.ramp_offsets.values())
        if s <= starts[0]:
            return 0, 0.0, self.chainage.merge_start - starts[0]
        i = bisect.bisect_right(starts, s) - 1
        edge = self.desc.ramp[i]
        pos = min(s - starts[i], self.road.edge_length(edge))
        return i, pos, self.chainage.merge_start - starts[i] - pos

    def lane_breaks(self, rank: int, until: str | None = None) -> list[str]:
        """Where through lane `rank` of the highway (up to edge `until`) does not run on into the same rank of the
        next edge: one line per break, naming the edges and lanes (a lane drops, or the lanes shift)."""
        hw, road = self.desc.highway, self.road
        hw = hw[: hw.index(until) + 1] if until is not None else hw
        breaks = []
        for a, b in zip(hw, hw[1:], strict=False):
            la, lb = self.through_lanes(a), self.through_lanes(b)
            if rank >= len(la) or rank >= len(lb):
                continue
            if (la[rank], lb[rank]) not in road.connections(a, b):
                breaks.append(f"lane {la[rank]} of edge {a!r} does not lead to lane {lb[rank]} of {b!r}")
        return breaks

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




def net_summary(net: Net) -> dict[str, Any]:
    """What a traffic engineer asks of the net first, as plain data (JSON-ready): its file and sha256, where the
    roles came from (the description file, or what the inference read), the highway edge by edge (lanes, through
    lanes, length, speed limit), the approach and what follows the merge, the ramp, the acceleration lane and
    the lane the merging vehicle must enter."""
    road, desc = net.road, net.desc

    def edge(e: str) -> dict[str, Any]:
        lanes = road.edge(e).lanes
        return {"id": e, "lanes": len(lanes), "length_m": round(road.edge_length(e), 1),
                "speed_limits_kmh": sorted({round(lane.speed * 3.6) for lane in lanes})}

    highway = [{**edge(e), "through_lanes": len(net.through_lanes(e))} for e in desc.highway]
    chain = net.chainage
    return {
        "file": str(road.net_file), "sha256": file_sha256(road.net_file),
        "description": desc.source, "roles": dict(desc.reasons),
        "highway": highway, "merge_edge": desc.merge_edge,
        "approach_m": round(chain.merge_start, 1), "after_merge_m": round(chain.highway_end - chain.merge_end, 1),
        "ramp": [edge(e) for e in desc.ramp],
        "ramp_to_accel_lane_m": round(chain.merge_start - net.ramp_offsets[desc.ramp[0]], 1),
        "accel_lanes": list(desc.accel_lanes), "accel_length_m": round(net.accel_length, 1),
        "target_lane": net.through_lanes(desc.merge_edge)[net.target_rank()],
        "speed_limit_kmh": round(net.speed_limit * 3.6, 1),
        "ramp_speed_limit_kmh": round(net.ramp_speed_limit * 3.6, 1),
    }


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """`net_summary` as a few lines of text (also Markdown list items)."""

    def edges(items: list[dict[str, Any]]) -> str:
        return " -> ".join(f"{e['id']} ({e['lanes']} lane{'s' * (e['lanes'] != 1)}, {e['length_m']:g} m, "
                           f"{'/'.join(map(str, e['speed_limits_kmh']))} km/h)" for e in items)

    lines = [f"net {summary['file']} (sha256 {summary['sha256'][:12]})",
             f"highway: {edges(summary['highway'])}",
             f"approach {summary['approach_m']:g} m before the merge edge {summary['merge_edge']!r}, "
             f"{summary['after_merge_m']:g} m after the acceleration lane",
             f"ramp: {edges(summary['ramp'])}; {summary['ramp_to_accel_lane_m']:g} m to the acceleration lane",
             f"acceleration lane(s) {summary['accel_lanes']} of {summary['merge_edge']!r}: "
             f"{summary['accel_length_m']:g} m; the merging vehicle enters lane {summary['target_lane']} (speed limit "
             f"{summary['speed_limit_kmh']:g} km/h there, {summary['ramp_speed_limit_kmh']:g} km/h on the ramp)"]
    source = summary["description"]
    if source == "inferred":
        lines += [f"{role} (inferred): {why}" for role, why in summary["roles"].items()]
    else:
        lines.append(f"roles from {source}")
    return lines
