"""The vehicles of one episode: a seeded plan, and the SUMO route file that realises it.

Contract: `plan_episode(cfg, desc, road, seed)` is a pure function of its inputs (same seed, same plan):
N AVs and M HVs interleaved on the highway's through lanes upstream of the merge, with randomised gaps
and speeds, and the merging vehicle on the ramp. `write_episode(plan, cfg, desc, path)` writes vTypes,
routes and vehicles as one `.rou.xml` that SUMO loads at reset; every vehicle departs at t = 0 with SUMO's
insertion checks off so that the plan is realised exactly. Per-HV headway and imperfection come as a
vType of their own, so HVs differ as the config asks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from cosim.config import Config, DriverConfig
from cosim.errors import ConfigError
from cosim.netdesc import NetDescription
from cosim.roadnet import RoadNet
from cosim.snapshot import KIND_AV, KIND_HV, KIND_MERGER

MERGER_ID = "merger"


def av_id(i: int) -> str:
    return f"av_{i}"


def kind_of(vid: str) -> int:
    """Vehicle class from its id: ours are `av_*` and `merger`; anything else (inflow, user routes) is an HV."""
    if vid == MERGER_ID:
        return KIND_MERGER
    return KIND_AV if vid.startswith("av_") else KIND_HV


@dataclass(frozen=True)
class Spawn:
    vid: str
    kind: int
    route: str  # route id in the episode file
    lane: int
    pos: float  # [m] on the route's first edge
    speed: float  # [m/s]
    tau: float = 1.0  # [s] (HVs)
    sigma: float = 0.0  # [-] (HVs)


def route_ids(desc: NetDescription) -> dict[str, tuple[str, ...]]:
    """One highway route per possible start edge, and the ramp route through the merge edge onwards."""
    hw = desc.highway
    routes = {f"hw_{i}": hw[i:] for i in range(len(hw))}
    routes["ramp"] = desc.ramp + hw[hw.index(desc.merge_edge):]
    return routes


def plan_episode(cfg: Config, desc: NetDescription, road: RoadNet, seed: int) -> list[Spawn]:
    sc = cfg.scenario
    length = desc.highway_length(road)
    if sc.place_from < 0 or sc.place_to > length:
        raise ConfigError(f"scenario.place_from / place_to: [{sc.place_from}, {sc.place_to}] m must lie on the "
                          f"highway, [0, {length:.1f}] m long in {road.net_file}")
    rng = np.random.default_rng(seed)
    n_total = sc.n_avs + sc.n_hvs
    hw_index = {edge: i for i, edge in enumerate(desc.highway)}
    n_lanes = min(len(desc.through_lanes(road, e)) for e in desc.highway)
    # Slots per lane: front-to-front spacing drawn from [min_gap, max_gap], so lanes are staggered.
    slots: list[tuple[float, int]] = []
    for lane in range(n_lanes):
        s = sc.place_from + rng.uniform(0.0, sc.min_gap)
        while s <= sc.place_to:
            slots.append((s, lane))
            s += rng.uniform(sc.min_gap, sc.max_gap)
    if len(slots) < n_total:
        raise ConfigError(
            f"scenario: {n_total} vehicles (n_avs + n_hvs) do not fit in [place_from, place_to] = "
            f"[{sc.place_from}, {sc.place_to}] m on {n_lanes} lanes with min_gap {sc.min_gap} m; "
            f"about {len(slots)} fit: lower the counts or widen the window"
        )
    chosen = rng.choice(len(slots), size=n_total, replace=False)
    # A random permutation of AV and HV labels over the chosen slots interleaves the classes.
    is_av = np.zeros(n_total, dtype=bool)
    is_av[rng.choice(n_total, size=sc.n_avs, replace=False)] = True
    speeds = rng.uniform(*sc.speed_range, size=n_total)
    plan: list[Spawn] = []
    n_av = n_hv = 0
    for k, slot in enumerate(chosen):
        s, lane_rank = slots[slot]
        edge, pos = desc.highway_position(road, s)
        lane = desc.through_lanes(road, edge)[lane_rank]
        route = f"hw_{hw_index[edge]}"
        if is_av[k]:
            plan.append(Spawn(av_id(n_av), KIND_AV, route, lane, pos, float(speeds[k])))
            n_av += 1
        else:
            tau, sigma = rng.uniform(*cfg.hv.tau_range), rng.uniform(*cfg.hv.sigma_range)
            plan.append(Spawn(f"hv_{n_hv}", KIND_HV, route, lane, pos, float(speeds[k]), float(tau), float(sigma)))
            n_hv += 1
    ramp_len = road.edge_length(desc.ramp[0])
    if not 0 <= sc.merger_pos < ramp_len:
        raise ConfigError(f"scenario.merger_pos: must be within the ramp edge {desc.ramp[0]!r} "
                          f"(0 to {ramp_len:.1f} m), got {sc.merger_pos}")
    tau, sigma = rng.uniform(*cfg.merger.tau_range), rng.uniform(*cfg.merger.sigma_range)
    plan.append(Spawn(MERGER_ID, KIND_MERGER, "ramp", 0, sc.merger_pos,
                      float(rng.uniform(*sc.merger_speed)), float(tau), float(sigma)))
    # Sorted by position so SUMO inserts leaders before followers on each lane.
    plan.sort(key=lambda sp: (sp.route, -sp.pos))
    return plan


def _vtype(vid: str, drv: DriverConfig, tau: float, sigma: float) -> str:
    lc = "".join(f" {k}={quoteattr(str(v))}" for k, v in drv.lc_params.items())
    return (
        f'  <vType id="{vid}" carFollowModel="{drv.car_follow_model}" laneChangeModel="{drv.lane_change_model}"'
        f' accel="{drv.accel}" decel="{drv.decel}" emergencyDecel="{drv.emergency_decel}"'
        f' maxSpeed="{drv.max_speed}" length="{drv.length}" width="{drv.width}" minGap="{drv.min_gap}"'
        f' speedFactor="{drv.speed_factor}" tau="{tau:.3f}" sigma="{sigma:.3f}"{lc}/>\n'
    )


def write_episode(plan: list[Spawn], cfg: Config, desc: NetDescription, path: Path) -> None:
    av = cfg.av
    parts = ["<routes>\n"]
    if cfg.sim.av_driver == "sumo":  # the all-human baseline: AVs drive like (average) HVs
        hv = cfg.hv
        parts.append(_vtype("av", hv, float(np.mean(hv.tau_range)), float(np.mean(hv.sigma_range))))
    else:
        # AVs are driven by the env (speed mode 0); their vType only gives size and nominal limits.
        parts.append(
            f'  <vType id="av" accel="{av.accel}" decel="{av.decel}" emergencyDecel="{av.decel}"'
            f' maxSpeed="{av.max_speed}" length="{av.length}" width="{av.width}" speedFactor="1" sigma="0"'
            f' color="0,200,0"/>\n'
        )
    for name, edges in route_ids(desc).items():
        parts.append(f'  <route id="{name}" edges="{" ".join(edges)}"/>\n')
    for sp in plan:
        if sp.kind == KIND_AV:
            vtype = "av"
        else:
            vtype = f"t_{sp.vid}"
            parts.append(_vtype(vtype, cfg.merger if sp.kind == KIND_MERGER else cfg.hv, sp.tau, sp.sigma))
        parts.append(
            f'  <vehicle id="{sp.vid}" type="{vtype}" route="{sp.route}" depart="0" departLane="{sp.lane}"'
            f' departPos="{sp.pos:.3f}" departSpeed="{sp.speed:.3f}" insertionChecks="none"/>\n'
        )
    if cfg.scenario.inflow > 0:
        hv = cfg.hv
        parts.append(_vtype("hv_inflow", hv, float(np.mean(hv.tau_range)), float(np.mean(hv.sigma_range))))
        parts.append(
            f'  <flow id="inflow" type="hv_inflow" route="hw_0" begin="{cfg.sim.decision_period}"'
            f' end="{cfg.sim.horizon}" probability="{min(1.0, cfg.scenario.inflow / 3600.0):.6f}"'
            f' departLane="best" departSpeed="desired"/>\n'
        )
    parts.append("</routes>\n")
    path.write_text("".join(parts))
