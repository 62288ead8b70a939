"""What an evaluation or a training run ran on, recorded and in words: the net, the scenario resolved on it, the
overrides, the flow window and the detector; or, for a demand run, the demand.

Contract: `setting(cfg, overrides, seeds)` returns a JSON-ready dict: `net` (`cosim.sumo.net.net_summary`: path,
sha256, roles, lanes, lengths, limits) and `overrides` (the command line's --set and --net); for an episode
config `scenario` (`cosim.sumo.resolve.scenario_lines`), `capped` (the resolution's notes), `flow_window_s` and
`detector` (where SUMO's induction loops count the throughput); for a demand config (`demand.enabled`) `drivers`
(`cosim.sumo.resolve.driver_lines`: the episodes' placement means nothing there) and `demand` (the demand
resolved on the net, `cosim.sumo.demand.Demand`, with its detector interval and `seeds`, one run each).
`cosim evaluate` keeps it in `summary.json` and `net.json`, `cosim train` in the run's `net.json`;
`setting_lines(setting)` words it for the Markdown reports of `cosim evaluate` and `cosim compare`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

from cosim.config import Config
from cosim.sumo.demand import resolve_demand
from cosim.sumo.net import load_net, net_summary, summary_lines
from cosim.sumo.outputs import detector_site
from cosim.sumo.resolve import driver_lines, resolve, scenario_lines


def setting(cfg: Config, overrides: Sequence[str] = (), seeds: Sequence[int] = ()) -> dict[str, Any]:
    """`seeds`: the runs of a demand evaluation (an episode evaluation's seeds are in its summary)."""
    net = load_net(cfg.net.file, cfg.net.description)
    resolved = resolve(cfg, net)
    common = {"net": net_summary(net), "overrides": list(overrides)}
    if cfg.demand.enabled:
        demand = asdict(resolve_demand(resolved.config, net))
        return {**common, "drivers": driver_lines(resolved.config),
                "demand": {**demand, "interval": cfg.demand.interval, "seeds": list(seeds)}}
    site = detector_site(net, cfg.sim.detector_offset)
    return {**common, "scenario": scenario_lines(resolved.config, net), "capped": list(resolved.notes),
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
