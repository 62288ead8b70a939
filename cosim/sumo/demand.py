"""Traffic demand over minutes: capacities, the vehicles of one run, and SUMO's route file for them.

Contract:
- `freeway_capacity(limit)` and `ramp_capacity(limit)` [pc/h per lane] by speed limit [m/s], from the HCM: basic
  freeway segments 2,200 + 10 (FFS - 50) pc/h/ln with the free-flow speed FFS in mi/h taken as the limit and
  held within [50, 70]; ramp roadways 1,800 to 2,200 pc/h per lane in 10 mi/h steps (Exhibit 14-12). Vehicles
  are passenger cars, so pc/h = veh/h.
- `resolve_demand(cfg, net)` -> `Demand`: the config's `demand:` section on `net` in veh/h (mainline per lane of
  the highway's first edge, ramp in total), the AVs (a share of the mainline vehicles, or a count), the times
  (warm-up, window, horizon [s]), the capacities used, and the sizes an env needs: `max_avs`, the AVs a run can
  release (the count, or the penetration's expected number plus six standard deviations), `slots`, the most
  present at once (`demand.max_avs_present`, or estimated from the AV flow and the highway's length at half
  its speed limit, tripled; never more than `max_avs`). Sizes that would take the machine's memory are a
  `ConfigError` naming the key and the bound, before anything is allocated: an `av_count` above the mainline
  vehicles the demand releases (their expected number plus six standard deviations), and slots whose observations
  exceed `MAX_SLOT_VALUES` values.
- `plan_demand(cfg, net, demand, seed)` -> the run's `Arrival`s (`demand`: `resolve_demand`'s): exponential headways per
  highway lane and on the ramp from t = 0 to the horizon, each mainline vehicle an AV with the penetration's probability
  (or `av_count` AVs drawn among them), AVs named `av_0, av_1, ...` in order of departure (an AV beyond `max_avs`,
  unlikely by construction, drives as an HV), HVs `hv_K`, ramp vehicles `merger_K` (driven as the `merger:` section
  says), each human with drivers' parameters of its own as in the episode scenario.
- `write_demand(arrivals, cfg, desc, path)`: the route file. Vehicles enter at their desired speed, as traffic
  arriving from upstream does, and insertion checks stay on: a vehicle with no room to enter at that speed waits
  (SUMO's insertion backlog), which the flow metrics count as delay and ramp queue.
`cfg` is resolved on the net (`cosim.sumo.resolve`), as the env's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.config import Config
from cosim.errors import ConfigError
from cosim.files import scratch_write_text
from cosim.sumo.net import Net
from cosim.sumo.netdesc import NetDescription
from cosim.sumo.scenario import MERGER_ID, av_id, av_vtype_xml, routes_xml, vtype_xml
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER

MPH = 0.44704  # [m/s]


def freeway_capacity(limit: float) -> float:
    """[pc/h/ln] of a basic freeway segment whose free-flow speed is `limit` [m/s] (HCM)."""
    return 2200.0 + 10.0 * (min(max(limit / MPH, 50.0), 70.0) - 50.0)


def ramp_capacity(limit: float) -> float:
    """[pc/h] of one lane of a ramp roadway whose free-flow speed is `limit` [m/s] (HCM Exhibit 14-12)."""
    mph = limit / MPH
    return 1800.0 + 100.0 * sum(mph > bound for bound in (20.0, 30.0, 40.0, 50.0))


@dataclass(frozen=True)
class Demand:
    mainline_vph: float  # [veh/h] per lane of the highway's first edge
    mainline_lanes: int
    ramp_vph: float  # [veh/h] in total
    ramp_lanes: int
    av_penetration: float | None  # share of mainline vehicles, or None with av_count
    av_count: int | None
    warmup: float  # [s]
    window: float  # [s]
    horizon: float  # [s] warmup + window
    freeway_capacity: float  # [pc/h/ln] of the highway at the merge's limit
    ramp_capacity: float  # [pc/h] of the ramp, all lanes
    max_avs: int  # the AVs a run can release: possible agents
    slots: int  # the most AVs present at once: observation storage

    @property
    def mainline_total(self) -> float:
        return self.mainline_vph * self.mainline_lanes


# Observation values of every slot of a demand run at most: a worker keeps two stacks per slot (256 MiB as uint8).
MAX_SLOT_VALUES = 2**28


def resolve_demand(cfg: Config, net: Net) -> Demand:
    d = cfg.demand
    first = net.desc.highway[0]
    lanes = len(net.through_lanes(first))
    cap = freeway_capacity(net.speed_limit)
    ramp_lanes = net.road.num_lanes(net.desc.ramp[0])
    ramp_cap = ramp_capacity(net.ramp_speed_limit) * ramp_lanes
    mainline = d.mainline_vph if d.mainline_vph is not None else d.mainline_share * cap
    ramp = d.ramp_vph if d.ramp_vph is not None else d.ramp_share * ramp_cap
    horizon = d.warmup + d.window
    released = _most(mainline * lanes * horizon / 3600.0)  # mainline vehicles of a run, at most
    if d.av_count is not None:
        if d.av_count > released:
            raise ConfigError(f"demand.av_count: {d.av_count} AVs, but the mainline demand ({mainline * lanes:.0f} "
                              f"veh/h on {lanes} lane(s)) releases about {mainline * lanes * horizon / 3600:.0f} "
                              f"vehicles over warmup + window ({horizon:g} s), at most {released}; give at most "
                              f"{released}, or more demand or a longer window")
        max_avs = d.av_count
        rate = d.av_count / horizon  # [AV/s]
    else:
        max_avs = _most(d.av_penetration * mainline * lanes * horizon / 3600.0)
        rate = d.av_penetration * mainline * lanes / 3600.0
    crossing = net.highway_length / (0.5 * net.speed_limit)  # [s] through the net at half the limit
    slots = min(d.max_avs_present or int(math.ceil(3.0 * rate * crossing)) + 4, max_avs)
    values = math.prod(cfg.observation.shape)
    if slots * values > MAX_SLOT_VALUES:
        fit = MAX_SLOT_VALUES // values
        key = "demand.max_avs_present" if d.max_avs_present else "demand (its AVs present at once)"
        raise ConfigError(f"{key}: {slots} observation slots of {values:,} values each exceed the bound of "
                          f"{MAX_SLOT_VALUES:,} values ({MAX_SLOT_VALUES // 2**20} MiB as uint8; a worker keeps two "
                          f"stacks per slot): at most {fit} slots at this observation size; set "
                          f"demand.max_avs_present to at most {fit}, or a smaller observation")
    return Demand(mainline, lanes, ramp, ramp_lanes, d.av_penetration, d.av_count, d.warmup, d.window, horizon,
                  cap, ramp_cap, max_avs, max(slots, 1 if max_avs else 0))


def _most(expected: float) -> int:
    """The most vehicles a Poisson arrival process with this mean gives in practice: six standard deviations above."""
    return int(math.ceil(expected + 6.0 * math.sqrt(expected))) + (1 if expected > 0 else 0)


@dataclass(frozen=True)
class Arrival:
    vid: str
    kind: int  # KIND_*
    route: str  # a route of cosim.sumo.scenario.route_ids
    lane: int  # departure lane
    depart: float  # [s]
    tau: float = 1.0  # [s] (humans)
    sigma: float = 0.0
    speed_factor: float = 1.0
    alt: bool = False  # a ramp vehicle of the config's merger_alt type (scenario.merger_alt_share)


def _times(rng: np.random.Generator, vph: float, horizon: float) -> np.ndarray:
    """Arrival times [s] in [0, horizon) with exponential headways at `vph` [veh/h]."""
    if vph <= 0:
        return np.zeros(0)
    mean = 3600.0 / vph
    n = int(horizon / mean * 1.5 + 10 * math.sqrt(horizon / mean) + 10)  # enough headways to pass the horizon
    t = np.cumsum(rng.exponential(mean, size=n))
    return t[t < horizon]


def plan_demand(cfg: Config, net: Net, dem: Demand, seed: int) -> list[Arrival]:
    """Every vehicle of the run `seed`, by departure time (see the module doc); `cfg` and `dem` resolved on `net`."""
    rng = np.random.default_rng(seed)
    first = net.desc.highway[0]
    mainline = sorted((float(t), lane) for lane in net.through_lanes(first)
                      for t in _times(rng, dem.mainline_vph, dem.horizon))
    ramp_lanes = net.road.num_lanes(net.desc.ramp[0])
    lane = ramp_lanes - 1 if cfg.scenario.merger_lane is None else min(cfg.scenario.merger_lane, ramp_lanes - 1)
    ramp = _times(rng, dem.ramp_vph, dem.horizon)
    if dem.av_count is not None:
        is_av = np.zeros(len(mainline), bool)
        is_av[rng.choice(len(mainline), size=min(dem.av_count, len(mainline)), replace=False)] = True
    else:
        is_av = rng.random(len(mainline)) < dem.av_penetration
    hv, share = cfg.hv, cfg.scenario.merger_alt_share
    out: list[Arrival] = []
    n_av = n_hv = 0
    for (t, ln), av in zip(mainline, is_av, strict=True):
        if av and n_av < dem.max_avs:
            out.append(Arrival(av_id(n_av), KIND_AV, "hw_0", ln, t))
            n_av += 1
        else:
            out.append(Arrival(f"hv_{n_hv}", KIND_HV, "hw_0", ln, t, *_driver(rng, hv)))
            n_hv += 1
    # Drawn only where asked, so that every other config keeps its windows' random streams.
    alt = rng.random(len(ramp)) < share if share > 0 else np.zeros(len(ramp), bool)
    out += [Arrival(f"{MERGER_ID}_{k}", KIND_MERGER, "ramp_0", lane, float(t),
                    *_driver(rng, cfg.merger_driver(bool(a))), alt=bool(a))
            for k, (t, a) in enumerate(zip(ramp, alt, strict=True))]
    return sorted(out, key=lambda a: a.depart)


def _driver(rng: np.random.Generator, drv: object) -> tuple[float, float, float]:
    return tuple(float(rng.uniform(*r)) for r in (drv.tau_range, drv.sigma_range, drv.speed_factor))  # type: ignore[attr-defined]


def write_demand(arrivals: list[Arrival], cfg: Config, desc: NetDescription, path: Path) -> None:
    parts = ["<routes>\n", av_vtype_xml(cfg), routes_xml(desc)]
    for a in arrivals:
        vtype = "av"
        if a.kind != KIND_AV:
            vtype = f"t_{a.vid}"
            parts.append(vtype_xml(vtype, cfg.merger_driver(a.alt) if a.kind == KIND_MERGER else cfg.hv, a.tau, a.sigma,
                                   a.speed_factor))
        # departSpeed desired: at the driver's own free speed, as traffic arriving from upstream would be, or not yet
        # (the insertion backlog: delay). "max" let a vehicle in at whatever speed was safe behind the last one
        # inserted, often a crawl: a permanent slow band over the highway's first 100-250 m (14 m/s mean speed
        # over its first 100 m against 30 m/s downstream) that held the mainline below its demand.
        parts.append(f'  <vehicle id="{a.vid}" type="{vtype}" route="{a.route}" depart="{a.depart:.2f}" '
                     f'departLane="{a.lane}" departSpeed="desired"/>\n')
    parts.append("</routes>\n")
    scratch_write_text(path, "".join(parts))
