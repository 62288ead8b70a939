"""Validation during training (`train.eval_every`), as SB3's `EvalCallback` and the RL zoo do it: greedy episodes
on fixed seeds that neither training nor `cosim evaluate` plays, and the best policy kept by a stated rule.

Contract:
- `validation_seeds(episodes)` are `VALIDATION_SEED_START .. + episodes - 1`, the same at every validation: the
  curve compares policies, not episodes. Training's seeds lie below `EVAL_SEED_START` and evaluation's default
  ones just above it, so choosing the best checkpoint never looks at the episodes it is tested on.
- `validate(pool, policy, seeds, update)` plays those episodes on the training run's own workers: every live AV
  acts greedily (argmax among the actions its mask allows, in float32 as `cosim evaluate` plays a checkpoint),
  one batched forward per round over every worker; each episode writes SUMO's outputs, so its row (the env's
  episode summary, as `episodes.csv` and `cosim evaluate` have it) carries its SSM conflicts. A worker that fails
  plays its episode again on its replacement; a second failure of the same seed is `EpisodeError`. The rows come
  back in seed order, each with the AVs' mean greedy return (`av_return`) and how often each action was taken
  (`greedy_actions`, counts over the episode's decisions of every AV).
- Under demand an episode is a run (warm-up and window) with its window's flow metrics in its row, and the
  return is per AV released, as `episodes.csv`'s.
- `summarize(rows)` gives a validation's figures: crash and merge success [%] with Wilson intervals, conflicts,
  the merging vehicle's distance and the return with t-intervals (`cosim.evaluation.stats`); under demand the
  window's collisions, merge success per merging vehicle, throughput and delay per vehicle, with t-intervals over
  the runs (`DEMAND_FIGURES`); and `greedy_action_<k>`, the share [%] of the decisions that took action k.
  Where the episodes mix merging drivers (`scenario.merger_alt_share`), crash and merge success of each too
  (`crash_merger_alt`, `merge_merger`, ... with `_low` / `_high`: `cosim.evaluation.stats.by_merger`).
- `constant_action(fig)`: the action a validation's greedy policy took at >= `CONSTANT_SHARE` of its decisions, or
  None. Such a validation measures one constant action (every AV idling, say) rather than what the sampling
  policy has learned: the trainer says so in its log, since the curve and best.pt then compare no driving.
- `better(new, best, moving_vph)` is the rule that keeps `best.pt`: the lower upper bound of the crash rate (under
  demand: of the collisions per window); at equal bounds (the same crash count; no collision), the higher mean
  return, which is what the run optimises at its SVO angle. Under demand a policy that keeps traffic moving (mean
  throughput at least `moving_vph`, `MOVING_SHARE` of the flow offered: `moving_threshold`) comes first: a policy
  that holds the mainline still has few collisions, and would otherwise be kept over every one that drives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from agents.collect import per_av_released
from agents.multiagent import MultiAgentPolicy
from cosim.config import VALIDATION_SEED_START
from cosim.errors import EpisodeError
from cosim.evaluation import stats
from cosim.workers import StepResult, WorkerPool

# Validation's figures (validation.csv and TensorBoard name) -> the label of `cosim evaluate`'s summary.
FIGURES: dict[str, str] = {"crash": "crash [%]", "merge": "merge success [%]", "conflicts": "conflicts [per episode]",
                           "merger_distance": "merger distance [m]"}
# ... of a validation under demand -> the label of `cosim evaluate`'s summary of demand runs.
DEMAND_FIGURES: dict[str, str] = {"collisions": "collisions [per window]",
                                  "merge": "merge success, per merging vehicle [%]",
                                  "throughput": "throughput, total [veh/h]", "delay": "delay per vehicle [s]"}


def validation_seeds(episodes: int) -> list[int]:
    return [VALIDATION_SEED_START + k for k in range(episodes)]


def validate(pool: WorkerPool, policy: MultiAgentPolicy, seeds: Sequence[int], update: int) -> list[dict[str, Any]]:
    """The rows of the greedy episodes `seeds` played on `pool` (module doc)."""
    todo = list(reversed(seeds))
    playing: dict[int, int] = {}  # worker -> its episode's seed
    returns: dict[int, np.ndarray] = {}  # worker -> (N,) its episode's returns so far
    taken: dict[int, np.ndarray] = {}  # worker -> (A,) its episode's greedy actions so far, counted
    failed: set[int] = set()
    rows: dict[int, dict[str, Any]] = {}

    def start(ws: list[int]) -> None:
        for w in ws:
            returns[w] = np.zeros(len(pool.spec.agents))
            taken[w] = np.zeros(pool.spec.n_actions, dtype=np.int64)
        pool.send_reset(ws, [playing[w] for w in ws], outputs=True)

    first = list(range(min(len(pool), len(todo))))
    for w in first:
        playing[w] = todo.pop()
    start(first)
    while playing:
        ws = list(playing)
        restart, live = [], []
        for w, res in zip(ws, pool.recv(ws), strict=True):
            seed = playing[w]
            if res.lost:
                if seed in failed:
                    raise EpisodeError(f"validation episode (seed {seed}) fails the same way on a fresh worker: "
                                       f"{res.error}")
                failed.add(seed)
                restart.append(w)
                continue
            returns[w] += res.reward
            if res.episode is not None:
                # Per AV, as episodes.csv's return_mean (agents.train); under demand per AV that came and went.
                demand = "avs_released" in res.episode
                ret = per_av_released(returns[w].sum(), res.episode) if demand else returns[w].mean()
                rows[seed] = {**res.episode, "seed": seed, "av_return": float(ret),
                              "greedy_actions": taken[w].tolist()}
                if todo:
                    playing[w] = todo.pop()
                    restart.append(w)
                else:
                    del playing[w]
            else:
                live.append((w, res))
        if restart:
            start(restart)
        if live:
            for w, acts in _act_greedy(pool, policy, live, update).items():
                taken[w] += np.bincount(acts, minlength=pool.spec.n_actions)
    return [rows[s] for s in seeds]


def _act_greedy(pool: WorkerPool, policy: MultiAgentPolicy, live: list[tuple[int, StepResult]],
                update: int) -> dict[int, np.ndarray]:
    """One batched greedy forward for the live agents of `live` workers; their actions go out at once and come
    back by worker."""
    rows, agents, masks = [], [], []
    for w, res in live:
        idx = np.flatnonzero(res.alive)
        rows += [w] * len(idx)
        agents += idx.tolist()
        masks.append(res.action_mask[idx])
    obs = torch.from_numpy(pool.obs[rows, agents])  # (M, F, C, H, W) a copy out of the shared slots
    actions = policy.act(obs, torch.tensor(agents), update, torch.from_numpy(np.concatenate(masks)),
                         greedy=True)[0].numpy()
    full = np.ones((len(live), len(pool.spec.agents)), dtype=np.int64)  # idle for agents that are gone
    pos = {w: k for k, (w, _) in enumerate(live)}
    full[[pos[w] for w in rows], agents] = actions
    pool.send_step([w for w, _ in live], full)
    by_worker = np.array(rows)
    return {w: actions[by_worker == w] for w, _ in live}


def summarize(rows: Sequence[Mapping[str, Any]], confidence: float = 0.95) -> dict[str, float]:
    """One validation's figures: `<name>`, `<name>_low`, `<name>_high` for each of `FIGURES` (the intervals of
    `cosim evaluate`'s summary) and the AVs' mean greedy `return`, and `episodes_validated`; of `DEMAND_FIGURES`
    for demand runs' rows."""
    figures, known = ((DEMAND_FIGURES, stats.FLOW_METRICS) if is_demand(rows) else (FIGURES, stats.SUMMARY_METRICS))
    metrics = stats.summarize(rows, confidence, {label: known[label] for label in figures.values()})
    ret = stats.mean_ci([float(r["av_return"]) for r in rows], confidence)
    out: dict[str, float] = {"episodes_validated": float(len(rows))}
    for name, label in figures.items():
        got = metrics.get(label, {"mean": math.nan, "ci_low": math.nan, "ci_high": math.nan})
        out[name], out[f"{name}_low"], out[f"{name}_high"] = got["mean"], got["ci_low"], got["ci_high"]
    out["return"], out["return_low"], out["return_high"] = ret.mean, ret.low, ret.high
    split = {} if is_demand(rows) else stats.by_merger(rows, confidence)
    for name, label in FIGURES.items():
        for driver in stats.MERGER_DRIVERS:
            if (got := split.get(f"{label}, {driver}")) is not None:
                out[f"{name}_{driver}"], out[f"{name}_{driver}_low"] = got["mean"], got["ci_low"]
                out[f"{name}_{driver}_high"] = got["ci_high"]
    taken = np.sum([r["greedy_actions"] for r in rows if "greedy_actions" in r], axis=0)
    if np.ndim(taken) and taken.sum():
        out.update({f"greedy_action_{k}": float(100.0 * n / taken.sum()) for k, n in enumerate(taken)})
    return out


# A greedy policy that takes one action at this share [%] of its decisions or more is a constant one.
CONSTANT_SHARE = 99.0


def constant_action(fig: Mapping[str, float]) -> int | None:
    """The action a validation's greedy policy took at >= CONSTANT_SHARE of its decisions, or None."""
    shares = {int(k.rsplit("_", 1)[1]): v for k, v in fig.items() if k.startswith("greedy_action_")}
    top = max(shares, key=shares.__getitem__, default=None)
    return top if top is not None and shares[top] >= CONSTANT_SHARE else None


# Under demand, a validation whose mean throughput is below this share of the flow offered (the demand of every
# highway lane and the ramp) does not keep traffic moving. All-human traffic carried 80-100% of it at every level
# measured (results/demand_levels: 4,470 veh/h of 5,580 over capacity); AVs that hold the mainline still carry a
# quarter (the ramp's arrivals).
MOVING_SHARE = 0.75


def moving_threshold(offered_vph: float) -> float:
    """The mean throughput [veh/h] of a validation under demand that keeps traffic moving, for `offered_vph`."""
    return MOVING_SHARE * offered_vph


def better(new: Mapping[str, float], best: Mapping[str, float] | None, moving_vph: float | None = None) -> bool:
    """Whether validation `new` beats the best so far (module doc: under demand with `moving_vph`, keeping traffic
    moving first; then the crash upper bound, then the return)."""
    if best is None:
        return True
    if moving_vph is not None and "throughput" in new:
        moving, was_moving = new["throughput"] >= moving_vph, best["throughput"] >= moving_vph
        if moving != was_moving:
            return moving
    bound = "collisions_high" if "collisions_high" in new else "crash_high"
    if new[bound] != best[bound]:
        return new[bound] < best[bound]
    return new["return"] > best["return"]


def is_demand(rows: Sequence[Mapping[str, Any]]) -> bool:
    """Whether validation rows are demand runs' (their window's flow metrics) rather than episodes'."""
    return bool(rows) and "throughput_total_vph" in rows[0]


def describe(fig: Mapping[str, float]) -> str:
    """One validation's figures in words, for the training log."""
    if "collisions" in fig:
        return (f"collisions {fig['collisions']:.2f} [{fig['collisions_low']:.2f}, {fig['collisions_high']:.2f}] per "
                f"window, merge {fig['merge']:.1f}% [{fig['merge_low']:.1f}, {fig['merge_high']:.1f}], throughput "
                f"{fig['throughput']:.0f} veh/h [{fig['throughput_low']:.0f}, {fig['throughput_high']:.0f}], delay "
                f"{fig['delay']:.1f} s per vehicle, return {fig['return']:.1f}")
    drivers = [d for d in stats.MERGER_DRIVERS if f"crash_{d}" in fig]
    split = "".join(f", {d}: crash {fig[f'crash_{d}']:.1f}% [{fig[f'crash_{d}_low']:.1f}, "
                    f"{fig[f'crash_{d}_high']:.1f}] merge {fig[f'merge_{d}']:.1f}%" for d in drivers)
    return (f"crash {fig['crash']:.1f}% [{fig['crash_low']:.1f}, {fig['crash_high']:.1f}], merge {fig['merge']:.1f}% "
            f"[{fig['merge_low']:.1f}, {fig['merge_high']:.1f}], conflicts {fig['conflicts']:.2f} per episode, "
            f"return {fig['return']:.1f}{split}")


# The criterion of a safe policy (issue 29), on one validation's figures: crash at most 2% with an upper bound at
# most 5%, and where the AVs are altruistic (phi > 0) merge success within 5 points of a reference (the `courteous`
# rule's on the same validation seeds).
CRASH_MAX, CRASH_HIGH_MAX, MERGE_GAP = 2.0, 5.0, 5.0


def meets_criterion(fig: Mapping[str, float], phi: float, merge_reference: float | None) -> bool:
    """Whether a validation's figures (`summarize`) meet the criterion at SVO angle `phi` [rad]; `merge_reference`:
    the merge success [%] the altruistic AVs must come within `MERGE_GAP` points of (unused, and may be None, at
    phi <= 0)."""
    safe = fig["crash"] <= CRASH_MAX and fig["crash_high"] <= CRASH_HIGH_MAX
    if phi <= 0:
        return safe
    if merge_reference is None:
        raise ValueError(f"meets_criterion: phi = {phi} > 0 needs the merge reference")
    return safe and fig["merge"] >= merge_reference - MERGE_GAP
