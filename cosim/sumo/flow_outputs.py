"""SUMO's outputs over a demand run's measurement window: the detectors it writes and what they measured.

Contract:
- `flow_sites(net, influence_area)` -> `FlowSites`, placed from the net description: an instant induction loop on
  every lane of the first highway edge past the acceleration lane, `EXIT_POS` into it (each vehicle leaving the
  merge area, with its id, so by origin: ramp or mainline); a lane-area detector along each ramp lane into its
  acceleration lane (the ramp queue: SUMO's jam length along the lane chain); lane-area detectors over the HCM
  merge influence area (the acceleration lanes and the two right through lanes, from the acceleration lane's
  start `influence_area` metres downstream, along the lanes' connections); and an edgeData over the window.
- `flow_output_args(folder, sites, warmup, horizon, interval, safety)` writes `folder/flow.add.xml` and returns
  SUMO's options for it and for tripinfo (unfinished and undeparted trips included); with a `safety` section whose
  `ssm` is on, SUMO's SSM device in every vehicle too (`cosim.sumo.outputs.ssm_args`).
- `read_flow_outputs(folder, warmup, horizon, end, ssm)` -> `FlowOutputs` over the window [warmup, horizon] [s]: the
  loops' passages, the detectors' intervals that lie in the window, the edgeData totals, every trip, and with `ssm`
  every conflict of the run (`read_ssm`). SUMO completes the files at close or reload; a missing or truncated one
  raises `SimulationError` naming it.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from cosim.config import SafetyConfig
from cosim.errors import SimulationError
from cosim.files import atomic_write_text
from cosim.sumo.net import Net
from cosim.sumo.outputs import SSM_FILE, Conflict, read_ssm, ssm_args

ADDITIONAL = "flow.add.xml"
PASSAGES, AREAS, EDGES, TRIPS = "passages.xml", "areas.xml", "edges.xml", "tripinfo.xml"
EXIT_POS = 5.0  # [m] into the edge past the acceleration lane: every vehicle that left the merge area crosses it


@dataclass(frozen=True)
class Area:
    """A lane-area detector along consecutive lanes."""

    did: str
    lanes: tuple[str, ...]  # lane ids, consecutive along connections
    end_pos: float  # [m] on the last lane
    length: float  # [m] covered


@dataclass(frozen=True)
class FlowSites:
    exit_lanes: tuple[str, ...]  # lane ids with an instant loop
    queues: tuple[Area, ...]  # one per ramp lane, into its acceleration lane
    influence: tuple[Area, ...]  # the merge influence area, one per lane


def _chain_down(net: Net, edge: str, lane: int, length: float) -> tuple[tuple[str, ...], float, float]:
    """Lane ids from (edge, lane) downstream along the highway's connections, `length` [m] of them (less where
    the net ends first): (lanes, position on the last, length covered)."""
    road, hw = net.road, net.desc.highway
    lanes, left = [], length
    while True:
        lane_len = road.lane(edge, lane).length
        lanes.append(road.lane(edge, lane).id)
        if left <= lane_len:
            return tuple(lanes), left, length
        left -= lane_len
        k = hw.index(edge) + 1 if edge in hw else len(hw)
        nxt = [j for e, j in road.lane(edge, lane).successors if k < len(hw) and e == hw[k]]
        if not nxt:
            return tuple(lanes), lane_len, length - left
        edge, lane = hw[k], nxt[0]


def flow_sites(net: Net, influence_area: float) -> FlowSites:
    road, desc = net.road, net.desc
    k = desc.highway.index(desc.merge_edge)
    if k + 1 >= len(desc.highway):
        raise SimulationError(f"net {road.net_file}: no highway edge after the merge edge {desc.merge_edge!r} to count "
                              "the traffic leaving the merge area on")
    exit_edge = desc.highway[k + 1]
    exits = tuple(lane.id for lane in road.edge(exit_edge).lanes)
    queues = []
    for i in desc.accel_lanes:
        chain = [road.lane(desc.merge_edge, i).id]
        edge, lane = desc.merge_edge, i
        for r in reversed(desc.ramp):  # up the ramp along the connections into this acceleration lane
            feeding = [a for a, b in road.connections(r, edge) if b == lane]
            if not feeding:
                break
            edge, lane = r, feeding[0]
            chain.insert(0, road.lane(edge, lane).id)
        length = sum(road.lane(*_split(lid)).length for lid in chain)
        queues.append(Area(f"queue_{i}", tuple(chain), road.lane(desc.merge_edge, i).length, length))
    through = net.through_lanes(desc.merge_edge)
    starts = [*desc.accel_lanes, *through[:2]]  # the acceleration lanes and the two right through lanes
    influence = []
    for i in starts:
        lanes, end, length = _chain_down(net, desc.merge_edge, i, influence_area)
        influence.append(Area(f"area_{i}", lanes, end, length))
    return FlowSites(exits, tuple(queues), tuple(influence))


def _split(lane_id: str) -> tuple[str, int]:
    edge, _, index = lane_id.rpartition("_")
    return edge, int(index)


def flow_output_args(folder: Path, sites: FlowSites, warmup: float, horizon: float, interval: float,
                     safety: SafetyConfig | None = None) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    lines = [f'  <instantInductionLoop id="exit_{k}" lane="{lane}" pos="{EXIT_POS}" file="{PASSAGES}"/>'
             for k, lane in enumerate(sites.exit_lanes)]
    lines += [f'  <laneAreaDetector id="{a.did}" lanes="{" ".join(a.lanes)}" pos="0" endPos="{a.end_pos:.2f}" '
              f'period="{interval:g}" file="{AREAS}"/>' for a in (*sites.queues, *sites.influence)]
    lines.append(f'  <edgeData id="window" file="{EDGES}" begin="{warmup:g}" end="{horizon:g}" withInternal="true" '
                 'excludeEmpty="true"/>')
    additional = folder / ADDITIONAL
    atomic_write_text(additional, "<additional>\n" + "\n".join(lines) + "\n</additional>\n")
    return ["--additional-files", str(additional), "--tripinfo-output", str(folder / TRIPS),
            "--tripinfo-output.write-unfinished", "true", "--tripinfo-output.write-undeparted", "true",
            *(ssm_args(folder, safety) if safety is not None and safety.ssm else ())]


@dataclass(frozen=True)
class Trip:
    vid: str
    intended: float  # [s] when it wanted to enter
    departed: bool
    depart_delay: float  # [s] waiting to enter (so far, for an undeparted one)
    time_loss: float  # [s] lost against driving at its desired speed, in the network
    distance: float  # [m] driven


@dataclass
class FlowOutputs:
    passages: list[tuple[float, str]] = field(default_factory=list)  # (time [s], vehicle) leaving the merge area
    intervals: dict[str, list[dict[str, float]]] = field(default_factory=dict)  # detector -> its window intervals
    time_spent: float = 0.0  # [s] vehicle-seconds in the network over the window (edgeData sampledSeconds)
    trips: list[Trip] = field(default_factory=list)
    conflicts: list[Conflict] | None = None  # the run's, where the SSM device rode (read_ssm)


def _root(path: Path) -> ET.Element:
    if not path.is_file():
        raise SimulationError(f"SUMO output {path}: not found (SUMO writes it when the simulation is reloaded or "
                              "closed)")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SimulationError(f"SUMO output {path}: incomplete or not XML ({exc})") from None


def read_flow_outputs(folder: Path, warmup: float, horizon: float, end: float | None = None,
                      ssm: bool = False) -> FlowOutputs:
    """`end`: the simulation's last time [s] (a step past `horizon` where the run began a step in), from which
    an undeparted vehicle's waiting is counted back to when it wanted to enter."""
    out = FlowOutputs()
    for e in _root(folder / PASSAGES).iter("instantOut"):
        t = float(e.get("time", "nan"))
        if e.get("state") == "enter" and warmup <= t < horizon:
            out.passages.append((t, e.get("vehID", "")))
    for e in _root(folder / AREAS).iter("interval"):
        begin, end = float(e.get("begin", "nan")), float(e.get("end", "nan"))
        if begin >= warmup - 1e-6 and end <= horizon + 1e-6:
            out.intervals.setdefault(e.get("id", ""), []).append(
                {k: float(v) for k, v in e.attrib.items() if k != "id"})
    for e in _root(folder / EDGES).iter("edge"):
        out.time_spent += float(e.get("sampledSeconds", "0"))
    for t in _root(folder / TRIPS).iter("tripinfo"):
        depart, delay = float(t.get("depart", "-1")), float(t.get("departDelay", "0"))
        departed = depart >= 0
        # An undeparted vehicle's departDelay runs to the simulation's end: it wanted to enter that long before.
        intended = (depart if departed else (horizon if end is None else end)) - delay
        out.trips.append(Trip(t.get("id", ""), intended, departed, delay, float(t.get("timeLoss", "0")),
                              float(t.get("routeLength", "0")) if departed else 0.0))
    if ssm:
        out.conflicts = read_ssm(folder / SSM_FILE)
    return out
