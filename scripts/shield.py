"""The safety layer's effect: baselines and trained policies with and without `av.shield: sumo`, on the same
evaluation seeds, crash, merge success and conflicts side by side.

    python scripts/shield.py --out results/shield                                 # idle and scripted, 200 episodes
    python scripts/shield.py --runs runs/alt --policies idle scripted --out results/shield

Each (policy, shield) pair is one `cosim evaluate` into `OUT/<policy>_<shield>/` (resumable: an interrupted run
continues where it stopped); a trained run plays its best policy by validation (`best.pt`) where it kept one, as
`cosim evaluate --run` does. Writes `OUT/shield.md` (the table, the command, the wall time) and `OUT/shield.json`.
A policy trained without the shield and played with it is a policy under a safety supervisor, as MARL_CAVs' is
used; one trained with it (`--set av.shield=sumo` at training) learns under it.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from pathlib import Path

from cosim.cli import add_config_arguments, config_overrides
from cosim.config import EVAL_SEED_START, SHIELDS, load_config
from cosim.errors import CosimError, run_script
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import format_table
from cosim.files import atomic_write_text, write_json

log = logging.getLogger("shield")

METRICS = ("crash [%]", "merge success [%]", "conflicts [per episode]", "conflicts with the merging vehicle "
           "[per episode]", "hard braking [events per episode]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_arguments(parser, default=None)  # a run plays on its own config.yaml, baselines on the default
    parser.add_argument("--policies", nargs="*", default=["idle", "scripted"], help="baselines to play")
    parser.add_argument("--runs", nargs="*", type=Path, default=[], help="trained run folders to play")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--out", type=Path, default=Path("runs/shield"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    overrides = config_overrides(args)
    players = [(name, Baseline(name), args.config) for name in args.policies]
    if args.runs:
        from agents.checkpoint import TrainedPolicy, describe_checkpoint, find_checkpoint  # torch only for runs

        for run in args.runs:
            if not (run / "config.yaml").is_file():
                raise CosimError(f"--runs {run}: not a training run folder (no config.yaml)")
            played = find_checkpoint(run, None)
            log.info("%s: %s", run.name, describe_checkpoint(played))
            players.append((run.name, TrainedPolicy(str(played)), args.config or run / "config.yaml"))
    start = time.perf_counter()
    summaries, episodes = {}, {}
    for label, policy, config in players:
        for shield in SHIELDS:
            cfg = load_config(config or "configs/default.yaml", [*overrides, f"av.shield={shield}"])
            name = f"{label}, shield {shield}"
            summary = evaluate(cfg, policy, args.out / f"{label}_{shield}", episodes=args.episodes, seed=args.seed,
                               workers=args.workers, trajectories=0, plots=False)
            summaries[name] = {m: summary["metrics"][m] for m in METRICS if m in summary["metrics"]}
            episodes[name] = summary["episodes"]
    wall = time.perf_counter() - start
    table = format_table(summaries, episodes, markdown=True)
    command = shlex.join(["python", *sys.argv])
    atomic_write_text(args.out / "shield.md", f"# The safety layer (av.shield)\n\n`{command}`, {wall:.0f} s\n\n"
                      f"{table}\n")
    write_json(args.out / "shield.json", {"command": command, "wall_s": wall, "summaries": summaries})
    print(table)


if __name__ == "__main__":
    run_script(main, log)
