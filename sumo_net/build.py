"""Builder of the on-ramp merge network: plain XML sources -> netconvert -> `.net.xml` + description YAML.

Contract: `build_merge_net(out_dir, ...)` writes `NAME.nod.xml`, `NAME.edg.xml`, `NAME.con.xml`,
`NAME.net.xml` and `NAME.yaml` (the net description read by `cosim.sumo.netdesc`) into `out_dir` and returns
the `.net.xml` path.
Bad parameters and a failing netconvert raise `cosim.errors.NetError` with a message naming the parameter or
netconvert's stderr. `add_arguments` / `run` are the `cosim build-net` command.

Geometry (metres, SUMO world frame, no offset normalisation so positions match the node file), by default:

    x = 0          U              U+A                        U+A+D
    hw_in  ------> hw_merge -----> hw_out ------------------->        highway, top border at y = 0
    (L lanes)      (L+R lanes)     (L lanes)
                 /  lanes 0..R-1 = acceleration lanes, no connection onward (lane drop)
          ramp  /   R lanes, straight diagonal from below (the right side in driving direction)

Lanes are spread to the right of the edge line (SUMO's default), so highway lane i of hw_in lines up with
lane i+R of hw_merge and lane i of hw_out, and the ramp's centre line ends on the centre of the acceleration
lanes. Other shapes of the usual kinds, for nets like a user's: the approach, the ramp and the road after the
merge split into several edges (`hw_in_0, hw_in_1, ...`, `ramp_0, ...`, `hw_out_0, ...`), a highway that bends
left on a radius (`curve_radius`; the ramp still joins from the right), a ramp of several lanes, the leftmost
lane ending after the first edge past the merge (`lane_drop`), and edge ids of one's own (`ids`, e.g. OSM's
`-4711#0`).
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from cosim.errors import NetError
from cosim.files import atomic_write_text

log = logging.getLogger(__name__)

# The ramp approaches at this angle to the highway: gentle enough that the short internal lane joining it to
# the acceleration lane has no sharp kink, steep enough that the ramp start stays clear of the highway.
RAMP_ANGLE_DEG = 12.0
# Small junctions: netconvert's default radius (4 m) makes the lane-drop junction 8 m long, which would
# shorten the acceleration lane by that much.
JUNCTION_RADIUS = 0.5
# Shorter, and a 5 m car at ramp speed has no room to find a gap and change lanes: no merge is possible.
MIN_ACCEL_LENGTH = 20.0  # [m]
HIGHWAY_PRIORITY = 3
RAMP_PRIORITY = 1
CURVE_STEP = 20.0  # [m] between two shape points of a curved edge


@dataclass(frozen=True)
class MergeGeometry:
    """Parameters of the merge net, validated at construction."""

    lanes: int = 3  # through lanes of the highway
    upstream_length: float = 120.0  # [m] hw_in
    accel_length: float = 120.0  # [m] hw_merge, i.e. the acceleration lane
    ramp_length: float = 120.0  # [m] ramp (approximately: the diagonal's length)
    downstream_length: float = 900.0  # [m] hw_out
    highway_speed: float = 33.33  # [m/s] speed limit of the highway edges
    ramp_speed: float = 22.22  # [m/s] speed limit of the ramp
    lane_width: float = 3.2  # [m]
    name: str = "merge"  # file stem of every output
    ramp_lanes: int = 1  # lanes of the ramp, each leading into an acceleration lane of its own
    upstream_edges: int = 1  # edges the approach is split into
    ramp_edges: int = 1
    downstream_edges: int = 1
    lane_drop: bool = False  # the leftmost lane ends at the end of the first edge past the merge
    curve_radius: float = 0.0  # [m] the highway bends left on this radius; 0: straight
    ids: Mapping[str, str] = field(default_factory=dict)  # edge id -> the id to write instead

    def __post_init__(self) -> None:
        for key in ("lanes", "ramp_lanes", "upstream_edges", "ramp_edges", "downstream_edges"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise NetError(f"merge net: {key} must be an integer >= 1, got {value!r}")
        for key in ("upstream_length", "accel_length", "ramp_length", "downstream_length",
                    "highway_speed", "ramp_speed", "lane_width"):
            value = getattr(self, key)
            if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise NetError(f"merge net: {key} must be a positive number, got {value!r}")
        if self.accel_length < MIN_ACCEL_LENGTH:
            raise NetError(f"merge net: accel_length must be at least {MIN_ACCEL_LENGTH:g} m, or no vehicle can merge "
                           f"from the ramp, got {self.accel_length!r}")
        if not self.name or any(c in self.name for c in "/\\") or self.name.startswith("."):
            raise NetError(f"merge net: name must be a plain file stem, got {self.name!r}")
        if self.lane_drop and (self.lanes < 2 or self.downstream_edges < 2):
            raise NetError("merge net: lane_drop needs lanes >= 2 and downstream_edges >= 2 (the lane ends at the end "
                           "of the first edge past the merge)")
        if self.curve_radius and (not math.isfinite(self.curve_radius) or self.curve_radius < 50.0):
            raise NetError(f"merge net: curve_radius must be 0 (straight) or at least 50 m, got {self.curve_radius!r}")

    def edge_names(self) -> dict[str, list[str]]:
        """Edge ids by role, upstream to downstream, as written (after `ids`)."""

        def split(base: str, n: int) -> list[str]:
            return [base] if n == 1 else [f"{base}_{k}" for k in range(n)]

        names = {"upstream": split("hw_in", self.upstream_edges), "merge": ["hw_merge"],
                 "downstream": split("hw_out", self.downstream_edges), "ramp": split("ramp", self.ramp_edges)}
        return {role: [self.ids.get(e, e) for e in edges] for role, edges in names.items()}


def build_merge_net(
    out_dir: Path,
    *,
    lanes: int = 3,
    upstream_length: float = 120.0,
    accel_length: float = 120.0,
    ramp_length: float = 120.0,
    downstream_length: float = 900.0,
    highway_speed: float = 33.33,
    ramp_speed: float = 22.22,
    lane_width: float = 3.2,
    name: str = "merge",
    **shape: object,
) -> Path:
    """Write the merge net's sources, run netconvert and write the description; return the `.net.xml` path.
    `shape`: MergeGeometry's other fields (ramp_lanes, upstream_edges, ramp_edges, downstream_edges, lane_drop,
    curve_radius, ids)."""
    unknown = set(shape) - set(MergeGeometry.__dataclass_fields__)
    if unknown:
        raise NetError(f"merge net: unknown parameter(s) {sorted(unknown)}")
    geom = MergeGeometry(lanes, upstream_length, accel_length, ramp_length, downstream_length,
                         highway_speed, ramp_speed, lane_width, name, **shape)  # type: ignore[arg-type]
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NetError(f"merge net: cannot create output folder {out_dir}: {exc}") from None
    atomic_write_text(out_dir / f"{name}.nod.xml", _nodes_xml(geom))
    atomic_write_text(out_dir / f"{name}.edg.xml", _edges_xml(geom))
    atomic_write_text(out_dir / f"{name}.con.xml", _connections_xml(geom))
    net_file = run_netconvert(out_dir, name)
    atomic_write_text(out_dir / f"{name}.yaml", _description_yaml(geom))
    log.debug("built %s (%d+1 lanes, acceleration lane %.0f m)", net_file, lanes, accel_length)
    return net_file


def run_netconvert(out_dir: Path, name: str) -> Path:
    """Run netconvert on `NAME.{nod,edg,con}.xml` in `out_dir`, writing `NAME.net.xml`; return its path."""
    import sumolib  # here, not at module level: importing this module must not need SUMO

    if not os.environ.get("SUMO_HOME"):
        import sumo  # the eclipse-sumo package knows where its data (XML schemas) lives

        os.environ["SUMO_HOME"] = sumo.SUMO_HOME
    cmd = [
        sumolib.checkBinary("netconvert"),
        "--node-files", f"{name}.nod.xml",
        "--edge-files", f"{name}.edg.xml",
        "--connection-files", f"{name}.con.xml",
        "--output-file", f"{name}.net.xml",
        "--offset.disable-normalization", "true",  # keep the node file's coordinates
        "--no-turnarounds", "true",
        "--no-internal-links", "false",  # internal lanes make the junction crossing continuous
    ]
    net_file = Path(out_dir) / f"{name}.net.xml"
    net_file.unlink(missing_ok=True)  # a failed run must not leave an older net looking like its output
    # cwd=out_dir with relative names: the net's header then records no machine-specific paths.
    try:
        proc = subprocess.run(cmd, cwd=out_dir, capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetError(f"netconvert for {out_dir / name}: could not run ({exc})") from None
    if proc.returncode != 0 or not net_file.is_file():
        net_file.unlink(missing_ok=True)  # what a failed run wrote (a full disk) is no net
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-10:])
        raise NetError(f"netconvert failed on {out_dir / name}.*.xml (exit {proc.returncode}):\n{tail}")
    if proc.stderr.strip():
        log.debug("netconvert: %s", proc.stderr.strip())
    return net_file


def _centre(g: MergeGeometry, c: float) -> tuple[float, float, float]:
    """(x, y, heading [rad]) of the highway's edge line at chainage `c` [m]."""
    if not g.curve_radius:
        return c, 0.0, 0.0
    r, th = g.curve_radius, c / g.curve_radius
    return r * math.sin(th), r * (1.0 - math.cos(th)), th


def _chainages(g: MergeGeometry) -> dict[str, float]:
    """Chainage [m] of every highway node, by node id, upstream to downstream."""
    u, a, d = g.upstream_length, g.accel_length, g.downstream_length
    nodes = {"hw_start": 0.0}
    nodes.update({f"up_{k}": u * k / g.upstream_edges for k in range(1, g.upstream_edges)})
    nodes["merge"], nodes["drop"] = u, u + a
    nodes.update({f"down_{k}": u + a + d * k / g.downstream_edges for k in range(1, g.downstream_edges)})
    nodes["hw_end"] = u + a + d
    return nodes


def _ramp_point(g: MergeGeometry, back: float) -> tuple[float, float]:
    """The ramp's centre line `back` [m] before its end, which lies on the acceleration lanes' centre."""
    x, y, th = _centre(g, g.upstream_length)
    off = (g.lanes + 0.5 * g.ramp_lanes) * g.lane_width  # right of the edge line
    ex, ey = x + off * math.sin(th), y - off * math.cos(th)
    a = th + math.radians(RAMP_ANGLE_DEG)
    return ex - back * math.cos(a), ey - back * math.sin(a)


def _ramp_nodes(g: MergeGeometry) -> list[tuple[str, float, float]]:
    """The ramp's nodes before the merge node, upstream first."""
    out = []
    for k in range(g.ramp_edges):
        x, y = _ramp_point(g, g.ramp_length * (1.0 - k / g.ramp_edges))
        out.append(("ramp_start" if k == 0 else f"ramp_{k}", x, y))
    return out


def _nodes_xml(g: MergeGeometry) -> str:
    rows = [(i, *_centre(g, c)[:2]) for i, c in _chainages(g).items()] + _ramp_nodes(g)
    lines = [f'    <node id="{i}" x="{x:.2f}" y="{y:.2f}" type="priority" radius="{JUNCTION_RADIUS}"/>'
             for i, x, y in rows]
    return _xml("nodes", "nodes_file", lines)


def _shape(g: MergeGeometry, c0: float, c1: float) -> str:
    """` shape="..."` following the curve from chainage c0 to c1; nothing on a straight highway."""
    if not g.curve_radius:
        return ""
    n = max(2, math.ceil((c1 - c0) / CURVE_STEP) + 1)
    points = (_centre(g, c0 + (c1 - c0) * k / (n - 1)) for k in range(n))
    return ' shape="' + " ".join(f"{x:.2f},{y:.2f}" for x, y, _ in points) + '"'


def _highway_edges(g: MergeGeometry) -> list[tuple[str, str, str, int]]:
    """(edge id, from node, to node, lanes) of the highway, upstream to downstream."""
    names, nodes = g.edge_names(), list(_chainages(g))
    edges = [*names["upstream"], *names["merge"], *names["downstream"]]
    lanes = [g.lanes] * len(names["upstream"]) + [g.lanes + g.ramp_lanes] + [g.lanes] * len(names["downstream"])
    if g.lane_drop:
        for k in range(len(names["upstream"]) + 2, len(edges)):
            lanes[k] = g.lanes - 1
    return list(zip(edges, nodes[:-1], nodes[1:], lanes, strict=True))


def _edges_xml(g: MergeGeometry) -> str:
    hw = f'speed="{g.highway_speed:.2f}" width="{g.lane_width:.2f}" priority="{HIGHWAY_PRIORITY}"'
    chain = _chainages(g)
    lines = [f'    <edge id="{e}" from="{a}" to="{b}" numLanes="{n}" {hw}{_shape(g, chain[a], chain[b])}/>'
             for e, a, b, n in _highway_edges(g)]
    ramp = f'speed="{g.ramp_speed:.2f}" width="{g.lane_width:.2f}" priority="{RAMP_PRIORITY}" spreadType="center"'
    nodes = _ramp_nodes(g)
    for k, e in enumerate(g.edge_names()["ramp"]):
        start, x0, y0 = nodes[k]
        if k + 1 < len(nodes):
            lines.append(f'    <edge id="{e}" from="{start}" to="{nodes[k + 1][0]}" numLanes="{g.ramp_lanes}" {ramp}/>')
        else:
            # The last edge's explicit shape ends exactly on the acceleration lanes' centre line.
            ex, ey = _ramp_point(g, 0.0)
            lines.append(f'    <edge id="{e}" from="{start}" to="merge" numLanes="{g.ramp_lanes}" {ramp} '
                         f'shape="{x0:.2f},{y0:.2f} {ex:.2f},{ey:.2f}"/>')
    return _xml("edges", "edges_file", lines)


def _connections_xml(g: MergeGeometry) -> str:
    names = g.edge_names()
    hw = _highway_edges(g)
    merge = len(names["upstream"])
    r = g.ramp_lanes
    lines = []
    for k, ((a, _, _, na), (b, _, _, nb)) in enumerate(zip(hw, hw[1:], strict=False)):
        if k + 1 == merge:  # into the merge edge: lanes i -> i + R; the ramp takes 0..R-1
            pairs = [(i, i + r) for i in range(na)]
        elif k == merge:  # out of it: the acceleration lanes 0..R-1 get no connection (they end)
            pairs = [(i + r, i) for i in range(nb)]
        else:  # lane i goes on as lane i; a lane with none onward ends (lane_drop)
            pairs = [(i, i) for i in range(min(na, nb))]
        lines += [f'    <connection from="{a}" to="{b}" fromLane="{i}" toLane="{j}"/>' for i, j in pairs]
        if k + 1 == merge:
            ramp = names["ramp"]
            lines += [f'    <connection from="{x}" to="{y}" fromLane="{i}" toLane="{i}"/>'
                      for x, y in zip(ramp, ramp[1:], strict=False) for i in range(r)]
            lines += [f'    <connection from="{ramp[-1]}" to="{b}" fromLane="{i}" toLane="{i}"/>' for i in range(r)]
    return _xml("connections", "connections_file", lines)


def _xml(root: str, schema: str, lines: list[str]) -> str:
    head = (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<{root} xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
            f'xsi:noNamespaceSchemaLocation="http://sumo.dlr.de/xsd/{schema}.xsd">\n')
    return head + "\n".join(lines) + f"\n</{root}>\n"


def _description_yaml(g: MergeGeometry) -> str:
    names = g.edge_names()
    highway = [*names["upstream"], *names["merge"], *names["downstream"]]

    def flow(ids: list[str]) -> str:
        return "[" + ", ".join(ids if all(i.replace("_", "").isalnum() for i in ids) else map(repr, ids)) + "]"

    return (
        f"# Net description for {g.name}.net.xml: which edges are what.\n"
        f"highway: {flow(highway)}\n"
        f"ramp: {flow(names['ramp'])}\n"
        f"merge_edge: {flow(names['merge'])[1:-1]}\n"
        f"accel_lanes: [{', '.join(str(i) for i in range(g.ramp_lanes))}]\n"
    )
