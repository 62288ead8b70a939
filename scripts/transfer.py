"""Trained policies on nets they never saw, beside the baselines there: merge success and crash, 95% intervals.

    python scripts/transfer.py --run policies/egoistic policies/altruistic --out results/transfer

Builds each shape (sumo_net/shapes.py) into OUT/nets/ (its description removed: the roles are inferred, as for
a user's own net), then evaluates each run's policy (a run folder or a shipped policy, labelled by its folder's
name, on its own config, on each net in turn) and the baselines `idle`, `scripted`, `courteous`, `sumo` on the
runs' own net and on each built net, all on the same evaluation seeds (the baselines on the first run's config).
Every evaluation resumes where an interrupted one stopped. Writes OUT/transfer.md (the table, the nets, the wall
time) and OUT/transfer.json.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from pathlib import Path

from cosim.config import EVAL_SEED_START, load_config
from cosim.errors import CosimError, run_script
from cosim.evaluation.checknet import POLICIES
from cosim.evaluation.plots import short_path
from cosim.evaluation.runner import Baseline, evaluate
from cosim.files import atomic_write_text, write_json
from cosim.sumo.net import load_net, net_summary, summary_lines
from sumo_net.shapes import SHAPES, build_shape

log = logging.getLogger("transfer")
METRICS = ("merge success [%]", "crash [%]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, nargs="+", required=True,
                        help="training run folders or shipped policies (config.yaml and a checkpoint), on one net")
    parser.add_argument("--shapes", nargs="+", choices=sorted(SHAPES), default=["curved", "two_lane_ramp",
                                                                                 "lane_drop"])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--out", type=Path, default=Path("runs/transfer"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    from agents.checkpoint import TrainedPolicy, describe_checkpoint, find_checkpoint  # torch only once checked

    t0 = time.perf_counter()
    runs = {run.resolve().name: run for run in args.run}
    if len(runs) < len(args.run) or set(runs) & set(POLICIES):
        raise CosimError(f"--run: {[str(r) for r in args.run]}: each run is labelled by its folder's name, so the "
                         f"names must differ from each other and from the baselines {list(POLICIES)}")
    configs = {label: load_config(run / "config.yaml") for label, run in runs.items()}
    own = {Path(c.net.file).resolve() for c in configs.values()}
    if len(own) > 1:
        raise CosimError(f"--run: the runs trained on different nets ({sorted(map(str, own))}); give runs of one net")
    nets = {"own": own.pop()}
    for shape in args.shapes:
        net = args.out / "nets" / shape / f"{shape}.net.xml"
        if not net.is_file():
            net = build_shape(shape, net.parent)
            net.with_name(f"{shape}.yaml").unlink()
        nets[shape] = net
    trained = {}
    for label, run in runs.items():
        played = find_checkpoint(run, None)
        log.info("%s: %s", label, describe_checkpoint(played))
        trained[label] = TrainedPolicy(str(played), greedy=True)
    labels = [*runs, *POLICIES]
    results: dict[str, dict[str, dict]] = {}
    for name, net in nets.items():
        for label in labels:
            run_cfg = configs.get(label, next(iter(configs.values())))
            cfg = load_config(run_cfg, [f"net.file={net.resolve()}", "net.description=null"])
            policy = trained[label] if label in trained else Baseline(label)
            summary = evaluate(cfg, policy, args.out / name / label, episodes=args.episodes, seed=args.seed,
                               workers=args.workers, trajectories=0, plots=False)
            results.setdefault(name, {})[label] = {m: summary["metrics"][m] for m in METRICS}
            log.info("%s on %s: merge %.1f%%, crash %.1f%%", label, name, *(results[name][label][m]["mean"]
                                                                          for m in METRICS))
    wall = time.perf_counter() - t0
    lines = [f"# Transfer: {', '.join(map(str, args.run))} on nets they never saw", "",
             f"`{shlex.join(['python', *sys.argv])}`", "",
             f"Merge success and crash [%], mean [95% Wilson interval], {args.episodes} episodes each on evaluation "
             f"seeds {args.seed}..{args.seed + args.episodes - 1}; each run's policy played greedily, trained on "
             f"`{short_path(nets['own'])}`. Wall time {wall:.0f} s (episodes done before a resume not counted).", "",
             "| net | metric | " + " | ".join(labels) + " |", "|---|---|" + "---|" * len(labels)]
    for name in nets:
        for m in METRICS:
            cells = [f"{results[name][p][m]['mean']:.1f} [{results[name][p][m]['ci_low']:.1f}, "
                     f"{results[name][p][m]['ci_high']:.1f}]" for p in labels]
            lines.append(f"| {name} | {m} | " + " | ".join(cells) + " |")
    lines += ["", "The nets:", ""]
    for name, net in nets.items():
        lines += [f"- **{name}**: " + "; ".join(summary_lines(net_summary(load_net(net)))[1:5])]
    atomic_write_text(args.out / "transfer.md", "\n".join(lines) + "\n")
    write_json(args.out / "transfer.json", {"runs": {k: str(v) for k, v in runs.items()},
                                            "nets": {k: str(v) for k, v in nets.items()}, "results": results,
                                            "wall_s": wall})
    print("\n".join(lines))


if __name__ == "__main__":
    run_script(main, log)
