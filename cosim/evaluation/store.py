"""An evaluation folder on disk: what `cosim evaluate` writes and `cosim compare` / `cosim sweep` read.

Contract: `episodes.csv` holds one row per episode (`cosim.files.read_csv` reads it); `summarize_evaluation`
and `pooled` pick the rows of the requested seeds and summarise them (`cosim.evaluation.stats.summarize`);
`trajectories/seed_S.npz` holds the recorded episodes (`save_trajectory` / `load_trajectory`), `plots/` their
videos (`video_files`); `summary.json`
names what was evaluated (`find_evaluation` reads it: a `CosimError` naming it when it is no JSON object or lacks
a key a reader needs). `checked_rows` gives an evaluation's rows checked against its summary: a `CosimError`
naming `episodes.csv` and both counts when the file is missing or holds fewer episodes than the summary counts.
`config_hash` and `scenario_hash` tell whether two folders evaluated the same episodes.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import CosimError
from cosim.evaluation.stats import summarize
from cosim.files import atomic_path, read_csv


@dataclass(frozen=True)
class Evaluation:
    label: str
    eval_dir: Path
    run_dir: Path | None  # the training run, for its training log
    summary: dict[str, Any]


# summary.json's keys that its readers need, with their types.
SUMMARY_KEYS: dict[str, tuple[type, ...]] = {"first_seed": (int,), "episodes": (int,)}
SUMMARY_OPTIONAL: dict[str, tuple[type, ...]] = {"requested_episodes": (int,), "confidence": (float, int),
                                                 "policy": (str,)}


def read_summary(path: Path) -> dict[str, Any]:
    """An evaluation's summary.json, checked for what its readers need."""
    rerun = f"run the same `cosim evaluate` into {path.parent} again to rewrite it"
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CosimError(f"{path}: not valid JSON ({exc}); {rerun}") from None
    if not isinstance(summary, dict):
        raise CosimError(f"{path}: expected a JSON object, got {type(summary).__name__}; {rerun}")
    missing = [k for k in SUMMARY_KEYS if k not in summary]
    if missing:
        raise CosimError(f"{path}: no {', '.join(missing)} (an evaluation summary has {sorted(SUMMARY_KEYS)}); "
                         f"{rerun}")
    for key, types in {**SUMMARY_KEYS, **SUMMARY_OPTIONAL}.items():
        value = summary.get(key)
        if key in summary and (isinstance(value, bool) or not isinstance(value, types)):
            raise CosimError(f"{path}: {key} {value!r} is not {' or '.join(t.__name__ for t in types)}; {rerun}")
    # Figures without a value are written as null (strict JSON): NaN again for the readers' arithmetic.
    for label, stats in summary.get("metrics", {}).items():
        summary["metrics"][label] = {k: math.nan if v is None else v for k, v in stats.items()}
    if isinstance(summary.get("demand"), dict):
        summary["demand"] = {k: math.nan if v is None else v for k, v in summary["demand"].items()}
    return summary


def find_evaluation(path: Path, label: str | None = None) -> Evaluation:
    """An evaluation folder, or a run folder with one in `eval/`."""
    path = Path(path)
    for eval_dir in (path, path / "eval"):
        if (eval_dir / "summary.json").is_file():
            summary = read_summary(eval_dir / "summary.json")
            run = summary.get("run") or (str(path) if eval_dir != path else None)
            return Evaluation(label or path.name, eval_dir, None if run is None else Path(run), summary)
    raise CosimError(f"{path}: no evaluation found (summary.json here or in {path / 'eval'}); run "
                     f"`cosim evaluate --out {path}` (or `--run {path}`) first")


def save_trajectory(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def summarize_evaluation(eval_dir: Path, first_seed: int, episodes: int,
                         confidence: float = 0.95) -> tuple[list[dict[str, str]], dict[str, dict[str, float | int]]]:
    """(rows, metrics): the episodes.csv rows of seeds `first_seed .. first_seed + episodes - 1` in seed order
    (one per seed), and their `summarize`d metrics. Rows of other seeds in the file are left out."""
    rows = seed_rows(eval_dir, first_seed, episodes)
    return rows, summarize(rows, confidence)


def seed_rows(eval_dir: Path, first_seed: int, episodes: int) -> list[dict[str, str]]:
    """The episodes.csv rows of seeds `first_seed .. first_seed + episodes - 1`, one per seed, in seed order."""
    wanted = range(first_seed, first_seed + episodes)
    rows = read_csv(Path(eval_dir) / "episodes.csv", ints=("seed",))
    by_seed = {int(r["seed"]): r for r in rows if int(r["seed"]) in wanted}
    return [by_seed[s] for s in sorted(by_seed)]


def checked_rows(e: Evaluation) -> list[dict[str, str]]:
    """The rows of the seeds `e`'s summary.json names (`seed_rows`), refused (`CosimError`, naming episodes.csv
    and both counts) when they are fewer than the episodes the summary counts: a summary of rows that are gone."""
    counted = int(e.summary["episodes"])
    # requested_episodes: where recorded (folders from before it was: the episodes found)
    first, requested = int(e.summary["first_seed"]), int(e.summary.get("requested_episodes", counted))
    path = e.eval_dir / "episodes.csv"
    rows = seed_rows(e.eval_dir, first, requested)
    if len(rows) < counted:
        seeds = f"seeds {first}..{first + requested - 1}"
        held = f"{len(rows)} episodes of {seeds}" if path.is_file() else f"not found ({seeds})"
        raise CosimError(f"{path}: {held}, but {path.parent / 'summary.json'} counts {counted}: deleted or cut? "
                         f"run the same `cosim evaluate` into {e.eval_dir} again to play the missing episodes")
    return rows


def _episodes_keys(config: Mapping[str, Any], sections: Sequence[str], sim: Sequence[str]) -> str:
    """Canonical JSON of `config` without `sections`, the `sim` keys named, and where the net's files are
    (`net.file`, `net.description`): an evaluation records the net's content (`net_sha256`), so a folder moved or
    cloned with its net elsewhere is still the same evaluation."""
    kept = {k: v for k, v in config.items() if k not in sections}
    kept["sim"] = {k: v for k, v in config.get("sim", {}).items() if k not in sim}
    kept["net"] = {k: v for k, v in config.get("net", {}).items() if k not in ("file", "description")}
    return json.dumps(kept, sort_keys=True, separators=(",", ":"), default=str)


def scenario_hash(config: Mapping[str, Any]) -> str:
    """sha256 of what makes the episodes themselves (simulation, scenario, drivers, observation; the net by its
    content elsewhere), leaving out what policies may differ in when compared: the reward (the SVO angle) and who
    drives the AVs."""
    text = _episodes_keys(config, ("train", "evaluate", "reward"), ("output_dir", "av_driver"))
    return hashlib.sha256(text.encode()).hexdigest()


def config_hash(config: Mapping[str, Any]) -> str:
    """sha256 of a resolved config (`Config.to_dict()`) as canonical JSON, over what shapes the episodes: not
    where the folder and the net are (`sim.output_dir`, the net's paths: a moved or copied evaluation still
    resumes), nor the `train` and `evaluate` sections (how many episodes and workers; the policy is compared on
    its own)."""
    return hashlib.sha256(_episodes_keys(config, ("train", "evaluate"), ("output_dir",)).encode()).hexdigest()


def trajectory_files(out_dir: Path) -> list[Path]:
    return sorted((out_dir / "trajectories").glob("seed_*.npz"), key=lambda p: int(p.stem.split("_")[1]))


def video_files(eval_dir: Path) -> list[Path]:
    """The episode videos in `eval_dir/plots/` (`cosim evaluate --videos`), by seed."""
    found = [p for p in (Path(eval_dir) / "plots").glob("video_seed_*.*") if p.suffix in (".mp4", ".gif")]
    return sorted(found, key=lambda p: int(p.stem.split("_")[2]))


def load_trajectory(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def run_name(phi: float, seed: int) -> str:
    """A sweep run's folder under `runs/`."""
    return f"phi_{phi:.4f}_seed_{seed}"


def pooled(eval_dirs: Sequence[Path], first_seed: int, episodes: int) -> tuple[list[dict[str, str]], dict]:
    """The evaluation rows of several folders (one per training seed), pooled, and their summary."""
    rows = [r for d in eval_dirs for r in seed_rows(d, first_seed, episodes)]
    return rows, summarize(rows)
