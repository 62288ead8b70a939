"""A training run's progress, small enough for the repository: what a new machine needs to see where a run stands
and to go on from it, without the resumable checkpoint (optimizer state, tens of MB).

    python scripts/snapshot_run.py runs/learner/base_pi4_s1 --out results/learner/base_pi4_s1

Copies `config.yaml` (its net's paths made relative to OUT, so that a clone of the repository anywhere finds the net
the run trained on: a run writes them absolute), `net.json`, `config_changes.yaml`, `updates.csv`, `validation.csv`
and `episodes.csv` (gzipped), and writes `policy.pt` and `best.pt` with float16 weights
(`agents.checkpoint.export_policy`). Where the
run folder itself is gone, `cosim train --init-from OUT/policy.pt` is not a resume: it starts a new run from these
weights with a fresh optimizer (say so beside any figure).
"""

from __future__ import annotations

import argparse
import gzip
import logging
import os
import shutil
from pathlib import Path

import yaml

from agents.checkpoint import BEST_NAME, POLICY_NAME, export_policy
from cosim.config.loading import FILE_KEYS
from cosim.errors import CosimError, run_script
from cosim.files import atomic_write_text

log = logging.getLogger("snapshot")

COPIED = ("net.json", "config_changes.yaml", "updates.csv", "validation.csv")


def portable_config(config: Path, out: Path) -> None:
    """`config` (a run's config.yaml) written into `out` with the paths it names (`FILE_KEYS`: the net, the policy
    it started from) relative to `out` (`cosim.config.load_config` reads them relative to the file's folder)."""
    data = yaml.safe_load(config.read_text(encoding="utf-8"))
    for section, key in FILE_KEYS:
        if data.get(section, {}).get(key):
            data[section][key] = os.path.relpath(Path(data[section][key]).resolve(), out.resolve())
    atomic_write_text(out / "config.yaml", yaml.safe_dump(data, sort_keys=False))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="training run folder")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if not (args.run / POLICY_NAME).is_file():
        raise CosimError(f"{args.run}: no {POLICY_NAME}; not a training run folder, or one without a checkpoint yet")
    args.out.mkdir(parents=True, exist_ok=True)
    portable_config(args.run / "config.yaml", args.out)
    for name in COPIED:
        if (args.run / name).is_file():
            shutil.copyfile(args.run / name, args.out / name)
    with (args.run / "episodes.csv").open("rb") as src, gzip.open(args.out / "episodes.csv.gz", "wb") as dst:
        shutil.copyfileobj(src, dst)
    for name in (POLICY_NAME, BEST_NAME):
        if (args.run / name).is_file():
            export_policy(args.run / name, args.out / name)
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    run_script(main, log)
