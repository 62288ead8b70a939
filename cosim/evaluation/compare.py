"""`cosim compare`: evaluated runs side by side: a table, the paper's figures, one Markdown report.

Contract: `compare(dirs, out_dir, labels)` takes evaluation folders (written by `cosim evaluate`: a
`summary.json` and `episodes.csv`) or training-run folders holding one in `eval/`, and writes into
`out_dir`: `bars.png` (crash %, merge %, mean distance with 95% intervals), `merger_distance.png` (the
merging vehicle's distance, overlaid), `training_curves.png` (when a run folder has the trainer's
`episodes.csv`), per run `LABEL/` with the time-space diagrams, guide-AV speed profiles and top views of
its recorded episodes, `summary.json` / `summary.csv` (all runs' metrics) and `report.md` (the table, what
the runs ran on: net, scenario, overrides, flow window and detector, once where they share it, the figures,
and links to the videos in each evaluation folder, `cosim evaluate --videos`). Runs on different nets (by
content) or episodes are compared with a warning. `evaluation_report(eval_dir, label, figures)` writes the same
report for one evaluation into its own folder (`cosim evaluate`). Each run is summarised from its
`episodes.csv` over the seeds its `summary.json` names, as `cosim evaluate` did
(`cosim.evaluation.store.checked_rows`): rows of other seeds in the file are left out; each run's own figures
are `cosim.evaluation.plots.plot_evaluation`'s, as `cosim evaluate` draws them. Before anything is written, a
folder without an evaluation, with a summary.json that is corrupt or lacks a key, or whose episodes.csv is
missing or holds fewer of those episodes than its summary.json counts raises `CosimError` naming the file (and
the counts).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from cosim.config import load_config
from cosim.errors import CosimError
from cosim.evaluation import plots
from cosim.evaluation.stats import SUMMARY_METRICS, format_table, summarize
from cosim.evaluation.store import Evaluation, checked_rows, find_evaluation, video_files
from cosim.files import atomic_write_text, column, write_csv, write_json
from cosim.sumo.setting import Setting, setting_lines

log = logging.getLogger(__name__)


def compare(dirs: Sequence[Path], out_dir: Path, labels: Sequence[str] | None = None) -> dict[str, Any]:
    """Write the comparison report into `out_dir`; returns {label: summary}."""
    if labels is not None and len(labels) != len(dirs):
        raise CosimError(f"--labels: {len(labels)} labels for {len(dirs)} folders")
    evals = [find_evaluation(d, None if labels is None else labels[i]) for i, d in enumerate(dirs)]
    names = [e.label for e in evals]
    if len(set(names)) != len(names):
        raise CosimError(f"runs need distinct labels, got {names}; pass --labels")
    # Recomputed from episodes.csv, so every run is summarised the same way (and as `cosim evaluate` did).
    rows = {e.label: checked_rows(e) for e in evals}
    metrics = {e.label: summarize(rows[e.label], e.summary.get("confidence", 0.95)) for e in evals}
    mismatches = incompatibilities(evals)
    for line in mismatches:
        log.warning("runs not directly comparable: %s", line)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    episodes = {e.label: len(rows[e.label]) for e in evals}
    caption = plots.evaluation_caption([e.summary for e in evals])
    # Episode evaluations get the episode figures, demand ones (`cosim evaluate` in demand mode) the flow's.
    demand = [e for e in evals if "demand" in e.summary]
    episodic = [e for e in evals if "demand" not in e.summary]
    figures: dict[str, Path] = {}
    if episodic:
        merger = {e.label: column(rows[e.label], "merger_distance") for e in episodic}
        # The acceleration lane's marks where every run has the same (net, ramp start positions).
        marks = [plots.accel_lane_marks(Setting.of(load_config(e.eval_dir / "config.yaml"))) for e in episodic]
        figures["bars"] = plots.bars({e.label: metrics[e.label] for e in episodic}, out_dir / "bars.png",
                                     caption=caption)
        figures["merger distance"] = plots.distance_histogram(
            merger, out_dir / "merger_distance.png", marks=marks[0] if marks.count(marks[0]) == len(marks) else None,
            caption=caption)
    if demand:
        from cosim.evaluation.flow_plots import flow_bars

        figures["traffic flow"] = flow_bars({e.label: metrics[e.label] for e in demand}, out_dir / "flow_bars.png",
                                            caption=caption)
    logs = {e.label: [e.run_dir / "episodes.csv"] for e in evals if e.run_dir is not None}
    curves = plots.training_curves(logs, out_dir / "training_curves.png", caption=caption) if logs else None
    if curves is not None:
        figures["training curves"] = curves
    per_run: dict[str, list[Path]] = {}
    for e in tqdm(evals, desc="plots", unit="run", leave=False, disable=None):
        if e in demand:
            from cosim.evaluation.flow_plots import plot_demand

            per_run[e.label] = plot_demand(e.eval_dir, out_dir / e.label, e.label,
                                           [int(r["seed"]) for r in rows[e.label]])
        else:
            per_run[e.label] = [*plots.plot_evaluation(e.eval_dir, out_dir / e.label, e.label),
                                *video_files(e.eval_dir)]
    result = {e.label: {**e.summary, "episodes": episodes[e.label], "metrics": metrics[e.label],
                        "eval_dir": str(e.eval_dir)} for e in evals}
    write_json(out_dir / "summary.json", result)
    write_csv(out_dir / "summary.csv", _summary_rows(metrics), ["run", "metric", "mean", "ci_low", "ci_high", "n"])
    atomic_write_text(out_dir / "report.md", _report(evals, metrics, episodes, figures, per_run, out_dir,
                                                     mismatches))
    return result


VIDEO = (".mp4", ".gif")

# What makes two evaluations comparable, as summary.json records it: the same episodes of the same scenario.
COMPARABLE = {"net_sha256": "net file content (net_sha256)", "first_seed": "first evaluation seed",
              "requested_episodes": "episodes",
              "scenario_sha256": "scenario (net, simulation, drivers, observation: scenario_sha256)"}


def incompatibilities(evals: Sequence[Evaluation]) -> list[str]:
    """One line per summary key whose value differs between the evaluations, naming each run's value."""
    lines = []
    for key, what in COMPARABLE.items():
        values = {e.label: e.summary.get(key) for e in evals}
        if len({json.dumps(v) for v in values.values()}) > 1:
            shown = {k: (v[:12] if key.endswith("sha256") and isinstance(v, str) else v) for k, v in values.items()}
            lines.append(f"different {what}: " + ", ".join(f"{k}: {v}" for k, v in shown.items()))
    return lines


def evaluation_report(eval_dir: Path, label: str, figures: Sequence[Path]) -> Path:
    """`eval_dir/report.md` of one evaluation (`cosim evaluate`): its table, `figures` and its videos."""
    e = find_evaluation(eval_dir, label)
    rows = checked_rows(e)
    conf = e.summary.get("confidence", 0.95)
    episodes = [p for p in figures if "_seed_" in p.stem]  # the recorded episodes' figures, then their videos
    text = _report([e], {label: summarize(rows, conf)}, {label: len(rows)},
                   {p.stem.replace("_", " "): p for p in figures if p not in episodes},
                   {label: [*episodes, *video_files(eval_dir)]}, eval_dir)
    atomic_write_text(eval_dir / "report.md", text)
    return eval_dir / "report.md"


def _summary_rows(metrics: dict[str, dict[str, dict[str, float]]]) -> list[dict[str, Any]]:
    return [{"run": run, "metric": label, **{k: ms[label][k] for k in ("mean", "ci_low", "ci_high", "n")}}
            for run, ms in metrics.items() for label in SUMMARY_METRICS if label in ms]


def _cells(evals: Sequence[Evaluation], episodes: dict[str, int], conf: float) -> str:
    """What a cell of the table holds, and which intervals a single episode (or demand run) leaves out."""
    demand = all("demand" in e.summary for e in evals)
    unit = "run" if demand else "episode"
    single = [e.label for e in evals if episodes[e.label] < 2]
    if demand:  # one row per seed's run, every metric a mean over them
        text = (f"Each cell: mean over the runs, one per seed [{conf:.0%} Student t interval]. Throughput, the ramp's "
                "queue, delay and density come from SUMO's own detectors and tripinfo output.")
        gap = "no interval"
    else:
        text = (f"Each cell: mean over {unit}s [{conf:.0%} interval: Wilson score for the crash and merge rates, "
                "Student t for the other metrics]. Throughput, time loss and mean speed come from SUMO's own "
                "induction loops and tripinfo output.")
        gap = "no Student t interval (the rates keep their Wilson interval)"
    if single:  # a t-interval needs two values: say so rather than leave the reader looking for it
        who = "" if len(single) == len(evals) else f" ({', '.join(single)})"
        text += f" With a single {unit}{who} there is {gap}: those cells show its value alone."
    return text


def _report(evals: Sequence[Evaluation], metrics: dict, episodes: dict[str, int], figures: dict[str, Path],
            per_run: dict[str, list[Path]], out_dir: Path, mismatches: Sequence[str] = ()) -> str:
    conf = evals[0].summary.get("confidence", 0.95)
    lines = ["# Evaluation report", "",
             "Runs: " + ", ".join(f"**{e.label}** ({e.summary.get('policy')}, `{e.eval_dir}`)" for e in evals),
             ""]
    # Which state of a trained run was played: best.pt (chosen by validation) or the last policy.
    played = [f"**{e.label}**: `{e.summary['checkpoint']}`" for e in evals if e.summary.get("checkpoint")]
    if played:
        lines += ["Trained policies played: " + ", ".join(played), ""]
    if mismatches:
        lines += ["> **Warning: these runs were not evaluated on the same episodes of the same scenario;** their "
                  "differences below mix the policies' effect with that of:", ">"]
        lines += [f"> - {m}" for m in mismatches] + [""]
    lines += [_cells(evals, episodes, conf), "", format_table(metrics, episodes, markdown=True, confidence=conf), ""]
    for e in evals:
        if "demand" in e.summary:  # a demand run's window: its demand and level of service
            from cosim.evaluation.flow_plots import demand_caption

            d = e.summary["demand"]
            lines += [f"**{e.label}** under demand ({demand_caption(e.summary, e.label)}): level of service "
                      f"**{d.get('level_of_service', '-')}** in the merge influence area (HCM; F where the demand "
                      f"exceeds the capacity: {d.get('capacity', '')}).", ""]
    settings = {e.label: e.summary["setting"] for e in evals if "setting" in e.summary}
    if settings and len({json.dumps(v, sort_keys=True) for v in settings.values()}) == 1:
        lines += ["## Setting (the same for every run)", "", *setting_lines(next(iter(settings.values()))), ""]
    else:
        for label, where in settings.items():
            lines += [f"## Setting of {label}", "", *setting_lines(where), ""]
    for title, path in figures.items():
        lines += [f"## {title.capitalize()}", "", f"![{title}]({path.relative_to(out_dir)})", ""]
    for label, paths in per_run.items():
        if paths:
            lines += [f"## {label}: recorded episodes", ""]
            # Videos stay in their evaluation folder: linked (Markdown shows no video inline), wherever that is.
            lines += [f"[{p.stem} ({p.suffix[1:].upper()})]({os.path.relpath(p, out_dir)})" if p.suffix in VIDEO
                      else f"![{p.stem}]({p.relative_to(out_dir)})" for p in paths] + [""]
    return "\n".join(lines)
