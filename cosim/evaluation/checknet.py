"""`cosim check-net`: is a net ready for the experiment, and is its merge a dilemma there?

Contract: `check_net(cfg, out_dir, ...)` loads the config's net (a net without an on-ramp merge stops at once:
`NetError`, one line), prints its summary (`cosim.sumo.net.net_summary`) and the scenario resolved on it with
the values it had to cap (`cosim.sumo.resolve`), plans a first episode (a placement the net makes impossible
stops here: `ConfigError`, one line naming the key or the net element), then evaluates the baselines (`idle`,
`scripted`, `courteous`, `sumo`) on the same evaluation seeds, `episodes` each, adding episodes up to
`max_episodes` while a target's 95% interval still straddles its bound. The verdict says whether the merge is
a dilemma (the `TARGETS`: the merging vehicle gets in without help at most 60% of the time, with AVs that open
a gap at least 90%, and careful AVs do not crash) and, where it is not, which config keys would make it one.
Everything goes to `out_dir`: `check.md`, `check.json` and one evaluation folder per baseline (resumable).
`TARGETS` is also the calibration script's (scripts/calibrate_scenario.py).
"""

from __future__ import annotations

import json
import logging
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cosim.config import EVAL_SEED_START, Config
from cosim.errors import ConfigError
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.stats import format_table
from cosim.files import atomic_write_text
from cosim.sumo.net import net_summary, summary_lines
from cosim.sumo.resolve import scenario_lines
from cosim.sumo.scenario import plan_episode
from cosim.sumo.setting import Setting

log = logging.getLogger(__name__)

POLICIES = ("idle", "scripted", "courteous", "sumo")


@dataclass(frozen=True)
class Target:
    policy: str
    metric: str  # a summary label (cosim.evaluation.stats.SUMMARY_METRICS)
    op: str  # "<=", ">=" or "=="
    bound: float

    @property
    def label(self) -> str:
        return f"{self.policy}: {self.metric} {self.op} {self.bound:g}"

    def met(self, value: float) -> bool:
        return bool(_OPS[self.op](value, self.bound))

    def decided(self, m: dict[str, float]) -> bool:
        """Whether the 95% interval lies on one side of the bound (an equality is decided by the mean)."""
        if self.op == "==":
            return True
        return not (m["ci_low"] <= self.bound <= m["ci_high"])


_OPS: dict[str, Callable[[float, float], bool]] = {"<=": operator.le, ">=": operator.ge, "==": operator.eq}
# A merge dilemma: unless an AV opens a gap the merging vehicle rarely gets in; with one that does, it almost
# always does; careful AVs do not crash, and SUMO's own drivers never do (crashes come from decisions, not from
# where the vehicles start).
TARGETS: tuple[Target, ...] = (
    Target("idle", "merge success [%]", "<=", 60.0),
    Target("scripted", "merge success [%]", "<=", 60.0),
    Target("courteous", "merge success [%]", ">=", 90.0),
    Target("courteous", "crash [%]", "<=", 10.0),
    Target("scripted", "crash [%]", "<=", 15.0),
    Target("sumo", "crash [%]", "==", 0.0),
)

# Where targets fail: the advice naming the keys, and a ladder of settings, each a step further, that --suggest
# measures in turn (the first that makes the merge a dilemma is reported).
@dataclass(frozen=True)
class Advice:
    targets: tuple[str, ...]  # labels of the targets it answers
    text: str  # formatted with the net's acceleration lane length {accel} [m] and its time at the ramp's limit
    ladder: tuple[tuple[str, ...], ...]  # --set overrides, mildest first


ADVICE: tuple[Advice, ...] = (
    Advice(("idle: merge success [%] <= 60", "scripted: merge success [%] <= 60"),
           "the merging vehicle finds a gap without help: make the stream denser (hv.tau_range, e.g. [0.4, 0.5]; "
           "scenario.stream_spacing, e.g. [1.0, 1.0]), or give the merging vehicle less time to look for a gap (a "
           "shorter acceleration lane in the net: here {accel:g} m, the dilemma net's 119 m)",
           (("hv.tau_range=[0.5, 0.7]", "scenario.stream_spacing=[1.0, 1.05]"),
            ("hv.tau_range=[0.4, 0.6]", "scenario.stream_spacing=[1.0, 1.0]"),
            ("hv.tau_range=[0.4, 0.5]", "scenario.stream_spacing=[1.0, 1.0]"),
            ("hv.tau_range=[0.3, 0.4]", "scenario.stream_spacing=[1.0, 1.0]"))),
    Advice(("courteous: merge success [%] >= 90",),
           "even AVs that open a gap do not get it in: time the AV that meets it (scenario.guide_window, "
           "scenario.merger_time) or slow the stream (scenario.stream_speed_factor); an acceleration lane of {accel:g} "
           "m leaves {accel_s:.1f} s at the ramp's speed limit to merge",
           (("scenario.guide_window=[0.5, 2.0]",),
            ("scenario.guide_window=[0.5, 2.0]", "scenario.stream_speed_factor=[0.6, 0.7]"),
            ("scenario.guide_window=[0.5, 2.0]", "scenario.stream_speed_factor=[0.5, 0.6]"))),
    Advice(("courteous: crash [%] <= 10", "scripted: crash [%] <= 15", "sumo: crash [%] == 0"),
           "careful drivers crash: the vehicles start too close (scenario.stream_spacing, e.g. [1.1, 1.3]; "
           "scenario.min_gap for the lanes beside the stream)",
           (("scenario.stream_spacing=[1.1, 1.3]",), ("scenario.stream_spacing=[1.2, 1.5]", "scenario.min_gap=40"))),
)


def check_net(cfg: Config, out_dir: Path, episodes: int = 100, max_episodes: int = 400, workers: int = 2,
              seed: int = EVAL_SEED_START, suggest: bool = False,
              say: Callable[[str], None] = print) -> dict[str, Any]:
    """Check `cfg`'s net (see the module doc); with `suggest`, where the merge is no dilemma, measure the advice's
    settings in turn (`episodes` each) and report the first that makes it one. `say` prints each part as it is
    known. Returns what check.json holds."""
    if cfg.demand.enabled:
        raise ConfigError("demand.enabled: check-net judges the episode scenario (whether the merge is a dilemma); "
                          "check the net with an episode config (e.g. --config configs/default.yaml --net NET), then "
                          "evaluate under demand: cosim evaluate --config CONFIG --net NET")
    on_net = Setting.of(cfg)
    net = on_net.net
    summary = net_summary(net)
    say("\n".join(summary_lines(summary)))
    say("scenario on this net:\n  " + "\n  ".join(scenario_lines(on_net.config, net)))
    for note in on_net.notes:
        say(f"capped: {note}")
    plan_episode(on_net.config, net, seed)  # a placement this net makes impossible stops here
    n = episodes
    while True:
        evaluations = _baselines(cfg, out_dir, n, workers, seed)
        undecided = [t for t in TARGETS if not t.decided(evaluations[t.policy]["metrics"][t.metric])]
        if not undecided or n >= max_episodes:
            break
        n = min(2 * n, max_episodes)
        log.info("%s undecided: %d episodes each", ", ".join(t.label for t in undecided), n)
    verdicts = targets_met(evaluations)
    failed = {v["target"] for v in verdicts if not v["met"]}
    accel_s = net.accel_length / net.ramp_speed_limit
    answers = [a for a in ADVICE if failed & set(a.targets)]
    result = {"net": summary, "config": cfg.source, "notes": list(on_net.notes), "episodes": n, "first_seed": seed,
              "dilemma": not failed, "targets": verdicts,
              "advice": [a.text.format(accel=round(net.accel_length), accel_s=accel_s) for a in answers],
              "suggestion": (_suggest(cfg, out_dir, answers[0], episodes, workers, seed) if suggest and answers
                             else None),
              "metrics": {p: e["metrics"] for p, e in evaluations.items()}}
    head, results = _report(result, evaluations, on_net.config, net)
    say(results)
    text = head + "\n\n" + results
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "check.md", text + "\n")
    atomic_write_text(out_dir / "check.json", json.dumps(result, indent=2, default=str) + "\n")
    return result


def _baselines(cfg: Config, out_dir: Path, episodes: int, workers: int, seed: int) -> dict[str, dict[str, Any]]:
    """Every baseline's evaluation summary on the same seeds (resumed where `out_dir` holds some)."""
    return {p: evaluate(cfg, Baseline(p), out_dir / p, episodes=episodes, seed=seed, workers=workers, trajectories=0,
                        plots=False) for p in POLICIES}


def _suggest(cfg: Config, out_dir: Path, advice: Advice, episodes: int, workers: int, seed: int) -> dict[str, Any]:
    """The first of `advice`'s settings under which every target holds (by the mean), measured; else the last."""
    from cosim.config import load_config

    tried = []
    for k, overrides in enumerate(advice.ladder):
        summaries = _baselines(load_config(cfg, list(overrides)), out_dir / f"suggest_{k}", episodes, workers, seed)
        verdicts = targets_met(summaries)
        tried.append({"set": list(overrides), "dilemma": all(v["met"] for v in verdicts),
                      "merge success [%]": {p: s["metrics"]["merge success [%]"]["mean"] for p, s in summaries.items()},
                      "crash [%]": {p: s["metrics"]["crash [%]"]["mean"] for p, s in summaries.items()}})
        log.info("--set %s: %s", " --set ".join(overrides), "a dilemma" if tried[-1]["dilemma"] else "not a dilemma")
        if tried[-1]["dilemma"]:
            break
    return {"found": tried[-1]["dilemma"], "tried": tried}


def _verdict(t: Target, m: dict[str, float]) -> dict[str, Any]:
    return {"target": t.label, "mean": m["mean"], "ci": [m["ci_low"], m["ci_high"]], "met": t.met(m["mean"]),
            "decided": t.decided(m)}


def _report(result: dict[str, Any], evaluations: dict[str, dict[str, Any]], cfg: Config, net: Any) -> tuple[str, str]:
    """Markdown: the net and the scenario, then the baselines and the verdict."""
    table = format_table({p: {k: e["metrics"][k] for k in ("merge success [%]", "crash [%]", "merger distance [m]")}
                          for p, e in evaluations.items()},
                         {p: e["episodes"] for p, e in evaluations.items()}, markdown=True)
    head = "\n".join(["# Net check", "", *(f"- {line}" for line in summary_lines(result["net"])),
                      f"- scenario ({result['config'] or 'built-in defaults'}): " + "; ".join(scenario_lines(cfg, net)),
                      *(f"- capped: {note}" for note in result["notes"])])
    lines = [f"Baselines on evaluation seeds {result['first_seed']}..{result['first_seed'] + result['episodes'] - 1}, "
             "the same for each:", "", table, "", "| target | mean [95% CI] | met | decided by the interval |",
             "|---|---|---|---|"]
    lines += [f"| {v['target']} | {v['mean']:.1f} [{v['ci'][0]:.1f}, {v['ci'][1]:.1f}] | {'yes' if v['met'] else 'NO'} "
              f"| {'yes' if v['decided'] else 'no (by the mean)'} |" for v in result["targets"]]
    if result["dilemma"]:
        lines += ["", "Verdict: the merge is a dilemma on this net: without help the merging vehicle rarely gets in, "
                  "AVs that open a gap get it in, and careful drivers do not crash."]
    else:
        lines += ["", "Verdict: NOT a dilemma on this net. To make it one:", *(f"- {a}" for a in result["advice"])]
        found = result["suggestion"]
        if found is None:
            lines.append("- (`cosim check-net NET --suggest` measures which settings make it one)")
        for t in (found or {}).get("tried", []):
            rates = ", ".join(f"{p} {t['merge success [%]'][p]:.0f}%" for p in POLICIES)
            crashes = ", ".join(f"{p} {t['crash [%]'][p]:.0f}%" for p in POLICIES if t["crash [%]"][p] > 0)
            lines.append(f"- measured `--set {' --set '.join(t['set'])}`: merge success {rates}"
                         f"{'; crashes ' + crashes if crashes else ''}: {'a dilemma' if t['dilemma'] else 'not yet'}")
    return head, "\n".join(lines)


def targets_met(summaries: dict[str, dict[str, Any]], targets: Sequence[Target] = TARGETS) -> list[dict[str, Any]]:
    """Each target of a policy in `summaries` (policy -> evaluation summary), judged by its mean."""
    return [_verdict(t, summaries[t.policy]["metrics"][t.metric]) for t in targets if t.policy in summaries]
