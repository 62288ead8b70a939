"""What cooperative AVs do to an on-ramp's traffic: trained AVs at several penetrations and demand levels against
all-human traffic, as a traffic engineer reads it.

    python scripts/demand_headline.py runs/demand/phi0 runs/demand/pi4 --out runs/headline     # 10 seeds a cell

Each cell is a demand level (`cosim.config.DEMAND_LEVELS`: near capacity and over capacity by default) and an AV
penetration (10, 30, 60% of the mainline vehicles). In each, on the same evaluation seeds (10,000,000 on: disjoint
from training and validation), every player is one resumable `cosim evaluate` into
`OUT/<level>/<penetration>/<player>/`: `all-human` (every AV a SUMO driver: the traffic without AVs), `scripted`
(the hand-written AV, the collisions bar), and each trained run's `best.pt` on its own config with only the demand
changed (the baselines play on `--config`; `--set` and `--net` apply to every player). A second call plays only
the runs missing. Writes `OUT/headline.md` (per cell the flow table with 95% t-intervals over seeds, each player's
level of service, and the checks: trained AVs' throughput no lower than all-human traffic's and their crash per
merging vehicle no higher than `scripted`'s, and egoistic against altruistic on each flow measure),
`OUT/headline.json` and `OUT/headline.png` (delay and throughput against penetration, a band per player).
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from cosim.cli import add_config_arguments, config_overrides
from cosim.config import DEFAULT_CONFIG, DEMAND_LEVELS, EVAL_SEED_START, load_config
from cosim.environment.flow_metrics import level_of_service
from cosim.errors import CosimError, run_script
from cosim.evaluation.flow_plots import penetration_curves
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import FLOW_METRICS, format_table, interval_text
from cosim.files import atomic_write_text, write_json

log = logging.getLogger("demand_headline")
HUMAN, BAR = "all-human", "scripted"
THROUGHPUT, CRASH = "throughput, total [veh/h]", "crash, per merging vehicle [%]"
DENSITY = "density, merge influence area [veh/km/ln]"
# The flow claim's measures, and whether more is better.
CLAIM = {"delay, ramp vehicles [s]": False, "total delay [veh h]": False, "total time spent [veh h]": False,
         THROUGHPUT: True, "ramp queue, mean [veh]": False, DENSITY: False,
         "distance per vehicle [m]": True, CRASH: False, "collisions [per window]": False,
         "conflicts [per window]": False, "conflicts with a ramp vehicle [per window]": False}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders (their config.yaml and best.pt)")
    add_config_arguments(parser, default=DEFAULT_CONFIG.with_name("demand.yaml"))  # --set, --net: every player's
    parser.add_argument("--levels", nargs="+", default=["near capacity", "over capacity"],
                        choices=list(DEMAND_LEVELS), metavar="LEVEL",
                        help=f"demand levels, of: {', '.join(DEMAND_LEVELS)}")
    parser.add_argument("--penetrations", nargs="+", type=float, default=[0.1, 0.3, 0.6],
                        help="AV shares of the mainline vehicles, each in (0, 1]")
    parser.add_argument("--seeds", type=int, default=10, help="runs per (cell, player)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/headline"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    bad = [p for p in args.penetrations if not 0 < p <= 1]
    if bad:
        raise CosimError(f"--penetrations: each must lie in (0, 1], got {', '.join(map(str, bad))}")
    if args.seeds < 2:
        raise CosimError(f"--seeds must be >= 2 for an interval over seeds, got {args.seeds}")
    from agents.checkpoint import TrainedPolicy, find_checkpoint  # torch only here

    user = config_overrides(args)
    names = [run.name for run in args.runs]
    if len(set(names)) < len(names) or {HUMAN, BAR} & set(names):
        raise CosimError(f"runs are named by their folders, which must differ from each other and from {HUMAN} and "
                         f"{BAR}: got {', '.join(names)}")
    phis, seeds = {}, {}
    for run in args.runs:
        if not (run / "config.yaml").is_file():
            raise CosimError(f"{run}: not a training run folder (no config.yaml)")
        run_cfg = load_config(run / "config.yaml")
        phis[run.name], seeds[run.name] = float(run_cfg.reward.phi), run_cfg.train.seed
    players: list[tuple[str, Any, Path]] = [(HUMAN, Baseline("sumo"), args.config), (BAR, Baseline("scripted"),
                                                                                    args.config)]
    players += [(run.name, TrainedPolicy(str(find_checkpoint(run, None))), run / "config.yaml") for run in args.runs]
    start = time.perf_counter()
    cells: dict[str, dict[float, dict[str, dict[str, Any]]]] = {}
    demands: dict[str, dict[float, dict[str, Any]]] = {}
    for level in args.levels:
        mainline, ramp = DEMAND_LEVELS[level]
        for share in args.penetrations:
            sets = [*user, "demand.enabled=true", f"demand.mainline_share={mainline}", "demand.mainline_vph=null",
                    f"demand.ramp_share={ramp}", "demand.ramp_vph=null", f"demand.av_penetration={share}",
                    "demand.av_count=null"]
            for name, policy, config in players:
                out = args.out / level.replace(" ", "_") / f"{round(100 * share)}pct" / name
                log.info("%s, %.0f%% AVs: %s, %d runs", level, 100 * share, name, args.seeds)
                summary = evaluate(load_config(config, sets), policy, out, episodes=args.seeds, seed=EVAL_SEED_START,
                                   workers=args.workers, plots=False, overrides=sets)
                cells.setdefault(level, {}).setdefault(share, {})[name] = summary["metrics"]
                if name == HUMAN:
                    demands.setdefault(level, {})[share] = summary["demand"]
    wall = time.perf_counter() - start
    command = shlex.join(["python", *sys.argv])
    lines = ["# Trained AVs in traffic against all-human traffic", "",
             f"`{command}`: {args.seeds} runs per (cell, player) of a warm-up and a measurement window on evaluation "
             f"seeds {EVAL_SEED_START}..{EVAL_SEED_START + args.seeds - 1}; means with 95% t-intervals over the "
             f"runs; {wall / 60:.1f} min (runs done before a resume not counted). `{HUMAN}`: every AV a SUMO "
             f"driver; trained runs: "
             f"{', '.join(f'{n} (phi {p:.4f}, training seed {seeds[n]})' for n, p in phis.items())}.", ""]
    checks: dict[str, dict[float, list[str]]] = {}
    for level, by_share in cells.items():
        for share, table in by_share.items():
            d = demands[level][share]
            lines += [f"## {level}, {100 * share:.0f}% AVs: {d['mainline_vph']:.0f} veh/h per highway lane x "
                      f"{d['mainline_lanes']}, ramp {d['ramp_vph']:.0f} veh/h", "",
                      f"{d['capacity']}; level of service (HCM, the all-human traffic's): "
                      f"{d.get('level_of_service', '?')}.", "",
                      format_table({p: {k: v for k, v in m.items() if k in FLOW_METRICS} for p, m in table.items()},
                                   {p: args.seeds for p in table}, markdown=True), "",
                      service_levels(table, bool(d.get("over_capacity"))), ""]
            found = cell_checks(table, phis, seeds)
            checks.setdefault(level, {})[share] = found
            lines += [f"- {c}" for c in found] + [""]
    caption = (f"{args.seeds} seeds per point; demand levels as shares of the HCM capacities "
               f"({', '.join(f'{lv}: {DEMAND_LEVELS[lv][0]:.0%} / {DEMAND_LEVELS[lv][1]:.0%}' for lv in cells)} of "
               f"a highway lane's / the ramp's); `{HUMAN}`: every AV a SUMO driver; {command}")
    penetration_curves(cells, args.out / "headline.png", caption=caption)
    atomic_write_text(args.out / "headline.md", "\n".join(lines))
    write_json(args.out / "headline.json", {"command": command, "wall_s": wall, "phi": phis, "seeds": args.seeds,
                                            "cells": {lv: {str(s): t for s, t in c.items()} for lv, c in cells.items()},
                                            "demand": {lv: {str(s): d for s, d in c.items()}
                                                       for lv, c in demands.items()},
                                            "checks": {lv: {str(s): c for s, c in c.items()}
                                                       for lv, c in checks.items()}})
    print("\n".join(lines))


def compare(a: dict[str, float], b: dict[str, float], higher_better: bool) -> str:
    """`a` against `b`: better or worse by the means, and whether their 95% intervals are apart."""
    apart = a["ci_low"] > b["ci_high"] or a["ci_high"] < b["ci_low"]
    better = (a["mean"] > b["mean"]) == higher_better and a["mean"] != b["mean"]
    return f"{'better' if better else 'worse' if a['mean'] != b['mean'] else 'equal'}" + \
        (" (intervals apart)" if apart else " (intervals overlap)")


def service_levels(table: dict[str, dict[str, dict[str, float]]], over_capacity: bool) -> str:
    """Each player's HCM level of service in the merge influence area, of its mean density and of its interval's
    bounds (F for all where the demand exceeds the capacity)."""
    def letters(m: dict[str, float]) -> str:
        low, mean, high = (level_of_service(m[k], over_capacity) for k in ("ci_low", "mean", "ci_high"))
        return f"{mean} [{low}, {high}]"
    return "level of service (HCM, of each player's mean density [and of its interval's bounds]): " + \
        "; ".join(f"{p} {letters(m[DENSITY])}" for p, m in table.items() if DENSITY in m)


def cell_checks(table: dict[str, dict[str, dict[str, float]]], phis: dict[str, float],
                seeds: dict[str, int]) -> list[str]:
    """One cell's checks: each trained run's total throughput against all-human traffic's (fails only where its
    interval lies wholly below) and its crash per merging vehicle against `scripted`'s (fails only where wholly
    above); then each flow measure of every run at the highest angle against the run at the lowest of its training
    seed (`seeds`: run -> train.seed), or the first run at the lowest where no run there shares its seed."""
    out = []
    for run in phis:
        t, h = table[run][THROUGHPUT], table[HUMAN][THROUGHPUT]
        out.append(f"{run}: throughput [veh/h] {interval_text(t)} against {HUMAN} {interval_text(h)}: "
                   f"{'fails (lower, intervals apart)' if t['ci_high'] < h['ci_low'] else 'holds'}")
        c, s = table[run][CRASH], table[BAR][CRASH]
        out.append(f"{run}: crash per merging vehicle [%] {interval_text(c)} against {BAR} {interval_text(s)}: "
                   f"{'fails (higher, intervals apart)' if c['ci_low'] > s['ci_high'] else 'holds'}")
    if len(set(phis.values())) >= 2:
        lowest = [run for run, phi in phis.items() if phi == min(phis.values())]
        for alt in [run for run, phi in phis.items() if phi == max(phis.values())]:
            ego = next((run for run in lowest if seeds[run] == seeds[alt]), lowest[0])
            for metric, higher in CLAIM.items():
                if metric in table[alt] and metric in table[ego]:
                    a, e = table[alt][metric], table[ego][metric]
                    out.append(f"{alt} against {ego}, {metric}: {interval_text(a)} vs {interval_text(e)}: "
                               f"altruism {compare(a, e, higher)}")
    return out


if __name__ == "__main__":
    run_script(main, log)
