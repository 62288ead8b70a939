"""Builder of the on-ramp merge network: plain XML sources -> netconvert -> `.net.xml` + description YAML.

Contract: `build_merge_net(out_dir, ...)` writes `NAME.nod.xml`, `NAME.edg.xml`, `NAME.con.xml`,
`NAME.net.xml` and `NAME.yaml` (the net description read by `cosim.sumo.netdesc`) into `out_dir` and returns
the `.net.xml` path.
Bad parameters and a failing netconvert raise `cosim.errors.NetError` with a message naming the parameter or
netconvert's stderr. `add_arguments` / `run` are the `cosim build-net` command.

Geometry (metres, SUMO world frame, no offset normalisation so positions match the node file):

    x = 0          U              U+A                        U+A+D
    hw_in  ------> hw_merge -----> hw_out ------------------->        highway, top border at y = 0
    (L lanes)      (L+1 lanes)     (L lanes)
                 /  lane 0 = acceleration lane, no connection onward (lane drop)
          ramp  /   1 lane, straight diagonal from below (the right side in driving direction)

Lanes are spread to the right of the edge line (SUMO's default), so highway lane i of hw_in lines up with
lane i+1 of hw_merge and lane i of hw_out, and the ramp's centre line ends on hw_merge lane 0's centre line.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

from cosim.errors import NetError

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

    def __post_init__(self) -> None:
        if isinstance(self.lanes, bool) or not isinstance(self.lanes, int) or self.lanes < 1:
            raise NetError(f"merge net: lanes must be an integer >= 1, got {self.lanes!r}")
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
) -> Path:
    """Write the merge net's sources, run netconvert and write the description; return the `.net.xml` path."""
    geom = MergeGeometry(lanes, upstream_length, accel_length, ramp_length, downstream_length,
                         highway_speed, ramp_speed, lane_width, name)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NetError(f"merge net: cannot create output folder {out_dir}: {exc}") from None
    (out_dir / f"{name}.nod.xml").write_text(_nodes_xml(geom))
    (out_dir / f"{name}.edg.xml").write_text(_edges_xml(geom))
    (out_dir / f"{name}.con.xml").write_text(_connections_xml(geom))
    net_file = run_netconvert(out_dir, name)
    (out_dir / f"{name}.yaml").write_text(_description_yaml(geom))
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
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-10:])
        raise NetError(f"netconvert failed on {out_dir / name}.*.xml (exit {proc.returncode}):\n{tail}")
    if proc.stderr.strip():
        log.debug("netconvert: %s", proc.stderr.strip())
    return net_file


def _nodes_xml(g: MergeGeometry) -> str:
    merge_x = g.upstream_length
    drop_x = merge_x + g.accel_length
    end_x = drop_x + g.downstream_length
    rx, ry = _ramp_start(g)
    rows = [
        ("hw_start", 0.0, 0.0, "priority"),
        ("merge", merge_x, 0.0, "priority"),
        ("drop", drop_x, 0.0, "priority"),
        ("hw_end", end_x, 0.0, "priority"),
        ("ramp_start", rx, ry, "priority"),
    ]
    lines = [f'    <node id="{i}" x="{x:.2f}" y="{y:.2f}" type="{t}" radius="{JUNCTION_RADIUS}"/>'
             for i, x, y, t in rows]
    return _xml("nodes", "nodes_file", lines)


def _ramp_start(g: MergeGeometry) -> tuple[float, float]:
    end_x, end_y = g.upstream_length, _accel_lane_y(g)
    a = math.radians(RAMP_ANGLE_DEG)
    return end_x - g.ramp_length * math.cos(a), end_y - g.ramp_length * math.sin(a)


def _accel_lane_y(g: MergeGeometry) -> float:
    # Centre of hw_merge lane 0: below the lanes+1 lanes hanging right of the edge line at y = 0.
    return -(g.lanes + 0.5) * g.lane_width


def _edges_xml(g: MergeGeometry) -> str:
    rx, ry = _ramp_start(g)
    hw = f'speed="{g.highway_speed:.2f}" width="{g.lane_width:.2f}" priority="{HIGHWAY_PRIORITY}"'
    lines = [
        f'    <edge id="hw_in" from="hw_start" to="merge" numLanes="{g.lanes}" {hw}/>',
        f'    <edge id="hw_merge" from="merge" to="drop" numLanes="{g.lanes + 1}" {hw}/>',
        f'    <edge id="hw_out" from="drop" to="hw_end" numLanes="{g.lanes}" {hw}/>',
        # spreadType center + explicit shape: the ramp's lane centre runs exactly onto lane 0's centre line.
        f'    <edge id="ramp" from="ramp_start" to="merge" numLanes="1" speed="{g.ramp_speed:.2f}" '
        f'width="{g.lane_width:.2f}" priority="{RAMP_PRIORITY}" spreadType="center" '
        f'shape="{rx:.2f},{ry:.2f} {g.upstream_length:.2f},{_accel_lane_y(g):.2f}"/>',
    ]
    return _xml("edges", "edges_file", lines)


def _connections_xml(g: MergeGeometry) -> str:
    lines = [f'    <connection from="hw_in" to="hw_merge" fromLane="{i}" toLane="{i + 1}"/>'
             for i in range(g.lanes)]
    lines.append('    <connection from="ramp" to="hw_merge" fromLane="0" toLane="0"/>')
    # hw_merge lane 0 gets no connection: the acceleration lane ends (lane drop).
    lines += [f'    <connection from="hw_merge" to="hw_out" fromLane="{i + 1}" toLane="{i}"/>'
              for i in range(g.lanes)]
    return _xml("connections", "connections_file", lines)


def _xml(root: str, schema: str, lines: list[str]) -> str:
    head = (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<{root} xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
            f'xsi:noNamespaceSchemaLocation="http://sumo.dlr.de/xsd/{schema}.xsd">\n')
    return head + "\n".join(lines) + f"\n</{root}>\n"


def _description_yaml(g: MergeGeometry) -> str:
    return (
        f"# Net description for {g.name}.net.xml: which edges are what.\n"
        "highway: [hw_in, hw_merge, hw_out]\n"
        "ramp: [ramp]\n"
        "merge_edge: hw_merge\n"
        "accel_lanes: [0]\n"
    )
