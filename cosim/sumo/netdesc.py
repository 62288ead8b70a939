"""What the edges of a merge net mean: highway chain, on-ramp, merge edge and its acceleration lanes.

Contract: `load_net_description(roadnet, description_file)` returns a validated `NetDescription`. With a file
it reads that YAML; without one it reads `<net stem>.yaml` beside the net if present, else infers the
description from the net's lane topology (logged once per net and process, as the file that would make it
explicit: `description_yaml`). Every edge id, lane index and chainage used elsewhere in the
toolkit comes from here, never from code. Problems raise `NetError` naming the file and the key:
a missing file, unknown or missing keys, an edge not in the net, a lane index out of range, a merge edge not
on the highway, edges that are not connected in the stated order, or a net whose merge cannot be inferred.

YAML format (as written by `sumo_net.build`):

    highway: [hw_in, hw_merge, hw_out]   # upstream -> downstream, includes the merge edge
    ramp: [ramp]                         # upstream -> downstream, its last edge feeds the merge edge
    merge_edge: hw_merge
    accel_lanes: [0]                     # lanes of merge_edge that end (not through lanes)
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from cosim.config import yaml_problem
from cosim.errors import NetError
from cosim.sumo.roadnet import RoadNet

log = logging.getLogger(__name__)

KEYS = ("highway", "ramp", "merge_edge", "accel_lanes")
_INFERRED_LOGGED: set[Path] = set()  # nets whose inferred description this process has logged
# One line (YAML flow style), so that every error about a description stays one line.
EXAMPLE_YAML = "{highway: [hw_in, hw_merge, hw_out], ramp: [ramp], merge_edge: hw_merge, accel_lanes: [0]}"


@dataclass(frozen=True)
class NetDescription:
    highway: tuple[str, ...]  # highway edges, upstream -> downstream, including merge_edge
    ramp: tuple[str, ...]  # ramp edges, upstream -> downstream, the last one feeding merge_edge
    merge_edge: str  # the highway edge the ramp joins
    accel_lanes: tuple[int, ...]  # lane indices of merge_edge that are not through lanes
    source: str  # the description file's path, or "inferred"
    # Where each role came from: the file, or the topology that the inference read (role -> one line).
    reasons: Mapping[str, str] = field(default_factory=dict, compare=False)


def load_net_description(roadnet: RoadNet, description_file: str | Path | None = None) -> NetDescription:
    """Describe `roadnet`: from `description_file`, else `<net stem>.yaml` beside the net, else inferred."""
    if description_file is not None:
        path = Path(description_file)
        if not path.is_file():
            raise NetError(f"net description {path}: not found")
        return _from_yaml(roadnet, path)
    stem = roadnet.net_file.name.removesuffix(".gz").removesuffix(".xml").removesuffix(".net")
    beside = roadnet.net_file.with_name(f"{stem}.yaml")
    if beside.is_file():
        return _from_yaml(roadnet, beside)
    desc = infer_net_description(roadnet)
    # Once per net and process: every env, resolution and plot of a run loads the net again.
    if roadnet.net_file.resolve() not in _INFERRED_LOGGED:
        _INFERRED_LOGGED.add(roadnet.net_file.resolve())
        log.info("net %s: no description file; inferred %s (write it to %s beside the net to make it explicit)",
                 roadnet.net_file, description_yaml(desc), beside.name)
    return desc


def description_yaml(desc: NetDescription) -> str:
    """`desc` as a description file holds it, on one line (YAML flow style)."""
    return yaml.safe_dump({"highway": list(desc.highway), "ramp": list(desc.ramp), "merge_edge": desc.merge_edge,
                           "accel_lanes": list(desc.accel_lanes)}, default_flow_style=True, sort_keys=False,
                          width=10**6).strip()


def _from_yaml(roadnet: RoadNet, path: Path) -> NetDescription:
    where = f"net description {path}"
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise NetError(f"{where}: not readable ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise NetError(f"{where}: not valid YAML: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise NetError(f"{where}: expected a mapping with keys {list(KEYS)}, e.g. {EXAMPLE_YAML}")
    for key in data:
        if key not in KEYS:
            raise NetError(f"{where}: unknown key {key!r}; expected {list(KEYS)}")
    for key in KEYS:
        if key not in data:
            raise NetError(f"{where}: missing key {key!r}; expected {list(KEYS)}")
    highway = _edge_list(data, "highway", where)
    ramp = _edge_list(data, "ramp", where)
    merge_edge = data["merge_edge"]
    if not isinstance(merge_edge, str):
        raise NetError(f"{where}: key merge_edge: expected an edge id, got {merge_edge!r}")
    lanes = data["accel_lanes"]
    if not isinstance(lanes, list) or any(isinstance(i, bool) or not isinstance(i, int) for i in lanes):
        raise NetError(f"{where}: key accel_lanes: expected a list of lane indices, got {lanes!r}")
    desc = NetDescription(tuple(highway), tuple(ramp), merge_edge, tuple(sorted(set(lanes))), str(path),
                          dict.fromkeys(KEYS, f"from {path}"))
    validate(roadnet, desc)
    return desc


def _edge_list(data: dict[str, Any], key: str, where: str) -> list[str]:
    value = data[key]
    if not isinstance(value, list) or not value or not all(isinstance(e, str) for e in value):
        raise NetError(f"{where}: key {key}: expected a non-empty list of edge ids, got {value!r}")
    return value


def validate(roadnet: RoadNet, desc: NetDescription) -> None:
    """Check `desc` against the net; raise `NetError` naming the key at fault."""
    where = f"net description {desc.source}"
    net = roadnet.net_file
    for key, edges in (("highway", desc.highway), ("ramp", desc.ramp), ("merge_edge", (desc.merge_edge,))):
        for e in edges:
            if e not in roadnet.edges:
                raise NetError(f"{where}: edge {e!r} (key {key}) does not exist in {net}; edges are: "
                               f"{', '.join(roadnet.edge_ids)}")
    if len(set(desc.highway)) != len(desc.highway) or set(desc.highway) & set(desc.ramp):
        raise NetError(f"{where}: keys highway and ramp must list distinct edges, each once")
    if desc.merge_edge not in desc.highway:
        raise NetError(f"{where}: merge_edge {desc.merge_edge!r} is not in highway {list(desc.highway)}")
    n = roadnet.num_lanes(desc.merge_edge)
    if not desc.accel_lanes:  # the merge is defined by leaving them: without one there is none
        raise NetError(f"{where}: key accel_lanes: name the acceleration lane(s) of {desc.merge_edge!r}, "
                       "the lanes the merging vehicle must leave")
    for i in desc.accel_lanes:
        if not 0 <= i < n:
            raise NetError(f"{where}: key accel_lanes: lane {i} out of range; {desc.merge_edge!r} has lanes "
                           f"0..{n - 1}")
    if len(desc.accel_lanes) >= n:
        raise NetError(f"{where}: key accel_lanes: leaves no through lane on {desc.merge_edge!r}")
    for key, chain in (("highway", desc.highway), ("ramp", (*desc.ramp, desc.merge_edge))):
        for a, b in zip(chain, chain[1:], strict=False):
            if b not in roadnet.successors(a):
                raise NetError(f"{where}: key {key}: edge {a!r} has no connection to {b!r} in {net}")


def infer_net_description(roadnet: RoadNet) -> NetDescription:
    """Find the on-ramp merge from the lane topology alone; raise `NetError` (one line, with a YAML example) when
    there is none or several.

    The merge edge has two predecessors or more; the ramp is the one whose lanes all lead into lanes of the merge
    edge that end there (no connection onward while its other lanes have one: the acceleration lanes), while
    another predecessor, the highway, feeds lanes that go on; or, where no lane ends, a narrower predecessor
    whose lanes only it feeds. Ramps of any number of lanes; the highway is followed up- and downstream along
    the most connected lanes, the ramp upstream over edges no wider than its last one.
    """
    found = []
    for m in roadnet.edge_ids:
        preds = roadnet.predecessors(m)
        if len(preds) < 2 or roadnet.num_lanes(m) < 2:
            continue
        ends = _dropped_lanes(roadnet, m)
        for r in preds:
            others = [h for h in preds if h != r]
            ramp_targets = {j for _, j in roadnet.connections(r, m)}
            fed_by_others = {j for h in others for _, j in roadnet.connections(h, m)}
            if not ramp_targets or not fed_by_others - ends:
                continue
            if ends and ramp_targets <= ends:
                accel = sorted(ramp_targets)
                why = (f"every lane of {r!r} leads into a lane of {m!r} that ends there (lane(s) {accel}), while "
                       f"{', '.join(map(repr, others))} feed(s) lanes that go on")
            elif (not ramp_targets & fed_by_others
                  and roadnet.num_lanes(r) < max(roadnet.num_lanes(h) for h in others)):
                accel = sorted(ramp_targets)
                why = f"{r!r} is narrower than {', '.join(map(repr, others))} and alone feeds lane(s) {accel} of {m!r}"
            else:
                continue
            found.append((m, r, others, tuple(accel), why))
    if len(found) != 1:
        what = "none" if not found else ", ".join(f"ramp {r!r} -> {m!r}" for m, r, *_ in found)
        raise NetError(
            f"net {roadnet.net_file}: cannot infer the on-ramp merge: looked for an edge joining the highway whose "
            f"lanes all lead into lanes that end (an acceleration lane), found {what}. Write a description YAML "
            f"beside the net ({_stem_yaml(roadnet)}) or set net.description, with keys {', '.join(KEYS)}, e.g. "
            f"{EXAMPLE_YAML}")
    m, r, others, accel, why = found[0]
    upstream = max(others, key=lambda h: (len(roadnet.connections(h, m)), h))
    highway = [*reversed(_chain(roadnet, upstream, upstream=True)), m]
    desc_m = NetDescription((), (), m, accel, "inferred")
    highway += _chain(roadnet, m, upstream=False, through=desc_m)[1:]
    ramp = list(reversed(_chain(roadnet, r, upstream=True, max_lanes=roadnet.num_lanes(r))))
    reasons = {
        "highway": f"{len(highway)} edge(s) along the most connected lanes up from {upstream!r} and down from {m!r}",
        "ramp": f"{len(ramp)} edge(s) up from {r!r} over edges no wider than it; {why}",
        "merge_edge": f"{m!r}, where the ramp joins",
        "accel_lanes": f"lane(s) {list(accel)} of {m!r}: the ramp's lanes lead into them and they end there",
    }
    desc = NetDescription(tuple(highway), tuple(ramp), m, accel, "inferred", reasons)
    validate(roadnet, desc)
    return desc


def _stem_yaml(roadnet: RoadNet) -> str:
    return roadnet.net_file.name.removesuffix(".gz").removesuffix(".xml").removesuffix(".net") + ".yaml"


def _dropped_lanes(roadnet: RoadNet, edge: str) -> set[int]:
    """Lanes of `edge` with no connection onward while another lane of it has one (a lane drop)."""
    lanes = roadnet.edge(edge).lanes
    if not any(lane.successors for lane in lanes):
        return set()  # the end of the net, not a lane drop
    return {lane.index for lane in lanes if not lane.successors}


def _chain(roadnet: RoadNet, start: str, *, upstream: bool, max_lanes: int | None = None,
           through: NetDescription | None = None) -> list[str]:
    """Edges from `start` following the strongest connection up- or downstream, `start` first."""
    chain, seen = [start], {start}
    while True:
        cur = chain[-1]
        if upstream:
            # The predecessor with the most lanes connecting into `cur` (the highway beats a joining ramp).
            cands = [(len(roadnet.connections(p, cur)), p) for p in roadnet.predecessors(cur)]
        else:
            # Through lanes only: the acceleration lanes end (`through` is the description found so far).
            skip = set(through.accel_lanes) if through and cur == through.merge_edge else set()
            lanes = [i for i in range(roadnet.num_lanes(cur)) if i not in skip]
            counts: dict[str, int] = {}
            for i in lanes:
                for e, _ in roadnet.lane(cur, i).successors:
                    counts[e] = counts.get(e, 0) + 1
            cands = [(c, e) for e, c in counts.items()]
        cands = [(c, e) for c, e in cands if e not in seen and (max_lanes is None or roadnet.num_lanes(e) <= max_lanes)]
        if not cands:
            return chain
        cands.sort(reverse=True)
        if len(cands) > 1 and cands[0][0] == cands[1][0]:
            log.warning("net %s: %s of %r is ambiguous (%s); stopping there", roadnet.net_file,
                        "upstream" if upstream else "downstream", cur, [e for _, e in cands])
            return chain
        chain.append(cands[0][1])
        seen.add(cands[0][1])
