"""Episodes to a safe policy: for each training run, the first validation (`validation.csv`) at which the criterion
of `agents.validation.meets_criterion` held, with its episodes and wall time.

    python scripts/episodes_to_criterion.py runs/learner/* --out results/learner

The merge reference of altruistic runs (phi > 0; egoistic ones are held to the crash rate alone) is the `courteous`
rule's merge success on the same validation seeds in the run's own setting (net, scenario, drivers, AVs, safety
layer: a run under `av.shield: sumo` is held to the rule under it), evaluated once per setting into
`OUT/courteous_validation_<hash of the setting>/` (resumable). Writes `OUT/criterion.md` (each run, then per
setting the share of its runs that met the criterion, with its interval), `OUT/criterion.json` and
`OUT/learning_curves.png`: training and validation curves, one line per SVO angle and setting (mean over its seeds,
with a band across them), a star where each run first met the criterion.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import shlex
import sys
from pathlib import Path

from agents.checkpoint import first_seed, run_record
from agents.config import train_config
from agents.train import RESUMABLE
from agents.validation import CRASH_HIGH_MAX, CRASH_MAX, MERGE_GAP, meets_criterion
from cosim.config import DEFAULT_CONFIG, VALIDATION_SEED_START, Config, load_config
from cosim.environment.reward import TERMS
from cosim.errors import CosimError, run_script
from cosim.evaluation import plots
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import rate_ci
from cosim.files import VALIDATION_LOG, atomic_write_text, cell_float, read_csv, write_json

log = logging.getLogger("criterion")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/criterion"))
    parser.add_argument("--by", type=int, default=None, metavar="EPISODES",
                        help="sum each setting up by this many episodes (default: the longest any of its runs ran)")
    args = parser.parse_args()
    if args.by is not None and args.by <= 0:
        parser.error(f"--by: a number of episodes above 0, got {args.by}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    runs = [r for r in args.runs if (r / VALIDATION_LOG).is_file()]
    if not runs:
        raise CosimError(f"no run among {[str(r) for r in args.runs]} has a {VALIDATION_LOG} (train.eval_every)")
    first = load_config(runs[0] / "config.yaml")
    default = load_config(DEFAULT_CONFIG)
    references: dict[str, float] = {}

    def reference_of(cfg: Config) -> float:
        key = _setting(cfg)
        if key not in references:
            # Named by the setting, so a later call with its runs in another order resumes the same evaluations.
            folder = f"courteous_validation_{hashlib.sha256(key.encode()).hexdigest()[:8]}"
            references[key] = evaluate(_reference_config(cfg, default), Baseline("courteous"), args.out / folder,
                                       episodes=cfg.train.eval_episodes, seed=VALIDATION_SEED_START,
                                       workers=args.workers, trajectories=0, plots=False
                                       )["metrics"]["merge success [%]"]["mean"]
        return references[key]

    rows = []
    for run in runs:
        cfg = load_config(run / "config.yaml")
        phi = float(cfg.reward.phi)
        reference = reference_of(cfg) if phi > 0 else None  # egoistic runs: no evaluation their criterion ignores
        validations = [{k: cell_float(v) for k, v in r.items()} for r in read_csv(run / VALIDATION_LOG)]
        met = next((v for v in validations if meets_criterion(v, phi, reference)), None)
        last = validations[-1] if validations else {}
        rows.append({"run": str(run), "phi": phi, "seed": cfg.train.seed, "first_seed": first_seed(run),
                     "validations": len(validations),
                     "differs": _differs(cfg, default, run_record(run).get("init_from")),
                     "curve": [(v["episodes"], v["crash"]) for v in validations],
                     "last_validated": last.get("episodes", 0), "merge_reference": reference,
                     "met_at_episodes": met and met["episodes"],
                     "met_at_train_s": met and met["train_s"], "best_crash": min((v["crash"] for v in validations),
                                                                                default=math.nan)})
    lines = ["# Episodes to the criterion", "",
             f"`{shlex.join(['python', *sys.argv])}`", "",
             f"Criterion: validation crash <= {CRASH_MAX:g}% with its upper bound <= {CRASH_HIGH_MAX:g}%; at phi > 0 "
             f"also merge success within {MERGE_GAP:g} points of courteous's on the validation seeds in the run's "
             f"setting ({_references(rows)}).", "",
             "| run | phi | seed | differs from configs/default.yaml | validation crash [%] at [episodes] | "
             "criterion met at [episodes] | [h of training] |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        met = f"not by {r['last_validated']:,.0f}" if r["met_at_episodes"] is None else f"{r['met_at_episodes']:,.0f}"
        hours = "" if r["met_at_train_s"] is None else f"{r['met_at_train_s'] / 3600:.2f}"
        curve = ", ".join(f"{c:.1f} ({e:,.0f})" for e, c in r["curve"])
        seeds = r["seed"] if r["first_seed"] is None else f"{r['first_seed']}, then {r['seed']}"  # a joined run's
        lines.append(f"| {r['run']} | {r['phi']:.4f} | {seeds} | {r['differs'] or 'nothing'} | {curve} | {met} | "
                     f"{hours} |")
    lines += ["", *_summary(rows, args.by)]
    logs = [next((p for p in (run / "episodes.csv", run / "episodes.csv.gz") if p.is_file()), run / "episodes.csv")
            for run in runs]  # a run kept in results/ has its log gzipped (scripts/snapshot_run.py)
    groups: dict[str, list[Path]] = {}
    for log_path, r in zip(logs, rows, strict=True):
        groups.setdefault(_group(r), []).append(log_path)
    met = {log_path: r["met_at_episodes"] for log_path, r in zip(logs, rows, strict=True)
           if r["met_at_episodes"] is not None}
    plots.training_curves(groups, args.out / "learning_curves.png", criterion_met=met,
                          caption=plots.caption_text(plots.short_path(first.net.file),
                                                     [str(r / "config.yaml") for r in runs], [str(r) for r in runs]))
    atomic_write_text(args.out / "criterion.md", "\n".join(lines) + "\n")
    write_json(args.out / "criterion.json", {"runs": rows})
    print("\n".join(lines))


# What the courteous rule's validation episodes depend on.
SETTING = ("net", "sim", "safety", "scenario", "hv", "merger", "merger_alt", "av", "demand")
# SUMO's outputs and the seed are bookkeeping: an evaluation turns the outputs on.
BOOKKEEPING = {"outputs", "output_dir", "seed"}


def _setting(cfg: Config) -> str:
    """The sections of `SETTING` as one canonical string: runs with equal strings share one merge reference."""
    return json.dumps(cfg.model_dump(include=set(SETTING), exclude={s: BOOKKEEPING for s in SETTING}),
                      sort_keys=True, default=str)


def _reference_config(cfg: Config, default: Config) -> Config:
    """The default config with the run's setting (its bookkeeping keys the default's): the courteous rule's episodes
    depend on nothing else, so the runs of one setting share its folder whatever their reward, angle or training (the
    folder's episodes hold returns, and a resumed evaluation must have been made with the same config)."""
    def own(section: str) -> object:
        mine, theirs = getattr(cfg, section), getattr(default, section)
        if mine is None or theirs is None:  # an optional section (demand, merger_alt): nothing to keep apart
            return mine
        return mine.model_copy(update={k: getattr(theirs, k) for k in BOOKKEEPING if k in type(mine).model_fields})

    return default.model_copy(update={section: own(section) for section in SETTING})


def _references(rows: list[dict]) -> str:
    """The merge references in the table's words: one figure where every run shares it, else each with its runs."""
    by_value: dict[float, list[str]] = {}
    for r in (r for r in rows if r["merge_reference"] is not None):
        by_value.setdefault(r["merge_reference"], []).append(Path(r["run"]).name)
    if not by_value:
        return "no run at phi > 0 here"
    if len(by_value) == 1:
        return f"{next(iter(by_value)):.1f}%"
    return "; ".join(f"{v:.1f}% for {', '.join(names)}" for v, names in by_value.items())


def _group(row: dict) -> str:
    """A run's setting as the figure and the summary name it: its SVO angle and what differs from the default."""
    return f"phi={row['phi']:.3f}" + (f", {row['differs']}" if row["differs"] else "")


def _summary(rows: list[dict], by: int | None = None) -> list[str]:
    """Per setting (SVO angle and what differs from the default), how many of its runs met the criterion by `by`
    episodes (default: the longest budget any of them validated at), with a Wilson interval: one run meets it by
    chance where its policy's crash rate is near the bar (200 episodes with 3 crashes pass, 4 fail), so settings are
    compared over seeds. A run that stopped short of the budget without meeting it counts as unmet (said beside the
    count): it might have met it later, so the share is then a lower bound."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(_group(r), []).append(r)
    out = ["| phi | differs from configs/default.yaml | runs | met by [episodes] | of the runs [%] | "
           "half the runs met it by [episodes] |", "|---|---|---|---|---|---|"]
    for group in groups.values():
        phi, differs = group[0]["phi"], group[0]["differs"]
        budget = by or max(r["last_validated"] for r in group)
        hits = [r["met_at_episodes"] is not None and r["met_at_episodes"] <= budget for r in group]
        short = sum(not hit and r["last_validated"] < budget for r, hit in zip(group, hits, strict=True))
        share = rate_ci(hits)
        at = sorted(r["met_at_episodes"] if hit else math.inf for r, hit in zip(group, hits, strict=True))
        half = at[(len(at) + 1) // 2 - 1]  # the fewest episodes by which at least half the runs met it
        out.append(f"| {phi:.4f} | {differs or 'nothing'} | {len(group)}"
                   + (f" ({short} stopped short unmet: at least)" if short else "")
                   + f" | {budget:,.0f} | {sum(hits)} of {len(hits)}: {100 * share.mean:.0f} "
                   f"[{100 * share.low:.0f}, {100 * share.high:.0f}] | "
                   + (f"not by {budget:,.0f}" if math.isinf(half) else f"{half:,.0f}") + " |")
    return out


def _differs(cfg: Config, default: Config, started_from: str | None = None) -> str:
    """The run's settings that are not the default config's (the seed, the SVO angle and the bookkeeping keys
    aside), as KEY=VALUE: a run on both merging drivers differs in its scenario, one with a narrower VelocityMap in
    its observation, one with the impatient merging vehicle in its merger. `started_from`: the policy a run started
    from by `--init-from` as its net.json says (runs from before 2026-12-07 kept train.init_from null in their
    config), which sets it apart as the key does."""
    # What a resume may change is how long and how a run ran, not what it learned with; where it started is.
    ignored = {"seed", *(k.removeprefix("train.") for k in RESUMABLE)} - {"init_from"}
    mine, theirs = train_config(cfg).model_dump(), train_config(default).model_dump()
    if started_from is not None and mine.get("init_from") is None:
        mine["init_from"] = started_from
    out = [f"train.{k}={v}" for k, v in mine.items() if k not in ignored and theirs.get(k) != v]
    out += [f"reward.weights.{k}={getattr(cfg.reward.weights, k)}" for k in TERMS
            if getattr(cfg.reward.weights, k) != getattr(default.reward.weights, k)]
    out += [f"reward.{k}={v}" for k, v in cfg.reward.model_dump(exclude={"phi", "weights"}).items()
            if getattr(default.reward, k) != v]
    # merger_alt is left out: scenario.merger_alt_share says whether a run met it, its config file what it was.
    for section in ("sim", "safety", "scenario", "hv", "merger", "av", "observation", "demand"):
        mine = getattr(cfg, section).model_dump(exclude=BOOKKEEPING)
        theirs = getattr(default, section).model_dump()
        out += [f"{section}.{k}={v}" for k, v in mine.items() if theirs.get(k) != v]
    return " ".join(out)


if __name__ == "__main__":
    run_script(main, log)
