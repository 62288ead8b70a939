"""An experiment on its net, resolved once, and what a run ran on, recorded and in words.

Contract: `Setting.of(cfg, warn=False)` loads the config's net and resolves the config on it once: `config` holds
the net-relative keys in absolute units (`cosim.sumo.resolve`), `notes` the values capped to fit the net (logged
as warnings with `warn`, as an env's start does) and, for a demand config, `demand` its traffic
(`cosim.sumo.demand.Demand`; None for the episode scenario). Everything downstream (the envs, the planners, the
evaluation's records and figures) takes the `Setting` and resolves nothing again.
`setting.record(overrides, seeds)` is what a run ran on, JSON-ready: `net` (`cosim.sumo.net.net_summary`) and
`overrides` (the command line's --set and --net); for the episode scenario `scenario`, `capped`, `flow_window_s`
and `detector` (where SUMO's induction loops count the throughput); under demand `drivers` and `demand` (with its
detector interval and `seeds`, one run each). `cosim evaluate` keeps it in `summary.json` and `net.json`,
`cosim train` in the run's `net.json`; `setting_lines(record)` words it for the Markdown reports.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

from cosim.config import Config
from cosim.sumo.demand import Demand, resolve_demand
from cosim.sumo.net import Net, load_net, net_summary, summary_lines
from cosim.sumo.outputs import detector_site
from cosim.sumo.resolve import driver_lines, resolve, scenario_lines

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Setting:
    config: Config  # resolved on `net`
    net: Net
    notes: tuple[str, ...]  # one line per capped value, naming its key
    demand: Demand | None  # the demand resolved on `net`; None for the episode scenario

    @classmethod
    def of(cls, cfg: Config, warn: bool = False) -> Setting:
        """`cfg` on its net (module doc); `warn`: log the capped values and ignored driver parameters."""
        net = load_net(cfg.net.file, cfg.net.description)
        resolved = resolve(cfg, net)
        for note in resolved.notes if warn else ():
            log.warning("%s", note)
        for key in ("hv", "merger", "merger_alt") if warn else ():
            driver = getattr(cfg, key)
            if driver is not None and (ignored := driver.ignored_lc_params()):
                log.warning("%s.lc_params: %s ignores %s (SL2015 reads it; set %s.lane_change_model: SL2015 to use "
                            "it)", key, driver.lane_change_model, ", ".join(ignored), key)
        config = resolved.config
        return cls(config, net, resolved.notes, resolve_demand(config, net) if config.demand.enabled else None)

    def record(self, overrides: Sequence[str] = (), seeds: Sequence[int] = ()) -> dict[str, Any]:
        """`seeds`: the runs of a demand evaluation (an episode evaluation's seeds are in its summary)."""
        cfg, net = self.config, self.net
        common = {"net": net_summary(net), "overrides": list(overrides)}
        if self.demand is not None:
            return {**common, "drivers": driver_lines(cfg),
                    "demand": {**asdict(self.demand), "interval": cfg.demand.interval, "seeds": list(seeds)}}
        site = detector_site(net, cfg.sim.detector_offset)
        return {**common, "scenario": scenario_lines(cfg, net), "capped": list(self.notes),
                "flow_window_s": cfg.sim.horizon,
                "detector": {"edge": site.edge, "lanes": list(site.lanes), "pos_m": round(site.pos, 1)}}


def setting_lines(s: dict[str, Any]) -> list[str]:
    """The setting as Markdown list items."""
    overrides = f"- overrides: {' '.join(f'`--set {o}`' for o in s['overrides']) if s['overrides'] else 'none'}"
    if "demand" in s:
        return [*(f"- {line}" for line in summary_lines(s["net"])), *_demand_lines(s["demand"]),
                *(f"- drivers: {line}" for line in s["drivers"]), overrides]
    det = s["detector"]
    return [*(f"- {line}" for line in summary_lines(s["net"])),
            *(f"- scenario: {line}" for line in s["scenario"]),
            *(f"- capped: {note}" for note in s["capped"]),
            overrides,
            f"- flow window: the first {s['flow_window_s']:g} s of each episode; throughput from induction loops "
            f"on all {len(det['lanes'])} lanes of {det['edge']!r}, {det['pos_m']:g} m past its start"]


def _demand_lines(d: dict[str, Any]) -> list[str]:
    """A demand run's traffic, times and seeds, as Markdown list items."""
    ramp_share = d["ramp_vph"] / d["ramp_capacity"] if d["ramp_capacity"] else 0.0
    avs = (f"{100 * d['av_penetration']:g}% of the mainline vehicles" if d["av_count"] is None
           else f"{d['av_count']} among the mainline vehicles")
    seeds = d["seeds"]
    runs = ("" if not seeds else f"seed {seeds[0]}" if len(seeds) == 1
            else f"{len(seeds)} seeds, {seeds[0]}..{seeds[-1]}")
    return [f"- demand: mainline {d['mainline_vph']:.0f} veh/h per lane on {d['mainline_lanes']} lane(s) "
            f"({d['mainline_vph'] / d['freeway_capacity']:.0%} of a highway lane's {d['freeway_capacity']:.0f} pc/h), "
            f"ramp {d['ramp_vph']:.0f} veh/h ({ramp_share:.0%} of its {d['ramp_capacity']:.0f} pc/h); exponential "
            "headways, vehicles waiting to enter where there is no room",
            f"- AVs: {avs}",
            f"- times: warm-up {d['warmup']:g} s (not measured), then a {d['window']:g} s measurement window; "
            f"detector interval {d['interval']:g} s",
            *([f"- runs: one per seed, {runs}"] if runs else [])]
