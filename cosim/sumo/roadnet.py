"""The road geometry and lane topology of a SUMO net, read once with sumolib into plain immutable data.

Contract: `load_roadnet(path)` parses a `.net.xml` once (junction-internal edges left out) and returns a
`RoadNet` that never refers back to sumolib: edge ids, per-edge lane counts and lengths, per-lane shapes
(`(K, 2)` float64 arrays in SUMO's world frame [m]), widths [m], lengths [m], speed limits [m/s] and lane
connections to the next normal edge. Junction-internal lanes (ids starting with ':', the short lanes
through a junction that SUMO's vehicles drive on between two edges) are kept apart in `internal`: each
with the normal lane it leaves and its length, so that positions stay continuous through junctions; they
are indexed after the normal edges (`index_of`). A missing, malformed or non-SUMO file raises `NetError`
naming the file. What the edges *mean* (highway, ramp, merge) is not here: see `cosim.sumo.netdesc`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from cosim.errors import NetError

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class LaneInfo:
    """One lane of a normal edge."""

    id: str  # SUMO lane id, "<edge>_<index>"
    index: int  # 0 = rightmost lane
    shape: np.ndarray  # (K, 2) float64 centre-line polyline [m], read-only
    width: float  # [m]
    length: float  # [m] along the centre line
    speed: float  # [m/s] speed limit
    successors: tuple[tuple[str, int], ...]  # (edge id, lane index) this lane connects to, through a junction


@dataclass(frozen=True, eq=False)
class EdgeInfo:
    """One normal (non-internal) edge."""

    id: str
    from_node: str
    to_node: str
    lanes: tuple[LaneInfo, ...]  # by index, rightmost first
    length: float  # [m] SUMO's edge length (its lanes' length on a straight edge)

    @property
    def num_lanes(self) -> int:
        return len(self.lanes)


@dataclass(frozen=True)
class InternalLane:
    """A junction-internal lane: the way through a junction from one normal lane to the next."""

    from_edge: str
    from_lane: int
    to_edge: str
    length: float  # [m]


@dataclass(frozen=True, eq=False)
class RoadNet:
    """All normal edges of a net, and its junction-internal lanes; build it with `load_roadnet`."""

    net_file: Path
    edge_ids: tuple[str, ...]  # sorted
    edge_index: dict[str, int]  # edge id -> position in edge_ids
    edges: dict[str, EdgeInfo]
    internal: dict[str, tuple[InternalLane, ...]]  # internal edge id (":...") -> its lanes by index

    @cached_property
    def internal_ids(self) -> tuple[str, ...]:
        """Internal edge ids, sorted: index `len(edge_ids) + k` in `index_of`."""
        return tuple(sorted(self.internal))

    @cached_property
    def index_of(self) -> dict[str, int]:
        """Edge id -> index for every edge a vehicle can be on: normal edges first, then internal ones."""
        n = len(self.edge_ids)
        return {**self.edge_index, **{e: n + k for k, e in enumerate(self.internal_ids)}}

    @cached_property
    def max_lanes(self) -> int:
        return max([e.num_lanes for e in self.edges.values()] + [len(v) for v in self.internal.values()])

    def junction_length(self, from_edge: str, to_edge: str) -> float:
        """[m] length of the way through the junction from `from_edge` to `to_edge` (0 without one)."""
        lengths = [lane.length for lanes in self.internal.values() for lane in lanes
                   if lane.from_edge == from_edge and lane.to_edge == to_edge]
        return float(max(lengths, default=0.0))

    def edge(self, edge_id: str) -> EdgeInfo:
        try:
            return self.edges[edge_id]
        except KeyError:
            raise NetError(f"net {self.net_file}: no edge {edge_id!r}") from None

    def num_lanes(self, edge_id: str) -> int:
        return self.edge(edge_id).num_lanes

    def edge_length(self, edge_id: str) -> float:
        """[m]"""
        return self.edge(edge_id).length

    def lane(self, edge_id: str, index: int) -> LaneInfo:
        lanes = self.edge(edge_id).lanes
        if not 0 <= index < len(lanes):
            raise NetError(f"net {self.net_file}: edge {edge_id!r} has no lane {index} (it has {len(lanes)})")
        return lanes[index]

    def successors(self, edge_id: str) -> tuple[str, ...]:
        """Edges that some lane of `edge_id` connects to, sorted."""
        return tuple(sorted({e for lane in self.edge(edge_id).lanes for e, _ in lane.successors}))

    def predecessors(self, edge_id: str) -> tuple[str, ...]:
        """Edges with some lane connecting to `edge_id`, sorted."""
        return tuple(e for e in self.edge_ids if edge_id in self.successors(e))

    def connections(self, from_edge: str, to_edge: str) -> tuple[tuple[int, int], ...]:
        """(from lane, to lane) pairs connecting `from_edge` to `to_edge`."""
        return tuple((lane.index, j) for lane in self.edge(from_edge).lanes
                     for e, j in lane.successors if e == to_edge)

    def lane_shapes(self) -> list[tuple[np.ndarray, float]]:
        """Every lane's centre line `(K, 2)` and width [m], by edge id then lane index (to draw the road)."""
        return [(lane.shape, lane.width) for e in self.edge_ids for lane in self.edges[e].lanes]


def load_roadnet(path: str | Path) -> RoadNet:
    """Read a SUMO `.net.xml` once; raise `NetError` naming the file if it is missing or not a SUMO net."""
    import sumolib  # imported when needed: importing cosim must not require SUMO

    net_file = Path(path)
    if not net_file.is_file():
        raise NetError(f"net file {net_file}: not found")
    try:
        net = sumolib.net.readNet(str(net_file), withInternal=True)
    except Exception as exc:  # sumolib raises SAX parse errors, KeyErrors on missing attributes, ...
        raise NetError(f"net file {net_file}: not a readable SUMO network, expected a .net.xml written by "
                       f"netconvert ({type(exc).__name__}: {exc})") from None
    edges: dict[str, EdgeInfo] = {}
    for e in net.getEdges(withInternal=False):
        if e.getFunction() == "internal" or e.getID().startswith(":"):
            continue
        lanes = tuple(_lane_info(lane) for lane in e.getLanes())
        edges[e.getID()] = EdgeInfo(e.getID(), e.getFromNode().getID(), e.getToNode().getID(), lanes,
                                    float(e.getLength()))
    if not edges:
        raise NetError(f"net file {net_file}: no edges found; expected a SUMO network (<net> with <edge> and "
                       f"<lane> elements, as written by netconvert)")
    edge_ids = tuple(sorted(edges))
    return RoadNet(net_file=net_file, edge_ids=edge_ids, edge_index={e: i for i, e in enumerate(edge_ids)},
                   edges=edges, internal=_internal_lanes(net, edges))


def _internal_lanes(net: object, edges: dict[str, EdgeInfo]) -> dict[str, tuple[InternalLane, ...]]:
    """Internal lanes reached from normal lanes through their connections' via lanes."""
    found: dict[str, dict[int, InternalLane]] = {}
    for e in edges:
        for lane in net.getEdge(e).getLanes():
            for c in lane.getOutgoing():
                via = c.getViaLaneID()
                if not via:
                    continue
                edge_id, _, index = via.rpartition("_")
                found.setdefault(edge_id, {})[int(index)] = InternalLane(
                    e, lane.getIndex(), c.getTo().getID(), float(net.getLane(via).getLength()))
    return {e: tuple(lanes[i] for i in sorted(lanes)) for e, lanes in found.items()}


def _lane_info(lane: object) -> LaneInfo:
    shape = np.asarray(lane.getShape(), dtype=np.float64)[:, :2].copy()  # drop z if the net has one
    shape.flags.writeable = False  # shared by everyone who reads the net
    successors = tuple((c.getTo().getID(), c.getToLane().getIndex()) for c in lane.getOutgoing()
                       if not c.getTo().getID().startswith(":"))
    return LaneInfo(lane.getID(), lane.getIndex(), shape, float(lane.getWidth()), float(lane.getLength()),
                    float(lane.getSpeed()), successors)
