"""SUMO's own outputs for traffic-engineering figures: induction loops and tripinfo, written and parsed.

Contract:
- `detector_site(net, offset)`: induction loops on every lane of the last highway edge, `offset` [m]
  past its start (clipped into the edge), placed from the net description, never from edge ids in code.
- `episode_folder(root, seed, busy)` names an episode's folder: `root/episode_{seed}`, or
  `root/episode_{seed}_1` when that is `busy`, the previous episode's folder (a reset with the same seed
  again): SUMO opens the new files at the reload, before the previous episode's are parsed, and must not
  truncate them.
- `episode_output_args(folder, site)` writes `folder/detectors.add.xml` and returns the SUMO options that
  make one episode write `folder/tripinfo.xml` (unfinished and undeparted vehicles included, so a
  time-limited episode reports every vehicle) and `folder/detectors.xml`. SUMO completes these files only
  when the simulation is reloaded or closed; parse them after that.
- `read_episode_outputs(folder, duration)` parses both files into `SumoOutputs` over the window [0,
  duration] [s] (the env runs every episode to the same window): throughput past the detector [veh/h] =
  vehicles entering any loop / duration, mean time loss and speed over all trips (an
  unfinished trip counts up to the window's end, waiting to enter counts as lost, a removed wreck stands
  until the end: `read_tripinfo`), and each vehicle's driven distance (tripinfo routeLength, which equals
  SUMO's odometer) for cross-checks. Missing or truncated files raise `SimulationError` naming the file.
- With a `safety` section whose `ssm` is on, `episode_output_args` also equips every vehicle with SUMO's SSM device
  (`ssm_args`: time to collision, deceleration rate to avoid a crash, post-encroachment time, with the section's
  thresholds; `folder/ssm.xml`), and `read_episode_outputs(..., safety, until)` counts its conflicts up to time
  `until` [s] (the episode's end: after it SUMO drives the AVs and the wrecks stand, `cosim.environment.merge_env`)
  into `SumoOutputs.safety` (`conflict_counts`). `read_ssm(path)` gives each conflict once (`Conflict`): SUMO logs
  an encounter from both vehicles, ego and foe swapped; records of one pair whose times overlap are one conflict.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.config import SafetyConfig
from cosim.errors import SimulationError
from cosim.files import atomic_write_text
from cosim.sumo.net import Net
from cosim.sumo.scenario import kind_of
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER

TRIPINFO_FILE = "tripinfo.xml"
DETECTOR_FILE = "detectors.xml"
ADDITIONAL_FILE = "detectors.add.xml"
SSM_FILE = "ssm.xml"


@dataclass(frozen=True)
class DetectorSite:
    edge: str  # the last highway edge
    lanes: tuple[str, ...]  # lane ids, one loop each
    pos: float  # [m] from the edge's start


def detector_site(net: Net, offset: float) -> DetectorSite:
    road = net.road
    edge = net.desc.highway[-1]
    length = road.edge_length(edge)
    pos = min(max(offset, 0.0), max(length - 0.5, 0.0))
    lanes = tuple(lane.id for lane in road.edge(edge).lanes)
    return DetectorSite(edge, lanes, pos)


def episode_folder(root: Path, seed: int, busy: Path | None = None) -> Path:
    """The output folder of an episode with `seed`, never `busy` (the previous episode's, not yet parsed)."""
    folder = root / f"episode_{seed}"
    return folder if folder != busy else root / f"episode_{seed}_1"


def episode_output_args(folder: Path, site: DetectorSite, period: float = 1e6,
                        safety: SafetyConfig | None = None) -> list[str]:
    """SUMO options for one episode's outputs in `folder` (created); one aggregation interval by default; the SSM
    device's too where `safety.ssm` is on."""
    folder.mkdir(parents=True, exist_ok=True)
    loops = "".join(
        f'    <inductionLoop id="loop_{i}" lane="{lane}" pos="{site.pos:.2f}" period="{period:g}" '
        f'file="{DETECTOR_FILE}"/>\n' for i, lane in enumerate(site.lanes))
    additional = folder / ADDITIONAL_FILE
    atomic_write_text(additional, f"<additional>\n{loops}</additional>\n")  # a failed write names the file
    return ["--additional-files", str(additional),
            "--tripinfo-output", str(folder / TRIPINFO_FILE),
            "--tripinfo-output.write-unfinished", "true",
            "--tripinfo-output.write-undeparted", "true",
            *(ssm_args(folder, safety) if safety is not None and safety.ssm else ())]


def ssm_args(folder: Path, safety: SafetyConfig) -> list[str]:
    """SUMO's SSM device in every vehicle, logging into `folder/ssm.xml` the conflicts in which TTC falls below,
    DRAC rises above or PET falls below the section's thresholds, each with its worst value (no trajectories)."""
    return ["--device.ssm.probability", "1", "--device.ssm.measures", "TTC DRAC PET",
            "--device.ssm.thresholds", f"{safety.ttc:g} {safety.drac:g} {safety.pet:g}",
            "--device.ssm.file", str(folder / SSM_FILE)]


@dataclass(frozen=True)
class SumoOutputs:
    detector_count: int  # vehicles that entered a loop
    throughput_vph: float  # [veh/h] detector_count over the episode's duration
    time_loss: float  # [s] mean time lost against driving at the desired speed
    mean_speed: float  # [m/s] mean over trips of distance driven / time in the window
    n_trips: int
    distance: dict[str, float] = field(default_factory=dict)  # [m] routeLength by vehicle id
    safety: dict[str, float] = field(default_factory=dict)  # conflict_counts, where the SSM device was on

    def as_row(self) -> dict[str, float | int]:
        return {"throughput_vph": self.throughput_vph, "detector_count": self.detector_count,
                "time_loss": self.time_loss, "window_speed": self.mean_speed,
                "n_trips": self.n_trips, **self.safety}


def _parse(path: Path) -> ET.Element:
    if not path.is_file():
        raise SimulationError(f"SUMO output {path}: not found (SUMO writes it when the simulation is "
                              f"reloaded or closed)")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SimulationError(f"SUMO output {path}: incomplete or not XML ({exc}); SUMO completes it only "
                              f"at the next reset or close") from None


def read_detectors(path: Path) -> int:
    """Vehicles that entered any loop, summed over loops and intervals."""
    return sum(int(float(iv.get("nVehEntered", "0"))) for iv in _parse(path).iter("interval"))


def read_tripinfo(path: Path, end: float) -> list[dict[str, float | str]]:
    """Trips of every vehicle, undeparted and unfinished ones included. Travel time and time loss include the
    time a vehicle waited to enter the road (SUMO's departDelay: a backlog at the entry is lost time too). A
    vehicle taken off the road (SUMO's `vaporized`, e.g. a removed wreck) counts as standing until `end` [s]:
    its trip would otherwise end early and improve the mean time loss and speed by the crash."""
    trips = []
    for t in _parse(path).iter("tripinfo"):
        delay = float(t.get("departDelay", "0"))
        duration, loss = float(t.get("duration", "nan")) + delay, float(t.get("timeLoss", "nan")) + delay
        arrival = float(t.get("arrival", "-1"))
        if t.get("vaporized") and 0 <= arrival < end:
            duration, loss = duration + end - arrival, loss + end - arrival
        trips.append({"id": t.get("id", ""), "duration": duration, "time_loss": loss,
                      "route_length": float(t.get("routeLength", "nan"))})
    return trips


@dataclass(frozen=True)
class Conflict:
    """One conflict of the SSM device: the two vehicles, when, and each measure's worst value with its time [s]
    (NaN where SUMO had none: a PET needs crossing paths)."""

    ego: str
    foe: str
    begin: float  # [s]
    end: float  # [s]
    ttc: float  # [s] minimum time to collision
    ttc_time: float
    drac: float  # [m/s^2] maximum deceleration rate to avoid a crash
    drac_time: float
    pet: float  # [s] post-encroachment time
    pet_time: float

    def vehicles(self) -> tuple[str, str]:
        return self.ego, self.foe


# SSM element -> (Conflict field, the worse of two values, the episode's column of its worst value)
_MEASURES = {"minTTC": ("ttc", min, "min_ttc"), "maxDRAC": ("drac", max, "max_drac"), "PET": ("pet", min, "min_pet")}


def _number(text: str | None) -> float:
    return math.nan if text in (None, "NA") else float(text)


def read_ssm(path: Path) -> list[Conflict]:
    """Each conflict of an SSM output file once, in order of begin (module doc)."""
    records = []
    for c in _parse(path).iter("conflict"):
        worst: dict[str, float] = {}
        for tag, (name, _, _) in _MEASURES.items():
            e = c.find(tag)
            worst[name] = math.nan if e is None else _number(e.get("value"))
            worst[f"{name}_time"] = math.nan if e is None else _number(e.get("time"))
        records.append(Conflict(c.get("ego", ""), c.get("foe", ""), float(c.get("begin", "nan")),
                                float(c.get("end", "nan")), **worst))
    records.sort(key=lambda r: (sorted(r.vehicles()), r.begin))
    merged: list[Conflict] = []
    for r in records:
        last = merged[-1] if merged else None
        if last is not None and sorted(last.vehicles()) == sorted(r.vehicles()) and r.begin <= last.end:
            merged[-1] = _worse(last, r)
        else:
            merged.append(r)
    return sorted(merged, key=lambda r: r.begin)


def _worse(a: Conflict, b: Conflict) -> Conflict:
    """One conflict from two records of a pair: the longer span, each measure's worse value and its time."""
    values: dict[str, float] = {}
    for name, worse, _ in _MEASURES.values():
        known = [c for c in (a, b) if not math.isnan(getattr(c, name))] or [a]
        pick = worse(known, key=lambda c: getattr(c, name))
        values[name], values[f"{name}_time"] = getattr(pick, name), getattr(pick, f"{name}_time")
    return Conflict(a.ego, a.foe, min(a.begin, b.begin), max(a.end, b.end), **values)


def conflict_counts(conflicts: list[Conflict], safety: SafetyConfig, until: float,
                    since: float = -math.inf) -> dict[str, float]:
    """The conflicts whose worst value passed its threshold between `since` and `until` [s]: in all, by measure,
    with an AV, with the merging vehicle (any ramp vehicle under demand); and the worst TTC, DRAC and PET among them
    (NaN: none)."""
    limits = {"ttc": safety.ttc, "drac": safety.drac, "pet": safety.pet}
    counts = dict.fromkeys(("conflicts", *(f"conflicts_{m}" for m in limits), "conflicts_av", "conflicts_merger"),
                           0.0)
    worst = {column: math.nan for _, _, column in _MEASURES.values()}
    for c in conflicts:
        hits = [(name, worse, column) for name, worse, column in _MEASURES.values()
                if since <= getattr(c, f"{name}_time") <= until  # NaN (no value) compares False
                and (getattr(c, name) < limits[name] if worse is min else getattr(c, name) > limits[name])]
        if not hits:
            continue
        counts["conflicts"] += 1
        kinds = {kind_of(v) for v in c.vehicles()}
        counts["conflicts_av"] += KIND_AV in kinds
        counts["conflicts_merger"] += KIND_MERGER in kinds
        for name, worse, column in hits:
            counts[f"conflicts_{name}"] += 1
            worst[column] = getattr(c, name) if math.isnan(worst[column]) else worse(worst[column], getattr(c, name))
    return {**counts, **worst}


def read_episode_outputs(folder: Path, duration: float, safety: SafetyConfig | None = None,
                         until: float | None = None) -> SumoOutputs:
    """Parse one episode's complete output files; `duration` [s] is the simulated time they cover; with `safety`
    (its `ssm` on) the SSM device's conflicts up to `until` [s] (default: `duration`) too."""
    count = read_detectors(folder / DETECTOR_FILE)
    trips = read_tripinfo(folder / TRIPINFO_FILE, duration)

    def mean(key: str) -> float:
        values = [float(t[key]) for t in trips]
        return sum(values) / len(values) if values else math.nan

    return SumoOutputs(
        detector_count=count,
        throughput_vph=count * 3600.0 / duration if duration > 0 else math.nan,
        time_loss=mean("time_loss"),
        mean_speed=float(np.mean([t["route_length"] / t["duration"] for t in trips if t["duration"] > 0]))
        if any(t["duration"] > 0 for t in trips) else math.nan,
        n_trips=len(trips),
        distance={str(t["id"]): float(t["route_length"]) for t in trips},
        safety=conflict_counts(read_ssm(folder / SSM_FILE), safety, duration if until is None else until)
        if safety is not None and safety.ssm else {},
    )
