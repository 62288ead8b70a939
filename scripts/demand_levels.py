"""The baselines under three demand levels on a net: every flow metric with its 95% interval over seeds.

    python scripts/demand_levels.py --out runs/demand_levels             # the default net, 5 seeds each
    python scripts/demand_levels.py --net my.net.xml --out runs/my_levels

Evaluates `idle`, `scripted`, `courteous` and `sumo` in `configs/demand.yaml`'s demand mode at three levels
(`cosim.config.DEMAND_LEVELS`: light, near capacity, over capacity; demands as shares of the HCM capacities, so
the same levels on any net), on the same evaluation seeds, each (level, policy) a resumable `cosim evaluate`;
writes OUT/levels.md (one table per level, with its demand, the capacity it is judged against and the level of
service) and OUT/levels.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from cosim.cli import add_config_arguments, config_overrides
from cosim.config import DEFAULT_CONFIG, DEMAND_LEVELS, EVAL_SEED_START, load_config
from cosim.errors import run_script
from cosim.evaluation.checknet import POLICIES
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import FLOW_METRICS, format_table
from cosim.files import atomic_write_text

log = logging.getLogger("demand_levels")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_arguments(parser, default=DEFAULT_CONFIG.with_name("demand.yaml"))
    parser.add_argument("--seeds", type=int, default=None, help="runs per (level, policy) (default: demand.seeds)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/demand_levels"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    base = load_config(args.config, config_overrides(args))
    seeds = args.seeds or base.demand.seeds
    t0 = time.perf_counter()
    result: dict[str, dict] = {}
    lines = [f"# Baselines under three demand levels: {base.net.file}", ""]
    for level, (mainline, ramp) in DEMAND_LEVELS.items():
        cfg = load_config(base, {"demand.mainline_share": mainline, "demand.ramp_share": ramp})
        summaries = {p: evaluate(cfg, Baseline(p), args.out / level.replace(" ", "_") / p, episodes=seeds,
                                 seed=EVAL_SEED_START, workers=args.workers, plots=p == "courteous")
                     for p in POLICIES}
        result[level] = {p: {"metrics": s["metrics"], "demand": s["demand"]} for p, s in summaries.items()}
        d = summaries["courteous"]["demand"]
        los = ", ".join(f"{p} {s['demand']['level_of_service']}" for p, s in summaries.items())
        lines += [f"## {level}: {d['mainline_vph']:.0f} veh/h per highway lane ({mainline:.0%} of its capacity) x "
                  f"{d['mainline_lanes']}, ramp {d['ramp_vph']:.0f} veh/h ({ramp:.0%}), "
                  f"{100 * (d['av_penetration'] or 0):.0f}% AVs", "",
                  f"Level of service in the merge influence area (HCM): {los}; {d['capacity']}.", "",
                  format_table({p: {k: v for k, v in s["metrics"].items() if k in FLOW_METRICS}
                                for p, s in summaries.items()}, {p: s["episodes"] for p, s in summaries.items()},
                               markdown=True), ""]
    wall = time.perf_counter() - t0
    lines.insert(2, f"{seeds} runs of a {base.demand.warmup:g} s warm-up and {base.demand.window:g} s window per "
                    f"(level, policy) on evaluation seeds {EVAL_SEED_START}..{EVAL_SEED_START + seeds - 1}; means "
                    f"with 95% t-intervals over the runs. Wall time {wall / 60:.1f} min (runs done before a resume "
                    "not counted).\n")
    atomic_write_text(args.out / "levels.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "levels.json", json.dumps({"levels": result, "wall_s": wall}, indent=2,
                                                           default=str) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    run_script(main, log)
