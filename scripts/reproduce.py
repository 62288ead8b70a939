"""One command per result: the training runs a committed table needs, then the script that makes the table from
them, every part resumable.

    python scripts/reproduce.py --list
    python scripts/reproduce.py heldout_obs_norm                # the README's headline table
    python scripts/reproduce.py phi_grid --parallel 3 --runs runs/reproduce --out runs/phi_grid

A recipe names its training runs (config, `--set`, episodes, the weights a fine-tune starts from) and the
evaluation that turns them into the table. Each run trains into `RUNS/<name>`: one whose checkpoint reached its
episodes is left as it is, one with a checkpoint short of them goes on (`cosim train --resume`), any other starts;
runs that several recipes share train once. `--parallel N` trains N at a time, each with `train.torch_threads=1`
(on 2 cores two runs at once give 1.2x one alone; two threads each fall to a fifth: docs/speed.md). Then the
evaluation script writes into `OUT` (default `RUNS/<recipe>`), itself resumable: a second call plays only what is
missing. Nothing is written into `results/` or `policies/`: compare with the committed report the recipe names.

The recipes are the commands the committed results were made with (each report states its command and machine),
but for `mixed_15k`, `mixed_30k` and the two of the shipped mixed pair (`transfer_mixed`, `demand_mixed`): their
committed runs were made in parts (resumes, and continuations from a float16 snapshot with a fresh optimizer:
docs/results.md), which the recipes train as one run each.
A rerun gives figures within their intervals, not the same bits: bfloat16 forward passes and the order in which
worker processes finish are not bitwise reproducible.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from cosim.errors import CosimError, run_script

log = logging.getLogger("reproduce")
ROOT = Path(__file__).resolve().parents[1]
ANGLES = {"phi0": "0", "pi8": "0.3927", "pi4": "0.7854", "3pi8": "1.1781", "pi2": "1.5708"}
# The console script beside this interpreter: a virtual environment's, whether or not it is activated.
_BESIDE = Path(sys.executable).with_name("cosim")
COSIM = str(_BESIDE) if _BESIDE.is_file() else "cosim"
SEEDS = (15, 16, 17)  # seeds no earlier run used, fixed before the first of these trained
OBS_NORM_SEEDS = (50, 51, 52)  # likewise, for the default with the input standardised
WARMUP_SEEDS = (80, 81, 82, 83, 84, 85)  # likewise, the measurement seeds of the egoistic warm-up


@dataclass(frozen=True)
class Run:
    name: str  # its folder under RUNS
    sets: tuple[str, ...]
    episodes: int
    config: str = "configs/default.yaml"
    init_from: Run | None = None  # the run whose best.pt a fine-tune starts from

    def argv(self, runs: Path, resume: bool) -> list[str]:
        sets = [*self.sets, "train.eval_every=500", "train.torch_threads=1"]
        argv = [COSIM, "train", "--config", str(ROOT / self.config), *(a for s in sets for a in ("--set", s)),
                "--episodes", str(self.episodes), "--out", str(runs / self.name)]
        if resume:
            return [*argv, "--resume"]
        return [*argv, "--init-from", str(runs / self.init_from.name / "best.pt")] if self.init_from else argv


@dataclass(frozen=True)
class Recipe:
    what: str
    report: str  # the committed report it reproduces
    runs: tuple[Run, ...]
    script: str
    args: tuple[str, ...] = ()  # after the run folders; {out} is OUT
    runs_flag: tuple[str, ...] = ()  # before the run folders, where the script takes them as an option

    def evaluation(self, runs: Path, out: Path) -> list[str]:
        folders = [str(runs / r.name) for r in self.runs]
        return [sys.executable, str(ROOT / "scripts" / self.script), *self.runs_flag, *folders,
                *(a.format(out=out) for a in self.args)]


# The committed runs but heldout_obs_norm's and heldout_warmup's trained before configs/default.yaml turned
# train.obs_norm on, and all of them but heldout_warmup's before it turned the egoistic warm-up on.
BEFORE_OBS_NORM = "train.obs_norm=false"
BEFORE_WARMUP = "train.egoistic_episodes=0"


def _default(angle: str, seed: int) -> Run:
    """The default config as it was (the headway cost on, the input not standardised) at one angle and seed, 4,008
    episodes."""
    return Run(f"hw1_{angle}_s{seed}", (f"reward.phi={ANGLES[angle]}", f"train.seed={seed}", BEFORE_OBS_NORM,
                                        BEFORE_WARMUP), 4008)


def _current(angle: str, seed: int) -> Run:
    """configs/default.yaml before the egoistic warm-up (the headway cost on, the input standardised) at one angle and
    seed, 4,008 episodes."""
    return Run(f"on_{angle}_s{seed}", (f"reward.phi={ANGLES[angle]}", f"train.seed={seed}", BEFORE_WARMUP), 4008)


def _mixed(angle: str, seed: int, episodes: int = 4008) -> Run:
    """The default run of the same angle and seed fine-tuned on both merging drivers; at the full budget named as
    its committed snapshots are (`mixfull_*`: the committed `mix30k_*` are the 15,000-episode ones)."""
    name = {4008: "mix", 30000: "mixfull"}.get(episodes, f"mix{episodes // 1000}k")
    return Run(f"{name}_{angle}_s{seed}", (f"reward.phi={ANGLES[angle]}", f"train.seed={seed}", BEFORE_OBS_NORM,
                                           BEFORE_WARMUP), episodes, "configs/mixed_merger.yaml", _default(angle, seed))


def _warmup(seed: int) -> Run:
    """configs/default.yaml with the egoistic warm-up of 504 episodes (named, as the committed runs named it) at pi/4
    and one seed, 2,004 episodes: the halving mark of docs/results.md's "Episodes to a safe policy"."""
    return Run(f"ego504_pi4_s{seed}", (f"reward.phi={ANGLES['pi4']}", f"train.seed={seed}",
                                       "train.egoistic_episodes=504"), 2004)


HELDOUT = ("--shield", "--out", "{out}")
SHIPPED_MIXED = (_mixed("phi0", SEEDS[0], 30000), _mixed("pi4", SEEDS[0], 30000))


def _mixed_longer(episodes: int, what: str) -> Recipe:
    """The mixed fine-tunes of every seed and both angles trained on to `episodes`, 300 held-out episodes with each
    merging driver."""
    return Recipe(f"the same fine-tunes {what}, 300 episodes with each merging driver",
                  f"results/heldout_mixed_{episodes // 1000}k/heldout.md",
                  tuple(_mixed(a, s, episodes) for a in ("phi0", "pi4") for s in SEEDS), "heldout.py",
                  ("--impatient-episodes", "300", *HELDOUT))


RECIPES = {
    "heldout_obs_norm": Recipe(
        "the paper's claims with the default before the egoistic warm-up (the input standardised), three training "
        "seeds per angle, polite and impatient merging vehicle, with and without the shield",
        "results/heldout_obs_norm/heldout.md",
        tuple(_current(a, s) for a in ("phi0", "pi4") for s in OBS_NORM_SEEDS), "heldout.py", HELDOUT),
    "heldout_warmup": Recipe(
        "the default with the egoistic warm-up at pi/4 after 2,004 episodes, six training seeds, polite merging "
        "vehicle",
        "results/heldout_warmup/heldout.md", tuple(_warmup(s) for s in WARMUP_SEEDS), "heldout.py",
        ("--impatient-episodes", "0", "--out", "{out}")),
    "heldout_headway": Recipe(
        "the same before the input was standardised (train.obs_norm off)", "results/heldout_headway/heldout.md",
        tuple(_default(a, s) for a in ("phi0", "pi4") for s in SEEDS), "heldout.py", HELDOUT),
    "phi_grid": Recipe(
        "the trade-off over the SVO angle, one training seed", "results/phi_grid_headway/heldout.md",
        tuple(_default(a, SEEDS[0]) for a in ANGLES), "heldout.py", ("--out", "{out}")),
    "mixed_merger": Recipe(
        "the same claims after fine-tuning on both merging drivers (configs/mixed_merger.yaml)",
        "results/heldout_mixed/heldout.md", tuple(_mixed(a, s) for a in ("phi0", "pi4") for s in SEEDS),
        "heldout.py", HELDOUT),
    "mixed_15k": _mixed_longer(15000, "trained on to 15,000 episodes"),
    "mixed_30k": _mixed_longer(30000, "at the paper's budget of 30,000 episodes"),
    "transfer": Recipe(
        "the first seed of each angle on nets it never saw, beside the baselines", "results/transfer/transfer.md",
        (_default("phi0", SEEDS[0]), _default("pi4", SEEDS[0])), "transfer.py", ("--out", "{out}"), ("--run",)),
    "transfer_mixed": Recipe(
        "the shipped mixed pair (policies/*_mixed: mixed_30k's first seed) on nets it never saw",
        "results/transfer_mixed/transfer.md", SHIPPED_MIXED, "transfer.py", ("--out", "{out}"), ("--run",)),
    "demand_mixed": Recipe(
        "the shipped mixed pair under traffic demand near capacity, 10% and 30% AVs, against all-human traffic",
        "results/headline_mixed/headline.md", SHIPPED_MIXED, "demand_headline.py",
        ("--levels", "near capacity", "--penetrations", "0.1", "0.3", "--out", "{out}")),
}


def _needed(recipe: Recipe) -> list[Run]:
    """The recipe's runs with the runs their fine-tunes start from first."""
    order: list[Run] = []
    for run in recipe.runs:
        for needed in (run.init_from, run):
            if needed is not None and needed not in order:
                order.append(needed)
    return order


def _state(run: Run, runs: Path) -> str:
    """done, partial (a checkpoint short of its episodes) or new."""
    ckpt = runs / run.name / "checkpoint.pt"
    if not ckpt.is_file():
        return "new"
    from agents.checkpoint import read_checkpoint  # torch only here

    return "done" if int(read_checkpoint(ckpt)["counters"]["episodes"]) >= run.episodes else "partial"


def _train(todo: list[Run], partial: set[str], runs: Path, parallel: int) -> None:
    """Train `todo` (dependencies before the runs that start from them), `parallel` at a time; the runs named in
    `partial` resume."""
    pending, live, failed = list(todo), {}, []
    while pending or live:
        names = {r.name for r in pending} | set(live)
        ready = [r for r in pending if not (r.init_from and r.init_from.name in names)]
        while ready and len(live) < parallel:
            run = ready.pop(0)
            pending.remove(run)
            argv = run.argv(runs, resume=run.name in partial)
            (runs / "logs").mkdir(parents=True, exist_ok=True)
            out = (runs / "logs" / f"{run.name}.log").open("a", encoding="utf-8")
            log.info("training %s: %s (log: %s)", run.name, shlex.join(argv), out.name)
            live[run.name] = (subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT), out)
        time.sleep(2)
        for name, (proc, out) in list(live.items()):
            if proc.poll() is not None:
                out.close()
                del live[name]
                if proc.returncode:
                    failed.append(name)
                    pending = [r for r in pending if not (r.init_from and r.init_from.name == name)]
                else:
                    log.info("%s trained", name)
    if failed:
        raise CosimError(f"training failed: {', '.join(failed)} (see {runs / 'logs'}); a second call resumes them")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recipe", nargs="?", choices=sorted(RECIPES), help="the result to reproduce")
    parser.add_argument("--list", action="store_true", help="list the recipes and what each would run")
    parser.add_argument("--runs", type=Path, default=Path("runs/reproduce"), help="where the training runs go")
    parser.add_argument("--parallel", type=int, default=2, help="training runs at once")
    parser.add_argument("--out", type=Path, help="the evaluation's folder (default RUNS/<recipe>)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.parallel < 1:
        raise CosimError(f"--parallel must be >= 1, got {args.parallel}")
    if args.list or args.recipe is None:
        for name, recipe in RECIPES.items():
            print(f"{name}: {recipe.what} ({recipe.report})")
            for run in _needed(recipe):
                print(f"    {shlex.join(run.argv(args.runs, resume=False))}")
            print(f"    then {shlex.join(recipe.evaluation(args.runs, args.out or args.runs / name))}")
        return
    recipe = RECIPES[args.recipe]
    start = time.perf_counter()
    needed = _needed(recipe)
    states = {r.name: _state(r, args.runs) for r in needed}
    todo = [r for r in needed if states[r.name] != "done"]
    log.info("%s: %d training runs, %d to train; then %s", args.recipe, len(needed), len(todo), recipe.script)
    _train(todo, {name for name, state in states.items() if state == "partial"}, args.runs, args.parallel)
    argv = recipe.evaluation(args.runs, args.out or args.runs / args.recipe)
    log.info("evaluating: %s", shlex.join(argv))
    if subprocess.run(argv, check=False).returncode:
        raise CosimError(f"{recipe.script} failed; a second call resumes it")
    log.info("%s reproduced in %.0f s (compare with %s)", args.recipe, time.perf_counter() - start, recipe.report)


if __name__ == "__main__":
    run_script(main, log)
