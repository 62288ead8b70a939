"""Individual utility as a registry of named, weighted terms, and the paper's decentralised SVO reward (pure
functions).

Contract:
- `TERMS` maps each term's name to its function of a `StepChange` (what one decision step did to every vehicle
  of the snapshot), giving the term's unweighted value per vehicle (V,). The names, weights (default,
  description, unit) and order are the fields of the config's `cosim.config.RewardWeights`, so the key
  reference and the JSON schema list every term: adding a term is its function here, `@term("name")` above it,
  and its field there; `reward.weights.name` then sets its weight, `infos[agent]["reward_terms"]` reports it
  and the trainer logs it. `term` refuses a name that is no field (at import), and the tests check that the
  registry's names are the fields, in order. The terms: `speed` (progress / (max speed * period), in [0, 1]),
  `accel` (-|speed change| / (AV accel * period), every vehicle, so forcing humans to brake costs the social
  part), `lane_change` and `invalid_action` (-1, AVs only), `collision` (-1 if crashed), `merge` (+1 for the
  merging vehicle on the step it merges), `headway` (min(0, ln(gap / (HEADWAY_TIME x speed))), AVs only: MARL_CAVs'
  headway cost; weight 0 unless set, the paper's reward has none; `configs/default.yaml` sets 1).
- `av_gaps(snap, weights)` gives a step's AV gaps for `headway`; `utility_terms(step)` evaluates every term;
  `weighted_utility(terms, cfg)` weighs them by `cfg.weights`; `step_utility(prev, snap, ...)` does all three for
  one decision step of an env, the same for every scenario.
- `svo_rewards(u, observed, ego_rows, merger_row, phis, mean=False)` is the paper's Eq. (3):
  R_i = cos(phi_i) u_i + sin(phi_i) (sum of u over the others i observes + u_M), where, as in the paper's
  sum over k in V~ ∪ {M}, the merging vehicle counts whether observed or not; `mean` (`reward.social: mean`)
  takes the mean over those others instead of the sum (0 where there are none).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cosim.config import Config, RewardConfig, RewardWeights
from cosim.sumo.snapshot import KIND_AV, Snapshot


@dataclass(frozen=True)
class StepChange:
    """What one decision step did to each vehicle of the snapshot, (V,) arrays, and the terms' scales."""

    progress: np.ndarray  # [m] distance driven
    speed_change: np.ndarray  # [m/s]
    lane_changed: np.ndarray  # bool: an AV changed lane
    invalid: np.ndarray  # bool: an AV asked for a lane change toward no lane
    crashed: np.ndarray  # bool
    merged_now: np.ndarray  # bool: the merging vehicle, on the step it reached a through lane
    max_speed: float  # [m/s] the AVs'
    max_accel: float  # [m/s^2] the AVs'
    period: float  # [s] decision period
    speed: np.ndarray | None = None  # [m/s] at the end of the step (None: no headway term, e.g. a hand-made step)
    gap: np.ndarray | None = None  # [m] each AV's gap to its leader on its lane (Snapshot.leader_gaps), inf: none or
    # not an AV


HEADWAY_TIME = 1.2  # [s] the time gap under which `headway` costs, as MARL_CAVs' HEADWAY_TIME
MIN_GAP = 0.1  # [m] floor of the gap in `headway`'s logarithm: an overlap (a crash) costs ln(0.1 / (1.2 v)), not -inf


Term = Callable[[StepChange], np.ndarray]  # a term's unweighted value per vehicle (V,)
TERMS: dict[str, Term] = {}  # in registration order, which is the order of summation (RewardWeights' fields)


def term(name: str) -> Callable[[Term], Term]:
    """Register a utility term under `name`, a field of `RewardWeights` (its weight); `ValueError` otherwise, or
    when `name` is registered already, so a term cannot exist without its config key or go unweighted."""
    if name not in RewardWeights.model_fields:
        raise ValueError(f"utility term {name!r} has no weight: add the field {name} to cosim.config.RewardWeights "
                         f"(its terms: {', '.join(RewardWeights.model_fields)})")
    if name in TERMS:
        raise ValueError(f"utility term {name!r} is registered already")

    def register(fn: Term) -> Term:
        TERMS[name] = fn
        return fn

    return register


@term("speed")
def _speed(s: StepChange) -> np.ndarray:
    return np.clip(s.progress / (s.max_speed * s.period), 0.0, 1.0)


@term("lane_change")
def _lane_change(s: StepChange) -> np.ndarray:
    return -s.lane_changed.astype(np.float64)


@term("invalid_action")
def _invalid_action(s: StepChange) -> np.ndarray:
    return -s.invalid.astype(np.float64)


@term("accel")
def _accel(s: StepChange) -> np.ndarray:
    return -np.abs(s.speed_change) / (s.max_accel * s.period)


@term("collision")
def _collision(s: StepChange) -> np.ndarray:
    return -s.crashed.astype(np.float64)


@term("merge")
def _merge(s: StepChange) -> np.ndarray:
    return s.merged_now.astype(np.float64)


@term("headway")
def _headway(s: StepChange) -> np.ndarray:
    if s.gap is None or s.speed is None:
        return np.zeros_like(s.progress)
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = np.log(np.maximum(s.gap, MIN_GAP) / (HEADWAY_TIME * s.speed))
    return np.where(np.isfinite(s.gap) & (s.speed > 0), np.minimum(cost, 0.0), 0.0)


def av_gaps(snap: Snapshot, weights: RewardWeights) -> np.ndarray | None:
    """`StepChange.gap` of a snapshot: each AV's gap to its leader, inf for the other vehicles; None (no headway
    term) where its weight is 0, so the paper's reward costs the step nothing more."""
    if not weights.headway:
        return None
    return np.where(snap.kind == KIND_AV, snap.leader_gaps(), np.inf)


def utility_terms(step: StepChange) -> dict[str, np.ndarray]:
    """Every registered term's unweighted values (V,)."""
    return {name: value(step) for name, value in TERMS.items()}


def weighted_utility(terms: dict[str, np.ndarray], cfg: RewardConfig) -> dict[str, np.ndarray]:
    """Each term times its weight (`cfg.weights.<name>`); the utility is the sum of the returned arrays."""
    return {name: getattr(cfg.weights, name) * terms[name] for name in TERMS}


def step_utility(prev: Snapshot, snap: Snapshot, lane_changed: np.ndarray, invalid: np.ndarray,
                 merged_now: np.ndarray, cfg: Config) -> dict[str, np.ndarray]:
    """Each term's weighted value (V,) over `snap`'s vehicles for the decision step from `prev` to `snap`;
    `lane_changed`, `invalid` and `merged_now` are (V,) bool over `snap`'s rows. A vehicle inserted since `prev`
    starts at 0 m and its own speed, so its first step counts what it drove since insertion."""
    before = prev.rows_of(snap.ids)
    seen = before >= 0
    prev_d, prev_v = np.zeros(len(snap)), snap.speed.copy()
    prev_d[seen], prev_v[seen] = prev.distance[before[seen]], prev.speed[before[seen]]
    step = StepChange(snap.distance - prev_d, snap.speed - prev_v, lane_changed, invalid, snap.crashed, merged_now,
                      cfg.av.max_speed, cfg.av.accel, cfg.sim.decision_period, snap.speed,
                      av_gaps(snap, cfg.reward.weights))
    return weighted_utility(utility_terms(step), cfg.reward)


def svo_rewards(utility: np.ndarray, observed: np.ndarray, ego_rows: np.ndarray, merger_row: int,
                phis: np.ndarray, mean: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """utility (V,); observed (N, V) bool (ego excluded); ego_rows (N,) with -1 for absent agents;
    merger_row -1 if the merging vehicle is gone. Returns (reward, ego part, social part), each (N,);
    absent agents get 0."""
    others = observed.copy()
    if merger_row >= 0:
        others[:, merger_row] = True
    present = ego_rows >= 0
    others[np.arange(len(ego_rows))[present], ego_rows[present]] = False  # never count oneself
    others[~present] = False
    social = others.astype(np.float64) @ utility
    if mean:
        social = social / np.maximum(others.sum(axis=1), 1)
    ego = np.where(present, utility[np.maximum(ego_rows, 0)], 0.0) if len(utility) else np.zeros(len(ego_rows))
    reward = np.cos(phis) * ego + np.sin(phis) * social
    return reward, ego, social
