"""What an evaluation or a training run ran on, recorded and in words: the net, the scenario resolved on it, the
overrides, the flow window and the detector.

Contract: `setting(cfg, overrides)` returns a JSON-ready dict: `net` (`cosim.sumo.net.net_summary`: path,
sha256, roles, lanes, lengths, limits), `scenario` (`cosim.sumo.resolve.scenario_lines`) and `capped` (the
resolution's notes), `overrides` (the command line's --set and --net), `flow_window_s` and `detector` (where
SUMO's induction loops count the throughput). `cosim evaluate` keeps it in `summary.json` and `net.json`,
`cosim train` in the run's `net.json`; `setting_lines(setting)` words it for the Markdown reports of
`cosim evaluate` and `cosim compare`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cosim.config import Config
from cosim.sumo.net import load_net, net_summary, summary_lines
from cosim.sumo.outputs import detector_site
from cosim.sumo.resolve import resolve, scenario_lines


def setting(cfg: Config, overrides: Sequence[str] = ()) -> dict[str, Any]:
    net = load_net(cfg.net.file, cfg.net.description)
    resolved = resolve(cfg, net)
    site = detector_site(net, cfg.sim.detector_offset)
    return {"net": net_summary(net), "scenario": scenario_lines(resolved.config, net),
            "capped": list(resolved.notes), "overrides": list(overrides), "flow_window_s": cfg.sim.horizon,
            "detector": {"edge": site.edge, "lanes": list(site.lanes), "pos_m": round(site.pos, 1)}}


def setting_lines(s: dict[str, Any]) -> list[str]:
    """The setting as Markdown list items."""
    det = s["detector"]
    return [*(f"- {line}" for line in summary_lines(s["net"])),
            *(f"- scenario: {line}" for line in s["scenario"]),
            *(f"- capped: {note}" for note in s["capped"]),
            f"- overrides: {' '.join(f'`--set {o}`' for o in s['overrides']) if s['overrides'] else 'none'}",
            f"- flow window: the first {s['flow_window_s']:g} s of each episode; throughput from induction loops "
            f"on all {len(det['lanes'])} lanes of {det['edge']!r}, {det['pos_m']:g} m past its start"]
