"""Is the scenario a merge dilemma? The baselines on the same evaluation seeds, with 95% intervals.

    python scripts/calibrate_scenario.py                                  # configs/default.yaml, 200 episodes each
    python scripts/calibrate_scenario.py --net my_merge/merge.net.xml --out runs/calibration_2lane

Runs `cosim evaluate` for the `idle`, `scripted`, `courteous` and `sumo` baselines (resumable: an interrupted run
continues where it stopped) and writes `OUT/calibration.md` (the table and the verdict on each target) and
`OUT/calibration.json`. The targets, on the default scenario: idle and scripted AVs let the merging vehicle in
at most 60% of the time; courteous AVs at least 90%, crashing at most 10%; scripted AVs crash at most 15% (a
careful policy avoids the crashes: they do not come from the placement); SUMO-driven AVs never crash.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

from cosim.config import EVAL_SEED_START, load_config
from cosim.errors import CosimError
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import format_table
from cosim.files import atomic_write_text

log = logging.getLogger("calibrate")

POLICIES = ("idle", "scripted", "courteous", "sumo")
# (policy, metric, bound, test on the interval's mean) for the default scenario.
TARGETS: list[tuple[str, str, str, Callable[[float], bool]]] = [
    ("idle", "merge success [%]", "<= 60", lambda m: m <= 60.0),
    ("scripted", "merge success [%]", "<= 60", lambda m: m <= 60.0),
    ("courteous", "merge success [%]", ">= 90", lambda m: m >= 90.0),
    ("courteous", "crash [%]", "<= 10", lambda m: m <= 10.0),
    ("scripted", "crash [%]", "<= 15", lambda m: m <= 15.0),
    ("sumo", "crash [%]", "== 0", lambda m: m == 0.0),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--net", type=Path, default=None, help="another .net.xml (description beside it or inferred)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    parser.add_argument("--out", type=Path, default=Path("runs/calibration"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    overrides = list(args.overrides)
    if args.net is not None:
        overrides += [f"net.file={args.net.resolve()}", "net.description=null"]
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
    verdicts = []
    for policy, metric, bound, ok in TARGETS:
        if policy in summaries:
            m = summaries[policy]["metrics"][metric]
            verdicts.append({"policy": policy, "metric": metric, "target": bound, "mean": m["mean"],
                             "ci": [m["ci_low"], m["ci_high"]], "met": bool(ok(m["mean"]))})
    lines = [f"# Scenario calibration: {cfg.net.file}", "",
             f"Config `{args.config}`{' with ' + ', '.join(overrides) if overrides else ''}; evaluation seeds "
             f"{args.seed}..{args.seed + args.episodes - 1}, the same for every policy. Wall time of this run "
             "(episodes done before a resume not counted): "
             + ", ".join(f"{k} {v:.0f} s" for k, v in walls.items()) + ".", "", table, "",
             "| target | mean [95% CI] | met |", "|---|---|---|"]
    lines += [f"| {v['policy']}: {v['metric']} {v['target']} | {v['mean']:.1f} [{v['ci'][0]:.1f}, {v['ci'][1]:.1f}] "
              f"| {'yes' if v['met'] else 'NO'} |" for v in verdicts]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "calibration.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "calibration.json", json.dumps({"summaries": summaries, "targets": verdicts,
                                                                "wall_s": walls}, indent=2, default=str) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    try:
        main()
    except CosimError as exc:  # bad input: one line, as from the cosim command
        log.error("%s", exc)
        sys.exit(2)
