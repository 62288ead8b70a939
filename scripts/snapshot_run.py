"""A training run's progress, small enough for the repository: what a new machine needs to see where a run stands
and to go on from it, without the resumable checkpoint (optimizer state, tens of MB).

    python scripts/snapshot_run.py runs/learner/base_pi4_s1 --out results/learner/base_pi4_s1
    python scripts/snapshot_run.py runs/learner/mix_phi0_s16b --continues results/learner/tuning/mix_phi0_s16 \
        --out results/learner/tuning/mix30k_phi0_s16

Copies `config.yaml` (its net's paths made relative to OUT, so that a clone of the repository anywhere finds the net
the run trained on: a run writes them absolute), `net.json`, `config_changes.yaml`, `updates.csv`, `validation.csv`
and `episodes.csv` (gzipped), and writes `policy.pt` and `best.pt` with float16 weights
(`agents.checkpoint.export_policy`). Where the
run folder itself is gone, `cosim train --init-from OUT/policy.pt` is not a resume: it starts a new run from these
weights with a fresh optimizer and value normaliser (say so beside any figure).

OUT is written whole or not at all: the snapshot is made in a folder beside it and moved in once complete, so a
failed snapshot (a refused join, a full disk) leaves an earlier one in OUT as it was; files in OUT that are not a
snapshot's stay.

`--continues START` snapshots such a run as the continuation of START (the snapshot whose `policy.pt` it started from;
its config the same but for `train.seed`, which a continuation changes so as not to replay START's training episodes,
and the keys a resume may change): START's logs come first, RUN's follow with their counts (updates, episodes, samples,
training time) running on from START's, the validation log's `best` marks are redone over both parts by training's rule
(`agents.validation.better`), `best.pt` is the better part's, the policy files' counters count both parts, the
config and `net.json` name the policy the first part started from (none from scratch), and `net.json` says where the
parts meet (`continues`; a third part joined onto a joined snapshot keeps the record of the
join before it, and the first part's training seed); OUT must be another folder than START. Validation curves, the
episodes to the criterion and held-out evaluations then read the snapshot as one run. Runs under demand are not joined
(their `best.pt` also weighs the flow offered).
"""

from __future__ import annotations

import argparse
import gzip
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import yaml

from agents.checkpoint import BEST_NAME, NET_RECORD, POLICY_NAME, export_policy, first_seed, load_policy, run_record
from agents.train import RESUMABLE, flat_keys
from agents.validation import better
from cosim.config import load_config
from cosim.config.loading import FILE_KEYS
from cosim.errors import CosimError, run_script
from cosim.files import VALIDATION_LOG, atomic_write_text, cell_float, read_csv, write_csv, write_json

log = logging.getLogger("snapshot")

COPIED = (NET_RECORD, "config_changes.yaml", "updates.csv", VALIDATION_LOG)
# What a continuation may change besides what a resume may: the seed of its training episodes.
CONTINUATION_KEYS = RESUMABLE | {"train.seed"}
# The columns of each log that count from the run's start, and the policy file's counter each continues.
_COUNTS = {"update": "updates", "episodes": "episodes", "samples": "samples", "train_s": "train_s"}
RUNNING_ON = {"updates.csv": {**_COUNTS, "restarts": "restarts"}, VALIDATION_LOG: _COUNTS,
              "episodes.csv.gz": {"episode": "episodes", "update": "updates"}}


def portable_config(config: Path, out: Path, **train: Any) -> None:
    """`config` (a run's config.yaml), with `train`'s keys set in its train section, written into `out` with the
    paths it names (`FILE_KEYS`: the net, the policy it started from) relative to `out` (`cosim.config.load_config`
    reads them relative to the file's folder)."""
    data = yaml.safe_load(config.read_text(encoding="utf-8"))
    if train:
        data["train"].update(train)
    for section, key in FILE_KEYS:
        if data.get(section, {}).get(key):
            data[section][key] = os.path.relpath(Path(data[section][key]).resolve(), out.resolve())
    atomic_write_text(out / "config.yaml", yaml.safe_dump(data, sort_keys=False))


def start_counters(run: Path, start: Path) -> dict[str, float]:
    """The counters of `start`'s policy file, once `run` is known to continue it (module doc) and both parts to have
    what the join takes; `CosimError` naming what is wrong otherwise."""
    began = run_record(run).get("init_from")
    if began is None or Path(began).resolve() != (start / POLICY_NAME).resolve():
        raise CosimError(f"--continues {start}: {run} started from {began or 'scratch'}, not from "
                         f"{start / POLICY_NAME}; pass the snapshot it was trained on from (cosim train --init-from), "
                         f"and run this in the folder training ran in ({NET_RECORD} keeps the path as it was given)")
    first = load_config(start / "config.yaml")
    old, new = (flat_keys(cfg.to_dict()) for cfg in (first, load_config(run / "config.yaml")))
    changed = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k) and k not in CONTINUATION_KEYS)
    if changed:
        raise CosimError(f"--continues {start}: {run} trains another config ({', '.join(changed)} differ); a "
                         f"continuation may change only train.seed and what a resume may")
    if first.demand.enabled:
        raise CosimError(f"--continues {start}: runs under demand are not joined (their best.pt also weighs the flow "
                         "offered); snapshot the run alone")
    for folder in (start, run):
        if read_csv(folder / VALIDATION_LOG) and not (folder / BEST_NAME).is_file():
            raise CosimError(f"--continues {start}: {folder} has validations but no {BEST_NAME} to join")
    return {k: float(v) for k, v in load_policy(start / POLICY_NAME)[1]["counters"].items()}


def _joined(first: list[dict[str, Any]], then: list[dict[str, Any]], columns: dict[str, str],
            counters: dict[str, float]) -> list[dict[str, Any]]:
    """`first`'s rows up to `counters` (a snapshot's logs may run past its policy file), then `then`'s with the
    `columns` counting on from `counters`."""
    kept = [r for r in first if all(cell_float(r[c]) <= counters[k] for c, k in columns.items()
                                    if c in r and k != "train_s")]  # time is no count: validation adds to it
    moved = [{**r, **{c: _plus(r[c], counters[k]) for c, k in columns.items() if c in r}} for r in then]
    return kept + moved


def _plus(cell: str, offset: float) -> int | float:
    """A count of the continuation counted on from its start's (an integer stays one)."""
    value = cell_float(cell) + offset
    return int(value) if value.is_integer() else value


def _rebest(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Mark the rows that training's rule would have kept as best.pt over both parts; the last such row, as
    training keeps it in best.pt (its counts integers)."""
    best = None
    for row in rows:
        fig = {k: cell_float(v) for k, v in row.items()}
        row["best"] = int(better(fig, best))
        if row["best"]:
            best = {**fig, **{k: int(fig[k]) for k in ("update", "episodes", "samples")}, "best": 1}
    return best


def join(run: Path, start: Path, out: Path, counters: dict[str, float]) -> None:
    """OUT (RUN's snapshot) as the continuation of `start`, whose policy file's `counters` RUN began from (module
    doc)."""
    best = None
    for name, columns in RUNNING_ON.items():
        theirs = start / name if (start / name).is_file() else start / name.removesuffix(".gz")  # a run folder's
        before, ours = read_csv(theirs), read_csv(out / name)
        rows = _joined(before, ours, columns, counters)
        if name == VALIDATION_LOG:
            best = _rebest(rows)
        # A newer part's log may have columns an older one lacks (left empty there).
        write_csv(out / name, rows, list(dict.fromkeys(k for r in (ours[:1] + before[:1]) for k in r)))
    _join_changes(start / "config_changes.yaml", out / "config_changes.yaml", int(counters["updates"]))
    export_policy(run / POLICY_NAME, out / POLICY_NAME, counters=_counted_on(run / POLICY_NAME, counters))
    if best is not None:
        earlier = best["episodes"] <= counters["episodes"]  # START's best.pt stays the best
        part, episode = (start, best["episodes"]) if earlier else (run, best["episodes"] - counters["episodes"])
        kept = load_policy(part / BEST_NAME)[1]["validation"] or {}
        if kept.get("episodes") != episode:
            raise CosimError(f"--continues {start}: {part / BEST_NAME} is from episode {kept.get('episodes')}, not "
                             f"from the validation training's rule picks in {part / VALIDATION_LOG} (episode "
                             f"{episode:.0f}; a snapshot taken while training went on?): snapshot that run again")
        if earlier:
            export_policy(start / BEST_NAME, out / BEST_NAME)
        else:
            export_policy(run / BEST_NAME, out / BEST_NAME, counters=_counted_on(run / BEST_NAME, counters),
                          validation=best)
    # The joined run began where its first part did: from scratch, or from the policy that part started from.
    first_cfg, first_record = load_config(start / "config.yaml"), run_record(start)
    portable_config(run / "config.yaml", out, init_from=first_cfg.train.init_from)
    record = run_record(out)
    record.pop("init_from", None)
    if first_record.get("init_from") is not None:
        record["init_from"] = first_record["init_from"]
    first = first_seed(start)
    record["continues"] = {"snapshot": os.path.relpath(start.resolve(), out.resolve()), "at": _counts(counters),
                           "train_seed": first_cfg.train.seed if first is None else first,
                           "fresh": "optimizer and value normaliser (a start from a policy file, not a resume)",
                           "before": first_record.get("continues")}
    write_json(out / NET_RECORD, record)


def _counted_on(policy: Path, counters: dict[str, float]) -> dict[str, int | float]:
    """The counters of a continuation's policy file counted on from its start's `counters`."""
    own = load_policy(policy)[1]["counters"]
    return _counts({k: counters[k] + float(v) for k, v in own.items() if k in counters})


def _counts(counters: dict[str, float]) -> dict[str, int | float]:
    """Counters as a policy file keeps them: counts as integers, the training time in seconds."""
    return {k: v if k == "train_s" else int(v) for k, v in counters.items()}


def _join_changes(before: Path, ours: Path, updates: int) -> None:
    """Both parts' config_changes.yaml as one history, the continuation's updates counted on."""
    history = yaml.safe_load(before.read_text(encoding="utf-8")) if before.is_file() else []
    then = yaml.safe_load(ours.read_text(encoding="utf-8")) if ours.is_file() else []
    if history or then:
        moved = [{**entry, "at_update": int(entry["at_update"]) + updates} for entry in then]
        atomic_write_text(ours, yaml.safe_dump([*history, *moved], sort_keys=False))


SNAPSHOT_FILES = ("config.yaml", *COPIED, "episodes.csv.gz", POLICY_NAME, BEST_NAME)


def snapshot(run: Path, out: Path) -> None:
    """RUN's files, as the module doc lists them, into the empty folder `out`."""
    portable_config(run / "config.yaml", out)
    for name in COPIED:
        if (run / name).is_file():
            shutil.copyfile(run / name, out / name)
    with (run / "episodes.csv").open("rb") as src, gzip.open(out / "episodes.csv.gz", "wb") as dst:
        shutil.copyfileobj(src, dst)
    for name in (POLICY_NAME, BEST_NAME):
        if (run / name).is_file():
            export_policy(run / name, out / name)


def publish(stage: Path, out: Path) -> None:
    """The snapshot in `stage` into `out`: each of its files replaces its namesake, a snapshot file it lacks (an
    earlier snapshot's best.pt, say) goes, anything else in `out` stays."""
    out.mkdir(exist_ok=True)
    for name in SNAPSHOT_FILES:
        if (stage / name).is_file():
            os.replace(stage / name, out / name)
        else:
            (out / name).unlink(missing_ok=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="training run folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--continues", type=Path, metavar="START",
                        help="the snapshot whose policy.pt RUN started from (cosim train --init-from): join the two")
    args = parser.parse_args()
    args.out = args.out.resolve()  # `--out .` has no parent or name to stage beside it under
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if not (args.run / POLICY_NAME).is_file():
        raise CosimError(f"{args.run}: no {POLICY_NAME}; not a training run folder, or one without a checkpoint yet")
    if args.continues is not None and args.continues.resolve() == args.out:
        raise CosimError(f"--continues {args.continues} and --out name the same folder: the joined snapshot would "
                         f"replace the part it continues and record itself as that part; write it to a new folder "
                         f"(or rename START first)")
    counters = start_counters(args.run, args.continues) if args.continues is not None else None  # refused first
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # Written beside OUT first (the same folder depth, so the relative paths hold) and moved in only once whole: a
    # snapshot that fails half way (a best.pt that its validation log does not pick, say) leaves OUT as it was.
    with tempfile.TemporaryDirectory(dir=args.out.parent, prefix=f".{args.out.name}.") as staging:
        stage = Path(staging)
        snapshot(args.run, stage)
        if counters is not None:
            join(args.run, args.continues, stage, counters)
        publish(stage, args.out)
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    run_script(main, log)
