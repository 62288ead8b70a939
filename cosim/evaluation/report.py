"""The sweep's report: tables, figures and the checks of the paper's claims, from the sweep folder alone.

Contract: `write_report(out, phis, seeds, baselines, episodes, command, walls)` reads `out/baselines/*/` and
`out/runs/*/eval/` (evaluations on the same seeds) and the runs' training logs, and writes `out/report.md`,
`out/sweep.json` and the figures beside them; returns {"table", "episodes", "claims"}. Rates are pooled over
the training seeds of an angle (Wilson intervals over every evaluation episode).
"""

from __future__ import annotations

import json
import math
import shlex
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from scipy.stats import mannwhitneyu

from cosim.config import EVAL_SEED_START, Config, load_config
from cosim.evaluation import plots
from cosim.evaluation.stats import RATE_METRICS, SUMMARY_METRICS, finite, format_table, median, rate, summarize
from cosim.evaluation.store import pooled, run_name
from cosim.files import atomic_write_text
from cosim.sumo.net import load_net
from cosim.sumo.setting import Setting

# Rate label -> its episodes.csv column, in the summary table's order (crash, crash by cause, merge success).
RATES = {label: column for label, (column, _) in SUMMARY_METRICS.items() if label in RATE_METRICS}
FLOW = ("throughput [veh/h]", "time loss [s]")
EGOISTIC, ALTRUISTIC = 0.0, math.pi / 4  # [rad] the paper's two SVO angles


def phi_label(phi: float) -> str:
    named = {EGOISTIC: " (egoistic)", ALTRUISTIC: " (altruistic)"}
    return f"phi={phi:.3f}" + next((v for k, v in named.items() if math.isclose(phi, k, abs_tol=1e-3)), "")


def write_report(out: Path, phis: Sequence[float], seeds: Sequence[int], baselines: Sequence[str], episodes: int,
                 command: str, walls: Mapping[str, float], demand_runs: int = 0) -> dict[str, Any]:

    base_rows = {b: pooled([out / "baselines" / b], EVAL_SEED_START, episodes)[0] for b in baselines}
    # The runs evaluated so far (all of them once the sweep is complete).
    run_rows = {(phi, s): rows for phi in phis for s in seeds
                if (rows := pooled([out / "runs" / run_name(phi, s) / "eval"], EVAL_SEED_START, episodes)[0])}
    phis_all = list(phis)
    phis = [p for p in phis if any(k[0] == p for k in run_rows)]
    phi_rows = {phi: [r for s in seeds for r in run_rows.get((phi, s), [])] for phi in phis}
    table = {**{b: summarize(rows) for b, rows in base_rows.items()},
             **{phi_label(phi): summarize(rows) for phi, rows in phi_rows.items()}}
    counts = {**{b: len(r) for b, r in base_rows.items()}, **{phi_label(p): len(r) for p, r in phi_rows.items()}}
    cfg = _sweep_config(out)
    caption = plots.caption_text(plots.short_path(cfg.net.file), _config_of(command),
                                 f"AVs trained at each SVO angle (training seeds {', '.join(map(str, seeds))}); "
                                 f"baselines {', '.join(baselines) or 'none'}")
    figures = {
        "Crash and merge rates over the SVO angle": _rates_vs_phi(out / "rates_vs_phi.png", phi_rows, base_rows,
                                                                  caption),
        "Traffic flow over the SVO angle": _flow_vs_phi(out / "flow_vs_phi.png", table, phis, baselines, caption),
        "The merging vehicle's distance": plots.distance_histogram(
            {label: [float(r["merger_distance"]) for r in rows] for label, rows in _ego_alt(phi_rows).items()},
            out / "merger_distance.png", marks=plots.accel_lane_marks(Setting.of(cfg)), caption=caption),
    }
    curves = plots.training_curves({phi_label(p): [out / "runs" / run_name(p, s) / "episodes.csv" for s in seeds
                                                   if (p, s) in run_rows] for p in phis},
                                   out / "training_curves.png", caption=caption)
    if curves is not None:
        figures["Training curves"] = curves
    claims = _claims(out, phi_rows, run_rows, base_rows, seeds)
    lines = ["# Sweep report", "", f"Command: `{command}`" if command else "", "",
             f"Evaluation: {episodes} episodes per run and baseline on seeds {EVAL_SEED_START}.."
             f"{EVAL_SEED_START + episodes - 1}, the same for all; trained angles pooled over training seeds "
             f"{list(seeds)}. Rates with 95% Wilson intervals, other metrics with 95% Student-t intervals.", "",
             f"Runs evaluated: {len(run_rows)} of {len(seeds) * len(phis_all)}.", "",
             format_table(table, counts, markdown=True), "", "## The paper's claims", ""]
    verdicts = {True: "holds", False: "NOT reached", None: "shown, not a statistical test"}
    lines += [f"- **{c['claim']}**: {verdicts[c['holds']]}. {c['detail']}" for c in claims]
    lines += [""]
    for title, path in figures.items():
        lines += [f"## {title}", "", f"![{title}]({path.name})", ""]
    if demand_runs:
        lines += _demand_section(out, phis, seeds, baselines, demand_runs, caption)
    lines += ["## Per training seed", "", _per_seed_table(run_rows, phis, seeds), "", "## Wall time", ""]
    lines += [f"- {k}: {v / 60:.1f} min" for k, v in walls.items()]
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    result = {"table": table, "episodes": counts, "claims": claims, "walls": dict(walls), "command": command}
    atomic_write_text(out / "sweep.json", json.dumps(result, indent=2, default=float) + "\n")
    return result


def _demand_section(out: Path, phis: Sequence[float], seeds: Sequence[int], baselines: Sequence[str], runs: int,
                    caption: str) -> list[str]:
    """The flow under traffic demand: every baseline and angle over its seeds' windows (each training seed's
    policy on the same `runs` demand seeds, pooled), the table and the flow bars."""
    from cosim.evaluation.flow_plots import flow_bars
    from cosim.evaluation.stats import FLOW_METRICS

    rows = {b: pooled([out / "baselines_demand" / b], EVAL_SEED_START, runs)[0] for b in baselines}
    rows.update({phi_label(p): got for p in phis
                 if (got := [r for s in seeds
                             for r in pooled([out / "runs" / run_name(p, s) / "eval_demand"], EVAL_SEED_START,
                                             runs)[0]])})
    rows = {k: v for k, v in rows.items() if v}
    if not rows:
        return []
    table = {k: summarize(v, metrics=FLOW_METRICS) for k, v in rows.items()}
    bars = flow_bars(table, out / "flow_demand.png", caption=caption)
    return ["## Traffic flow under demand", "",
            f"Each baseline and angle in `cosim evaluate --config DEMAND` (a {runs}-seed window each, per training "
            "seed for the angles, pooled); means with 95% t-intervals over the windows.", "",
            format_table(table, {k: len(v) for k, v in rows.items()}, markdown=True), "",
            f"![Traffic flow under demand]({bars.name})", ""]


def _ego_alt(phi_rows: Mapping[float, list]) -> dict[str, list]:
    """The egoistic and altruistic angles' rows where the sweep has them, else every angle's."""
    both = [p for p in (_find(phi_rows, EGOISTIC), _find(phi_rows, ALTRUISTIC)) if p is not None]
    return {phi_label(p): phi_rows[p] for p in (both if len(both) == 2 else phi_rows)}


def _find(phi_rows: Mapping[float, Any], target: float) -> float | None:
    return next((p for p in phi_rows if math.isclose(p, target, abs_tol=1e-3)), None)


def shift_p_value(egoistic: np.ndarray, altruistic: np.ndarray) -> float:
    """p-value of a one-sided Mann-Whitney U test that altruistic distances lie farther downstream (the paper's
    histogram: egoistic mass at the stuck position, altruistic mass beyond it); 1 without data."""
    if len(egoistic) == 0 or len(altruistic) == 0:
        return 1.0
    return float(mannwhitneyu(altruistic, egoistic, alternative="greater").pvalue)


def _sweep_config(out: Path) -> Config:
    """The resolved config of the sweep's first evaluated run (the net and scenario are the same for all)."""
    return load_config(next(out.glob("runs/*/eval/config.yaml")))


def _config_of(command: str) -> str:
    """The --config of the sweep's command line (the default config without one)."""
    words = shlex.split(command)
    given = [w.split("=", 1)[1] for w in words if w.startswith("--config=")]
    given += [b for a, b in zip(words, words[1:], strict=False) if a == "--config"]
    return given[-1] if given else "configs/default.yaml"


def _accel_end_distance(out: Path) -> float:
    """[m] from the ramp's start to the end of the acceleration lane. The merging vehicle starts on the ramp,
    so one that drove farther than this certainly passed the lane's end (one that started up the ramp may have
    passed it driving less: the fraction beyond is a lower bound)."""
    cfg = _sweep_config(out)
    return load_net(cfg.net.file, cfg.net.description).ramp_to_accel_end


def _claims(out: Path, phi_rows: Mapping[float, list], run_rows: Mapping[tuple[float, int], list],
            base_rows: Mapping[str, list], seeds: Sequence[int]) -> list[dict[str, Any]]:
    claims: list[dict[str, Any]] = []
    ego, alt = _find(phi_rows, EGOISTIC), _find(phi_rows, ALTRUISTIC)

    def ci(r: Mapping[str, float]) -> str:
        return f"{r['mean']:.1f}% [{r['ci_low']:.1f}, {r['ci_high']:.1f}] (n={r['n']})"

    for phi in (p for p in (ego, alt) if p is not None):
        crash = rate(phi_rows[phi], "crashed")
        parts, holds = [], all(b in base_rows for b in ("idle", "scripted"))  # nothing compared holds nothing
        for b in ("idle", "scripted"):
            if b in base_rows:
                other = rate(base_rows[b], "crashed")
                apart = crash["ci_high"] < other["ci_low"]
                below = crash["mean"] < other["mean"]
                holds &= below and (apart or b != "idle")
                verdict = "below, intervals apart" if apart else "below" if below else "not below"
                parts.append(f"{b} {ci(other)}: {verdict}")
        claims.append({"claim": f"(1) trained AVs at {phi_label(phi)} crash less than idle and scripted AVs",
                       "holds": holds, "detail": f"trained {ci(crash)}; " + "; ".join(parts)
                       + " (needs a lower mean than both, and intervals apart from idle's)"})
    if ego is not None and alt is not None:
        m_ego, m_alt = rate(phi_rows[ego], "merged"), rate(phi_rows[alt], "merged")
        per_seed = {s: (rate(run_rows[(ego, s)], "merged")["mean"], rate(run_rows[(alt, s)], "merged")["mean"])
                    for s in seeds if (ego, s) in run_rows and (alt, s) in run_rows}
        every = all(a > e for e, a in per_seed.values())
        apart = m_alt["ci_low"] > m_ego["ci_high"]
        claims.append({"claim": "(2) altruistic AVs get the merging vehicle in more often than egoistic ones",
                       "holds": apart and every and min(m_ego["n"], m_alt["n"]) >= 300,
                       "detail": f"egoistic {ci(m_ego)}, altruistic {ci(m_alt)}; intervals "
                                 f"{'apart' if apart else 'overlap'}; per seed (ego, alt): "
                                 + ", ".join(f"seed {s}: {e:.0f}% vs {a:.0f}%" for s, (e, a) in per_seed.items())
                                 + " (needs intervals apart, every seed in that direction and >= 300 episodes "
                                   "each)"})
        end = _accel_end_distance(out)
        beyond = {lbl: float(np.mean([float(r["merger_distance"]) > end for r in phi_rows[p]]))
                  for lbl, p in (("egoistic", ego), ("altruistic", alt))}
        med = {lbl: median(phi_rows[p], "merger_distance") for lbl, p in (("egoistic", ego), ("altruistic", alt))}
        p_value = shift_p_value(*(finite(phi_rows[p], "merger_distance") for p in (ego, alt)))
        claims.append({"claim": "(3) the merging vehicle's distance shifts downstream with altruistic AVs",
                       "holds": p_value < 0.05,
                       "detail": f"median {med['egoistic']:.1f} m egoistic vs {med['altruistic']:.1f} m altruistic; "
                                 f"one-sided Mann-Whitney U p = {p_value:.3g} (needs p < 0.05); driven past the "
                                 f"acceleration lane's end (farther than its {end:.0f} m from the ramp's start) in "
                                 f"{100 * beyond['egoistic']:.0f}% vs {100 * beyond['altruistic']:.0f}% of episodes"})
    flow = {phi_label(p): summarize(rows) for p, rows in phi_rows.items()}
    trade = "; ".join(f"{k}: crash {v['crash [%]']['mean']:.0f}%, merge {v['merge success [%]']['mean']:.0f}%, "
                      f"throughput {v.get('throughput [veh/h]', {}).get('mean', math.nan):.0f} veh/h, time loss "
                      f"{v.get('time loss [s]', {}).get('mean', math.nan):.2f} s" for k, v in flow.items())
    claims.append({"claim": "(4) the safety/flow trade-off over the SVO angle", "holds": None,
                   "detail": trade + " (figure below)"})
    return claims


def _per_seed_table(run_rows: Mapping[tuple[float, int], list], phis: Sequence[float], seeds: Sequence[int]) -> str:
    lines = ["| angle | seed | crash [%] | merge success [%] | episodes |", "|---|---|---|---|---|"]
    for phi in phis:
        for s in seeds:
            if (phi, s) not in run_rows:
                continue
            rows = run_rows[(phi, s)]
            c, m = rate(rows, "crashed"), rate(rows, "merged")
            lines.append(f"| {phi_label(phi)} | {s} | {c['mean']:.1f} [{c['ci_low']:.1f}, {c['ci_high']:.1f}] | "
                         f"{m['mean']:.1f} [{m['ci_low']:.1f}, {m['ci_high']:.1f}] | {len(rows)} |")
    return "\n".join(lines)


def _rates_vs_phi(path: Path, phi_rows: Mapping[float, list], base_rows: Mapping[str, list], caption: str) -> Path:
    fig = Figure(figsize=(11, 4.4), layout="constrained")
    axes = fig.subplots(1, 2)
    phis = sorted(phi_rows)
    # A cause often equals the total (every crash an AV's fault): each series is shifted a little along phi,
    # with its own marker and line, so that none hides another.
    styles = [("o", "-"), ("s", "--"), ("^", ":"), ("D", "-.")]
    dodge = 0.012 * (max(phis) - min(phis) or 1.0)
    for ax, labels in zip(axes, (list(RATES)[:4], ["merge success [%]"]), strict=True):
        for i, label in enumerate(labels):
            stats = [rate(phi_rows[p], RATES[label]) for p in phis]
            mean = np.array([s["mean"] for s in stats])
            err = np.array([[s["mean"] - s["ci_low"] for s in stats], [s["ci_high"] - s["mean"] for s in stats]])
            marker, ls = styles[i]
            x = np.asarray(phis) + dodge * (i - (len(labels) - 1) / 2)
            ax.errorbar(x, mean, yerr=err, marker=marker, ls=ls, ms=5, capsize=3, color=f"C{i}",
                        label=label.replace(" [%]", ""))
        for j, (b, rows) in enumerate(base_rows.items()):
            ax.axhline(rate(rows, RATES[labels[0]])["mean"], ls=(0, (4, 2)), lw=1, color=f"C{j + 5}",
                       label=f"baseline {b} ({labels[0].replace(' [%]', '')})")
        ax.set_xlabel("SVO angle phi [rad]")
        ax.set_ylabel("% of episodes")
        ax.set_ylim(-2, 102)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncols=2, frameon=False)
    axes[0].set_title("Crashes (total and by cause)")
    axes[1].set_title("Merge success")
    fig.suptitle("Trained AVs over the SVO angle (pooled over seeds), 95% Wilson intervals; dashed: baselines")
    plots.add_caption(fig, caption)
    return plots.save(fig, path)


def _flow_vs_phi(path: Path, table: Mapping[str, Mapping], phis: Sequence[float], baselines: Sequence[str],
                 caption: str) -> Path:
    fig = Figure(figsize=(10, 4.0), layout="constrained")
    axes = fig.subplots(1, 2)
    xs = sorted(phis)
    for ax, metric in zip(axes, FLOW, strict=True):
        stats = [table[phi_label(p)].get(metric, {}) for p in xs]
        mean = np.array([s.get("mean", math.nan) for s in stats])
        err = np.nan_to_num(np.array([[s.get("mean", math.nan) - s.get("ci_low", math.nan) for s in stats],
                                      [s.get("ci_high", math.nan) - s.get("mean", math.nan) for s in stats]]))
        ax.errorbar(xs, mean, yerr=err, marker="o", capsize=3, label="trained AVs")
        for j, b in enumerate(baselines):
            if metric in table[b]:
                ax.axhline(table[b][metric]["mean"], ls=(0, (4, 2)), lw=1, color=f"C{j + 1}", label=f"baseline {b}")
        ax.set_xlabel("SVO angle phi [rad]")
        ax.set_ylabel(metric)
        ax.set_title(f"{metric.split(' [')[0]} over the flow window")
    axes[-1].legend(*axes[0].get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8,
                    frameon=False)
    fig.suptitle("Traffic flow over the SVO angle (SUMO's detectors and tripinfo), 95% intervals")
    plots.add_caption(fig, caption)
    return plots.save(fig, path)
