"""Is the scenario a merge dilemma? The baselines on the same evaluation seeds, with 95% intervals.

    python scripts/calibrate_scenario.py                                  # configs/default.yaml, 200 episodes each
    python scripts/calibrate_scenario.py --net my_merge/merge.net.xml --out runs/calibration_2lane

Runs `cosim evaluate` for the `idle`, `scripted`, `courteous` and `sumo` baselines (resumable: an interrupted run
continues where it stopped) and writes `OUT/calibration.md` (the table and the verdict on each target) and
`OUT/calibration.json`. The targets, on the default scenario: idle and scripted AVs let the merging vehicle in
at most 60% of the time; courteous AVs at least 90%, crashing at most 10%; scripted AVs crash at most 15% (a
careful policy avoids the crashes: they do not come from the placement); SUMO-driven AVs never crash.

The dilemma in reward terms: the same baselines on the same seeds are scored under the SVO reward of each
`--phis` angle (the AVs' mean undiscounted return, `av_return`; the config's own angle from the episodes
above, every other one by running them again), and each other baseline's return is
compared with the gap-opening `courteous` one episode by episode (paired differences, 95% t-intervals). A
dilemma needs courteous AVs to earn less than another baseline when egoistic (phi = 0: letting the merging
vehicle in costs them) and more than every other one when altruistic (phi = pi/4: it pays).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from cosim.cli import add_config_arguments, config_overrides
from cosim.config import EVAL_SEED_START, load_config
from cosim.errors import run_script
from cosim.evaluation.checknet import POLICIES, targets_met
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import format_table, mean_ci
from cosim.evaluation.store import seed_rows
from cosim.files import atomic_write_text

log = logging.getLogger("calibrate")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_arguments(parser)  # --config, --set, --net as in every cosim command
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    parser.add_argument("--phis", type=float, nargs="*", default=[0.0, 0.7854], metavar="RAD",
                        help="SVO angles to score the baselines' returns under (none: skip)")
    parser.add_argument("--out", type=Path, default=Path("runs/calibration"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    overrides = config_overrides(args)
    cfg = load_config(args.config, overrides)
    summaries, walls = {}, {}
    for name in args.policies:
        t0 = time.perf_counter()
        summaries[name] = evaluate(cfg, Baseline(name), args.out / name, episodes=args.episodes, seed=args.seed,
                                   workers=args.workers, trajectories=0, plots=False)
        walls[name] = time.perf_counter() - t0
        log.info("%s: %d episodes in %.0f s", name, summaries[name]["episodes"], walls[name])
    table = format_table({k: v["metrics"] for k, v in summaries.items()},
                         {k: v["episodes"] for k, v in summaries.items()}, markdown=True)
    verdicts = targets_met(summaries)
    lines = [f"# Scenario calibration: {cfg.net.file}", "",
             f"Config `{args.config}`{' with ' + ', '.join(overrides) if overrides else ''}; evaluation seeds "
             f"{args.seed}..{args.seed + args.episodes - 1}, the same for every policy. Wall time of this run "
             "(episodes done before a resume not counted): "
             + ", ".join(f"{k} {v:.0f} s" for k, v in walls.items()) + ".", "", table, "",
             "| target | mean [95% CI] | met |", "|---|---|---|"]
    lines += [f"| {v['target']} | {v['mean']:.1f} [{v['ci'][0]:.1f}, {v['ci'][1]:.1f}] | "
              f"{'yes' if v['met'] else 'NO'} |" for v in verdicts]
    incentives = [returns_under(args, overrides, phi, walls, cfg.reward.phi) for phi in args.phis]
    if incentives:
        others = list(incentives[0]["courteous_minus"])
        lines += ["", "AVs' mean return under the SVO reward (undiscounted, per episode), and courteous minus each "
                  "other baseline, paired by seed (mean [95% CI]):", "",
                  "| phi | " + " | ".join([*args.policies, *(f"courteous - {p}" for p in others)]) + " |",
                  "|---" * (1 + len(args.policies) + len(others)) + "|"]
        lines += [f"| {r['phi']:.4f} | " + " | ".join([*(f"{r['return'][p]:.2f}" for p in args.policies),
                                                     *(_cell(r["courteous_minus"][p]) for p in others)]) + " |"
                  for r in incentives]
        lines.append("")
        for r in incentives:
            if not r["courteous_minus"]:
                continue
            highs = [ci["ci_high"] for ci in r["courteous_minus"].values()]
            lows = [ci["ci_low"] for ci in r["courteous_minus"].values()]
            # Egoistic: some baseline out-earns courteous; otherwise courteous out-earns every other one.
            want, met = ("below another", min(highs) < 0) if r["phi"] == 0 else ("above all", min(lows) > 0)
            verdicts.append({"target": f"courteous: return at phi {r['phi']:.4f} {want}", "met": bool(met)})
            lines.append(f"- phi {r['phi']:.4f}: courteous AVs' return {want} (95% CI of the paired difference "
                         f"apart from 0): {'yes' if met else 'NO'}")
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "calibration.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "calibration.json", json.dumps({"summaries": summaries, "targets": verdicts,
                                                                "returns": incentives, "wall_s": walls},
                                                               indent=2, default=str) + "\n")
    print("\n".join(lines))


def returns_under(args: argparse.Namespace, overrides: list[str], phi: float, walls: dict[str, float],
                  config_phi: float) -> dict:
    """Every policy's per-episode AV return with the reward at `phi`, and courteous minus each other, paired."""
    cfg = load_config(args.config, [*overrides, f"reward.phi={phi}"])
    # The config's own angle was scored by the merge-rate table's episodes: the same seeds, the same reward.
    own = math.isclose(phi, config_phi)
    returns = {}
    for name in args.policies:
        out = args.out / name if own else args.out / f"returns_phi_{phi:.4f}" / name
        if not own:
            t0 = time.perf_counter()
            evaluate(cfg, Baseline(name), out, episodes=args.episodes, seed=args.seed, workers=args.workers,
                     trajectories=0, plots=False)
            walls[f"{name} at phi {phi:.4f}"] = time.perf_counter() - t0
        returns[name] = np.array([float(r["av_return"]) for r in seed_rows(out, args.seed, args.episodes)])
    minus = {} if "courteous" not in returns else {
        p: mean_ci(returns["courteous"] - r).as_dict() for p, r in returns.items() if p != "courteous"}
    return {"phi": phi, "return": {p: float(r.mean()) for p, r in returns.items()}, "courteous_minus": minus}


def _cell(ci: dict) -> str:
    return f"{ci['mean']:+.2f} [{ci['ci_low']:+.2f}, {ci['ci_high']:+.2f}]"


if __name__ == "__main__":
    run_script(main, log)
