"""The vehicles of one episode: a seeded plan, and the SUMO route file that realises it.

Contract: `plan_episode(cfg, net, seed)` is a pure function of its inputs (same seed, same plan); the
config's `scenario.placement` picks the rule from `PLACEMENTS`:
- `window` (free flow): N AVs and M HVs interleaved on the highway's through lanes upstream of the merge,
  with randomised gaps and speeds.
- `stream` (the merge dilemma): a dense stream in the lane the merging vehicle must enter (the through
  lane beside the acceleration lane). Its first vehicle drives at the stream's speed; behind it every
  vehicle sits at an IDM driver's equilibrium gap at that speed (times a spacing factor), so the stream
  neither brakes nor thins out on its own, back to `place_from`, and a flow at the highway's start continues
  it at its mean spacing. AVs take stream slots, one of them timed to reach the merge edge just after the
  merging vehicle (the guide AV, who can open a gap), and start a little off the stream's speed. The head
  moves downstream where a short highway has no room for the AVs. `n_hvs` more HVs go on the other through
  lanes by the window rule.
The merging vehicle starts on the ramp at a random position and speed; `scenario.inflow` adds a random flow
of HVs. `write_episode(plan, cfg, desc, path)` writes vTypes, routes, vehicles and flows as one `.rou.xml`
that SUMO loads at reset; every placed vehicle departs at t = 0 with SUMO's insertion checks off so that
the plan is realised exactly. Each HV has a vType
of its own (headway, imperfection, desired speed), so HVs differ as the config asks.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from cosim.config import Config, DriverConfig
from cosim.errors import ConfigError
from cosim.files import scratch_write_text
from cosim.sumo.net import Net
from cosim.sumo.netdesc import NetDescription
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER

MERGER_ID = "merger"


def av_id(i: int) -> str:
    return f"av_{i}"


def kind_of(vid: str) -> int:
    """Vehicle class from its id: ours are `av_*` and `merger` (`merger_K`: the ramp's vehicles in demand mode);
    anything else (inflow, user routes) is an HV."""
    if vid == MERGER_ID or vid.startswith(MERGER_ID + "_"):
        return KIND_MERGER
    return KIND_AV if vid.startswith("av_") else KIND_HV


@dataclass(frozen=True)
class Flow:
    """HVs entering a route's first edge during the episode (a SUMO flow of one vType), from the first decision
    step to the horizon: every `period` [s], or with `probability` per second."""

    fid: str
    route: str
    lane: int | str  # lane index, or SUMO's "best"
    speed: float | str  # [m/s] at entry, or SUMO's "desired"
    period: float | None = None
    probability: float | None = None
    tau: float = 1.0  # [s]
    speed_factor: float = 1.0


@dataclass(frozen=True)
class Plan:
    vehicles: list[Spawn]  # sorted by route, then downstream first, so SUMO inserts leaders first
    flows: list[Flow]


@dataclass(frozen=True)
class Spawn:
    vid: str
    kind: int
    route: str  # route id in the episode file
    lane: int
    pos: float  # [m] front bumper on the route's first edge
    speed: float  # [m/s]
    tau: float = 1.0  # [s] (HVs)
    sigma: float = 0.0  # [-] (HVs)
    speed_factor: float = 1.0  # [-] desired speed / speed limit (HVs)
    max_speed: float | None = None  # [m/s] caps the desired speed (a stream's first vehicle); None: the driver's
    alt: bool = False  # the merging vehicle drives the config's merger_alt type (scenario.merger_alt_share)


def route_ids(desc: NetDescription) -> dict[str, tuple[str, ...]]:
    """One route per possible start edge: on the highway, and on the ramp through the merge edge onwards."""
    hw = desc.highway
    on = hw[hw.index(desc.merge_edge):]
    return {**{f"hw_{i}": hw[i:] for i in range(len(hw))},
            **{f"ramp_{i}": desc.ramp[i:] + on for i in range(len(desc.ramp))}}


def idm_gap(speed: float, desired: float, tau: float, min_gap: float) -> float:
    """[m] bumper-to-bumper gap at which an IDM driver (exponent 4) holds `speed` behind a leader at that
    speed: (s0 + v T) / sqrt(1 - (v / v0)^4), kept finite for a desired speed at or below `speed`."""
    return (min_gap + speed * tau) / math.sqrt(max(1.0 - (speed / desired) ** 4, 0.1))


class _Planner:
    """Shared state of one plan: the seeded RNG, the net's highway axis and the spawns made so far."""

    def __init__(self, cfg: Config, net: Net, seed: int) -> None:
        self.cfg, self.net, self.desc, self.road = cfg, net, net.desc, net.road
        self.rng = np.random.default_rng(seed)
        self.length = net.highway_length
        self.hw_index = {edge: i for i, edge in enumerate(net.desc.highway)}
        self.n_lanes = min(len(net.through_lanes(e)) for e in net.desc.highway)
        self.merge_start = net.highway_offsets[net.desc.merge_edge]
        self.plan: list[Spawn] = []
        self.flows: list[Flow] = []
        self.n_av = self.n_hv = 0

    def uniform(self, bounds: tuple[float, float]) -> float:
        return float(self.rng.uniform(*bounds))

    def add(self, kind: int, s: float, rank: int, speed: float, **driver: float) -> None:
        """A vehicle whose front bumper is at chainage `s` [m] in the `rank`-th through lane."""
        edge, pos = self.net.highway_position(s)
        lane = self.net.through_lanes(edge)[rank]
        route = f"hw_{self.hw_index[edge]}"
        limit = self.road.lane(edge, lane).speed
        if kind == KIND_AV:
            vid, self.n_av = av_id(self.n_av), self.n_av + 1
            # The AV's vType has speedFactor 1: SUMO refuses a departure above the lane's limit.
            self.plan.append(Spawn(vid, KIND_AV, route, lane, pos, min(speed, limit)))
        else:
            vid, self.n_hv = f"hv_{self.n_hv}", self.n_hv + 1
            hv = self.cfg.hv
            driver = {"tau": self.uniform(hv.tau_range), "sigma": self.uniform(hv.sigma_range),
                      "speed_factor": self.uniform(hv.speed_factor), **driver}
            # Never faster than the driver wants to go there: SUMO refuses such a departure.
            top = min(driver["speed_factor"] * limit, driver.get("max_speed") or hv.max_speed)
            self.plan.append(Spawn(vid, KIND_HV, route, lane, pos, min(speed, top), **driver))

    def window(self, ranks: list[int], n_avs: int, n_hvs: int) -> None:
        """`n_avs + n_hvs` vehicles in slots spread over the lanes `ranks` of [place_from, place_to]."""
        sc = self.cfg.scenario
        rng = self.rng
        n_total = n_avs + n_hvs
        if n_total == 0:
            return
        # Slots per lane: front-to-front spacing drawn from [min_gap, max_gap], so lanes are staggered.
        slots: list[tuple[float, int]] = []
        for rank in ranks:
            s = sc.place_from + rng.uniform(0.0, sc.min_gap)
            while s <= sc.place_to:
                slots.append((s, rank))
                s += rng.uniform(sc.min_gap, sc.max_gap)
        if len(slots) < n_total:
            raise ConfigError(
                f"scenario: {n_total} vehicles do not fit in [place_from, place_to] = [{sc.place_from}, "
                f"{sc.place_to}] m on {len(ranks)} lane(s) with min_gap {sc.min_gap} m; about {len(slots)} fit: "
                "lower the counts (n_avs, n_hvs) or widen the window")
        chosen = rng.choice(len(slots), size=n_total, replace=False)
        # A random permutation of AV and HV labels over the chosen slots interleaves the classes.
        is_av = np.zeros(n_total, dtype=bool)
        is_av[rng.choice(n_total, size=n_avs, replace=False)] = True
        # Factors of each vehicle's own lane's limit, or m/s.
        speeds = rng.uniform(*(sc.speed_range_factor or sc.speed_range), size=n_total)
        for k, slot in enumerate(chosen):
            s, rank = slots[slot]
            scale = 1.0 if sc.speed_range_factor is None else self.lane_limit(s, rank)
            self.add(KIND_AV if is_av[k] else KIND_HV, s, rank, float(speeds[k]) * scale)

    def lane_limit(self, s: float, rank: int) -> float:
        """[m/s] speed limit of through lane `rank` at chainage `s`."""
        edge, _ = self.net.highway_position(s)
        return self.road.lane(edge, self.net.through_lanes(edge)[rank]).speed

    def merger(self) -> float:
        """Place the merging vehicle on the ramp (`merger_time`, `merger_distance` or `merger_pos`, capped at the
        ramp's start); returns the time [s] it needs to the merge edge at its initial speed."""
        sc, net = self.cfg.scenario, self.net
        ramp = net.desc.ramp
        speed = self.uniform(sc.merger_speed)
        if sc.merger_pos is not None:
            k, pos = 0, self.uniform(sc.merger_pos)
            left = net.chainage.merge_start - net.ramp_offsets[ramp[0]] - pos
        else:
            before = self.uniform(sc.merger_distance) if sc.merger_distance is not None else (
                self.uniform(sc.merger_time) * speed)
            k, pos, left = net.ramp_position(before)
        lanes = self.road.num_lanes(ramp[k])
        lane = lanes - 1 if sc.merger_lane is None else min(sc.merger_lane, lanes - 1)
        # Drawn only where asked, so that every other config keeps its episodes' random streams.
        alt = sc.merger_alt_share > 0 and bool(self.rng.random() < sc.merger_alt_share)
        m = self.cfg.merger_driver(alt)
        tau, sigma, factor = self.uniform(m.tau_range), self.uniform(m.sigma_range), self.uniform(m.speed_factor)
        # SUMO refuses a departure above the lane's limit x the driver's speed factor (or its top speed).
        speed = min(speed, self.road.lane(ramp[k], lane).speed * factor, m.max_speed)
        self.plan.append(Spawn(MERGER_ID, KIND_MERGER, f"ramp_{k}", lane, pos, speed, tau, sigma, factor, alt=alt))
        return left / max(speed, 0.1)


def _place_window(p: _Planner) -> None:
    sc = p.cfg.scenario
    p.window(list(range(p.n_lanes)), sc.n_avs, sc.n_hvs)
    p.merger()


def _place_stream(p: _Planner) -> None:
    sc, hv, desc, road = p.cfg.scenario, p.cfg.hv, p.desc, p.road
    rank = p.net.target_rank()
    if rank >= p.n_lanes:
        raise ConfigError(f"scenario.placement stream: the lane beside the acceleration lane is not a through lane "
                          f"of every highway edge in {road.net_file}")
    breaks = p.net.lane_breaks(rank, until=desc.merge_edge)
    if breaks:
        raise ConfigError(f"scenario.placement stream: the stream's lane (through lane {rank} from the right, the "
                          f"one the merging vehicle enters) does not run through to the merge in {road.net_file}: "
                          f"{breaks[0]}; use placement window, or a net whose lane runs through")
    merger_time = p.merger()
    speed = p.uniform(sc.stream_speed)
    limit = road.lane(desc.merge_edge, p.net.through_lanes(desc.merge_edge)[rank]).speed
    # Followers of the stream's first vehicle, front to back: (tau, speed factor, front-to-front spacing [m]).
    drivers, reach = [], 0.0
    while reach < p.length - sc.place_from:
        tau, factor = p.uniform(hv.tau_range), p.uniform(hv.speed_factor)
        gap = idm_gap(speed, min(factor * limit, hv.max_speed), tau, hv.min_gap) * p.uniform(sc.stream_spacing)
        drivers.append((tau, factor, gap + hv.length))
        reach += gap + hv.length
    spacing = np.cumsum([d[2] for d in drivers])  # (K,) [m] behind the first vehicle's front
    # The head: past the merge edge's start by `stream_head`, further down where the AVs need the room.
    head = p.merge_start + p.uniform(sc.stream_head)
    head = min(max(head, sc.place_from + hv.length + spacing[min(sc.n_avs, len(spacing)) - 1] + 1.0), p.length - 1.0)
    fronts = head - spacing
    followers = int(np.count_nonzero(fronts - hv.length >= sc.place_from))
    if sc.n_avs > followers:
        raise ConfigError(f"scenario: {sc.n_avs} AVs do not fit in the stream on [{sc.place_from:.0f}, "
                          f"{p.length:.0f}] m ({followers} places behind its first vehicle): lower scenario.n_avs "
                          "or place_from, or use a net with a longer highway")
    # The guide AV reaches the merge edge `guide_window` after the merging vehicle; the nearest slot if none.
    arrival = (p.merge_start - fronts[:followers]) / speed - merger_time
    lo, hi = sc.guide_window
    inside = np.flatnonzero((arrival >= lo) & (arrival <= hi))
    guide = int(p.rng.choice(inside)) if inside.size else int(np.argmin(np.abs(arrival - 0.5 * (lo + hi))))
    rest = np.delete(np.arange(followers), guide)
    avs = {guide, *p.rng.choice(rest, size=sc.n_avs - 1, replace=False).tolist()}
    p.add(KIND_HV, head, rank, speed, max_speed=speed)  # drives at the stream's speed: the stream keeps it
    for k in range(followers):
        if k in avs:
            p.add(KIND_AV, fronts[k], rank, max(speed + p.uniform(sc.av_speed_offset), 0.0))
        else:
            p.add(KIND_HV, fronts[k], rank, speed, tau=drivers[k][0], speed_factor=drivers[k][1])
    # Behind the placed stream it goes on, entering at the highway's start at its mean spacing, unless the
    # placed stream's tail passes the acceleration lane's end only after the horizon anyway.
    tail = fronts[followers - 1]
    accel_end = p.merge_start + road.edge_length(desc.merge_edge)
    first = desc.highway[0]
    if (accel_end - tail) / max(speed, 0.1) < p.cfg.sim.horizon:
        p.flows.append(Flow("stream", "hw_0", p.net.through_lanes(first)[rank], speed,
                            period=float(np.mean([d[2] for d in drivers])) / max(speed, 0.1),
                            tau=float(np.mean(hv.tau_range)), speed_factor=float(np.mean(hv.speed_factor))))
    p.window([r for r in range(p.n_lanes) if r != rank], 0, sc.n_hvs)


PLACEMENTS: dict[str, Callable[[_Planner], None]] = {"window": _place_window, "stream": _place_stream}


def plan_episode(cfg: Config, net: Net, seed: int) -> Plan:
    """The episode `seed`'s vehicles for `cfg` resolved on `net` (`cosim.sumo.setting.Setting`)."""
    planner = _Planner(cfg, net, seed)
    PLACEMENTS[cfg.scenario.placement](planner)
    sc, hv = cfg.scenario, cfg.hv
    if sc.inflow > 0:
        planner.flows.append(Flow("inflow", "hw_0", "best", "desired", probability=min(1.0, sc.inflow / 3600.0),
                                  tau=float(np.mean(hv.tau_range)), speed_factor=float(np.mean(hv.speed_factor))))
    # Sorted by position so SUMO inserts leaders before followers on each lane.
    return Plan(sorted(planner.plan, key=lambda sp: (sp.route, -sp.pos)), planner.flows)


def vtype_xml(vid: str, drv: DriverConfig, tau: float, sigma: float, speed_factor: float,
              max_speed: float | None = None) -> str:
    """A human driver's `<vType>` (`drv` resolved: its max_speed in m/s)."""
    lc = "".join(f" {k}={quoteattr(str(v))}" for k, v in drv.lc_params.items())
    # speedDev 0: the drawn factor is the driver's, SUMO must not draw another around it.
    return (
        f'  <vType id="{vid}" carFollowModel="{drv.car_follow_model}" laneChangeModel="{drv.lane_change_model}"'
        f' accel="{drv.accel}" decel="{drv.decel}" emergencyDecel="{drv.emergency_decel}"'
        f' maxSpeed="{drv.max_speed if max_speed is None else max_speed:.3f}" length="{drv.length}"'
        f' width="{drv.width}" minGap="{drv.min_gap}" speedFactor="{speed_factor:.4f}" speedDev="0"'
        f' tau="{tau:.3f}" sigma="{sigma:.3f}"{lc}/>\n'
    )


def av_vtype_xml(cfg: Config) -> str:
    """The AVs' `<vType id="av">`: driven by the env (speed mode 0), it only gives size and nominal limits; with
    `sim.av_driver: sumo` (the all-human baseline) an average HV's."""
    av, hv = cfg.av, cfg.hv
    if cfg.sim.av_driver == "sumo":
        return vtype_xml("av", hv, *(float(np.mean(r)) for r in (hv.tau_range, hv.sigma_range, hv.speed_factor)))
    return (f'  <vType id="av" accel="{av.accel}" decel="{av.decel}" emergencyDecel="{av.decel}"'
            f' maxSpeed="{av.max_speed}" length="{av.length}" width="{av.width}" speedFactor="1" speedDev="0"'
            f' sigma="0" color="0,200,0"/>\n')


def routes_xml(desc: NetDescription) -> str:
    return "".join(f'  <route id="{name}" edges="{" ".join(edges)}"/>\n' for name, edges in route_ids(desc).items())


def write_episode(plan: Plan, cfg: Config, desc: NetDescription, path: Path) -> None:
    """Write `plan` as a SUMO route file; `cfg` resolved on the net (`resolve(cfg, net).config`, the env's)."""
    parts = ["<routes>\n", av_vtype_xml(cfg), routes_xml(desc)]
    hv = cfg.hv
    for sp in plan.vehicles:
        if sp.kind == KIND_AV:
            vtype = "av"
        else:
            vtype = f"t_{sp.vid}"
            drv = cfg.merger_driver(sp.alt) if sp.kind == KIND_MERGER else hv
            parts.append(vtype_xml(vtype, drv, sp.tau, sp.sigma, sp.speed_factor, sp.max_speed))
        parts.append(
            f'  <vehicle id="{sp.vid}" type="{vtype}" route="{sp.route}" depart="0" departLane="{sp.lane}"'
            f' departPos="{sp.pos:.3f}" departSpeed="{sp.speed:.3f}" insertionChecks="none"/>\n'
        )
    for f in plan.flows:
        parts.append(vtype_xml(f"t_{f.fid}", hv, f.tau, float(np.mean(hv.sigma_range)), f.speed_factor))
        rate = f'period="{f.period:.4f}"' if f.period is not None else f'probability="{f.probability:.6f}"'
        speed = f.speed if isinstance(f.speed, str) else f"{f.speed:.3f}"
        parts.append(
            f'  <flow id="{f.fid}" type="t_{f.fid}" route="{f.route}" begin="{cfg.sim.decision_period}"'
            f' end="{cfg.sim.horizon}" {rate} departLane="{f.lane}" departSpeed="{speed}"/>\n'
        )
    parts.append("</routes>\n")
    scratch_write_text(path, "".join(parts))
