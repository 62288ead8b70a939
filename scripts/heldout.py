"""The paper's claims on held-out episodes: trained runs at two SVO angles over several training seeds, with the
polite and the impatient merging vehicle, with and without the safety layer, beside the `courteous` rule.

    python scripts/heldout.py results/learner/base_phi0_s1 results/learner/base_pi4_s1 ... --out results/heldout

Each (player, merging vehicle, shield) is one `cosim evaluate` into `OUT/<merger>_<shield>/<player>/` on the same
evaluation seeds (10,000,000 on: disjoint from training and validation), resumable: a second call plays only the
episodes missing. A run plays its `best.pt` (its best validation), as `cosim evaluate --run` does (`--last`: its
final `policy.pt`, what its whole training made of it, as `cosim evaluate --last`), on its own
config with only the merging vehicle (the run's own `merger:`, or `configs/impatient.yaml`'s, alone: a run trained on
a mix of merging drivers, `configs/mixed_merger.yaml`, meets each in turn) and the shield changed.
Writes `OUT/heldout.md` (per seed, pooled over the seeds of each angle, the claims' checks, the command, the wall
time) and `OUT/heldout.json`. Rates carry Wilson intervals, per-episode measures t-intervals.
"""

from __future__ import annotations

import argparse
import logging
import math
import shlex
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import yaml

from cosim.config import EVAL_SEED_START, load_config
from cosim.errors import CosimError, run_script
from cosim.evaluation import plots
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import format_table, summarize
from cosim.evaluation.store import seed_rows
from cosim.files import atomic_write_text, write_json

log = logging.getLogger("heldout")

METRICS = ("crash [%]", "merge success [%]", "merger distance [m]", "mean distance [m]", "throughput [veh/h]",
           "conflicts [per episode]", "conflicts with the merging vehicle [per episode]",
           "hard braking [events per episode]")
IMPATIENT = Path(__file__).resolve().parents[1] / "configs" / "impatient.yaml"
CRASH_MAX, CRASH_HIGH_MAX = 2.0, 4.0  # [%] the science issue's bar: pooled crash, and its upper bound


def merger_overrides(name: str) -> list[str]:
    """The `--set` lines that give a run's config the merging vehicle `name` alone (polite: the run's own `merger`),
    whatever mix of merging drivers it trained on (`scenario.merger_alt_share`)."""
    alone = ["scenario.merger_alt_share=0"]
    if name == "polite":
        return alone
    merger = yaml.safe_load(IMPATIENT.read_text())["merger"]
    return [*alone, *(f"merger.{key}={yaml.safe_dump(value, default_flow_style=True).strip()}"
                      for key, value in merger.items())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders (their config.yaml and best.pt)")
    parser.add_argument("--episodes", type=int, default=300, help="episodes per player with the polite merger")
    parser.add_argument("--impatient-episodes", type=int, default=100, help="... with the impatient one (0: none)")
    parser.add_argument("--shield", action="store_true", help="also every player with av.shield=sumo")
    parser.add_argument("--last", action="store_true", help="each run's final policy.pt, not its best.pt")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/heldout"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    from agents.checkpoint import TrainedPolicy, find_checkpoint, first_seed  # torch only here

    runs = {}
    for run in args.runs:
        if not (run / "config.yaml").is_file():
            raise CosimError(f"{run}: not a training run folder (no config.yaml)")
        cfg = load_config(run / "config.yaml")
        first = first_seed(run)  # a run joined onto the one it continues goes by its first part's seed
        runs[run] = (float(cfg.reward.phi), int(cfg.train.seed) if first is None else first)
    played = {run: find_checkpoint(run, None, last=args.last) for run in runs}
    mergers = {"polite": args.episodes, **({"impatient": args.impatient_episodes} if args.impatient_episodes else {})}
    shields = ["none", "sumo"] if args.shield else ["none"]
    start = time.perf_counter()
    rows: dict[tuple[str, str, str], list[dict[str, Any]]] = {}  # (merger, shield, player) -> its episodes
    for merger, episodes in mergers.items():
        for shield in shields:
            sets = [*merger_overrides(merger), f"av.shield={shield}"]
            # The rule plays on the first run's config: the runs differ in their angle and seed only.
            players: list[tuple[str, Any, Path]] = [("courteous", Baseline("courteous"), args.runs[0])]
            players += [(run.name, TrainedPolicy(str(played[run])), run) for run in runs]
            for name, policy, run in players:
                out = args.out / f"{merger}_{shield}" / name
                log.info("%s merger, shield %s: %s, %d episodes", merger, shield, name, episodes)
                evaluate(load_config(run / "config.yaml", sets), policy, out, episodes=episodes, seed=EVAL_SEED_START,
                         workers=args.workers, trajectories=0, plots=False, overrides=sets)
                rows[(merger, shield, name)] = seed_rows(out, EVAL_SEED_START, episodes)
    wall = time.perf_counter() - start
    command = shlex.join(["python", *sys.argv])
    files = sorted({path.name for path in played.values()})
    lines = ["# The paper's claims on held-out episodes", "",
             f"`{command}`, {wall:.0f} s; each run plays its {' or '.join(files)}", ""]
    result: dict[str, Any] = {"command": command, "wall_s": wall, "runs": {str(r): v for r, v in runs.items()},
                              "played": {str(r): str(path) for r, path in played.items()}}
    for merger in mergers:
        for shield in shields:
            key = f"{merger}_{shield}"
            lines += [f"## {merger.capitalize()} merging vehicle, shield {shield}", ""]
            part = {name: r for (m, s, name), r in rows.items() if (m, s) == (merger, shield)}
            by_phi: dict[float, list[dict[str, Any]]] = defaultdict(list)
            for run, (phi, _) in runs.items():
                by_phi[phi] += part[run.name]
            seeds = {phi: sum(p == phi for p, _ in runs.values()) for phi in by_phi}
            pooled = {phi: f"phi {phi:.4f}, {seeds[phi]} seeds pooled" for phi in sorted(by_phi)}
            part.update({pooled[phi]: r for phi, r in sorted(by_phi.items())})
            tables = {name: summarize(r) for name, r in part.items()}
            if len(by_phi) > 2:  # an angle grid: its trade-off at a glance
                figure = plots.over_phi({phi: tables[name] for phi, name in pooled.items()}, METRICS,
                                        args.out / f"{key}_over_phi.png", {"courteous": tables["courteous"]},
                                        caption=plots.caption_text(
                                            plots.short_path(load_config(args.runs[0] / "config.yaml").net.file),
                                            [str(r / "config.yaml") for r in runs], [str(r) for r in runs]),
                                        title=f"Trained AVs over the SVO angle, {merger} merging vehicle, shield "
                                              f"{shield}: mean with its 95% interval (pooled over seeds)")
                lines += [f"![The trade-off over the SVO angle]({figure.name})", ""]
            episodes = {name: len(r) for name, r in part.items()}
            shown = {name: {m: t[m] for m in METRICS if m in t} for name, t in tables.items()}
            lines += [format_table(shown, episodes, markdown=True), ""]
            checks = claims(runs, tables)
            lines += [f"- {c}" for c in checks] + [""]
            result[key] = {"summaries": shown, "episodes": episodes, "claims": checks}
    atomic_write_text(args.out / "heldout.md", "\n".join(lines))
    write_json(args.out / "heldout.json", result)
    print("\n".join(lines))


def claims(runs: dict[Path, tuple[float, int]], tables: dict[str, dict[str, dict[str, float]]]) -> list[str]:
    """The science issue's checks on one (merger, shield) part: each angle's pooled crash against the bar, and on
    every training seed the altruistic AVs' merge success above the egoistic ones' with the intervals apart."""
    out = []
    for name, t in tables.items():
        if "pooled" in name:
            c = t["crash [%]"]
            ok = c["mean"] <= CRASH_MAX and c["ci_high"] <= CRASH_HIGH_MAX
            out.append(f"{name}: crash {c['mean']:.2f}% [{c['ci_low']:.2f}, {c['ci_high']:.2f}]: "
                       f"{'holds' if ok else 'fails'} (<= {CRASH_MAX}% with the upper bound <= {CRASH_HIGH_MAX}%)")
    phis = sorted({phi for phi, _ in runs.values()})
    if len(phis) >= 2:
        # The paper's pair: phi 0 against pi/4 where a grid holds it, else the smallest against the largest angle.
        ego, alt = phis[0], next((p for p in phis if abs(p - math.pi / 4) < 1e-3), phis[-1])
        for seed in sorted({s for _, s in runs.values()}):
            pair = {phi: next((r.name for r, ps in runs.items() if ps == (phi, seed)), None) for phi in (ego, alt)}
            if None in pair.values():
                continue
            e, a = (tables[pair[p]]["merge success [%]"] for p in (ego, alt))
            apart = a["ci_low"] > e["ci_high"]
            out.append(f"seed {seed}: merge success {a['mean']:.1f}% [{a['ci_low']:.1f}, {a['ci_high']:.1f}] at phi "
                       f"{alt:.4f} vs {e['mean']:.1f}% [{e['ci_low']:.1f}, {e['ci_high']:.1f}] at phi {ego:.4f}: "
                       f"{'holds (intervals apart)' if apart else 'fails' if a['mean'] <= e['mean'] else 'overlaps'}")
    return out


if __name__ == "__main__":
    run_script(main, log)
