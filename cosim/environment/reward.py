"""Individual utility as a registry of named, weighted terms, and the paper's decentralised SVO reward (pure
functions).

Contract:
- `TERMS` maps each term's name to its default weight and its function of a `StepChange` (what one decision
  step did to every vehicle of the snapshot), giving the term's unweighted value per vehicle (V,). Adding a
  term is one function and one line: `@term("name", weight)` above it; `reward.weights.name` then sets its
  weight, `infos[agent]["reward_terms"]` reports it and the trainer logs it. This module owns the term names:
  `cosim.config` imports nothing of it at load and checks `reward.weights` against `TERMS` when it validates
  a config, so a term registered before the config is loaded is a key there. The terms: `speed` (progress /
  (max speed * period), in [0, 1]), `accel` (-|speed change| / (AV accel * period), every vehicle, so
  forcing humans to brake costs the social part), `lane_change` and `invalid_action` (-1, AVs only),
  `collision` (-1 if crashed), `merge` (+1 for the merging vehicle on the step it merges).
- `utility_terms(step)` evaluates every term; `weighted_utility(terms, cfg)` weighs them.
- `svo_rewards(u, observed, ego_rows, merger_row, phis)` is the paper's Eq. (3):
  R_i = cos(phi_i) u_i + sin(phi_i) (sum of u over the others i observes + u_M), where, as in the paper's
  sum over k in V~ ∪ {M}, the merging vehicle counts whether observed or not.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cosim.config import RewardConfig


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


@dataclass(frozen=True)
class Term:
    weight: float  # default weight; `reward.weights` overrides it
    value: Callable[[StepChange], np.ndarray]  # unweighted value per vehicle (V,)


TERMS: dict[str, Term] = {}  # in registration order, which is the order of summation


def term(name: str, weight: float) -> Callable[[Callable[[StepChange], np.ndarray]], Callable]:
    """Register a utility term under `name` with its default weight."""
    def register(fn: Callable[[StepChange], np.ndarray]) -> Callable[[StepChange], np.ndarray]:
        TERMS[name] = Term(weight, fn)
        return fn

    return register


@term("speed", 1.0)
def _speed(s: StepChange) -> np.ndarray:
    return np.clip(s.progress / (s.max_speed * s.period), 0.0, 1.0)


@term("lane_change", 0.05)
def _lane_change(s: StepChange) -> np.ndarray:
    return -s.lane_changed.astype(np.float64)


@term("invalid_action", 0.1)
def _invalid_action(s: StepChange) -> np.ndarray:
    return -s.invalid.astype(np.float64)


@term("accel", 0.05)
def _accel(s: StepChange) -> np.ndarray:
    return -np.abs(s.speed_change) / (s.max_accel * s.period)


@term("collision", 5.0)  # -5 as in the authors' follow-up code
def _collision(s: StepChange) -> np.ndarray:
    return -s.crashed.astype(np.float64)


# +10 as in the authors' follow-up code. With +2, letting the merging vehicle in lowered the guide AV's own
# discounted return at phi = pi/4 (courteous 41.5 vs scripted 42.3 over 60 episodes); with +10 it raises it
# (45.3 vs 42.8). Against SUMO-driven AVs, though, gap-opening ones earn no more with +10, so the default scenario
# sets 50 (configs/default.yaml, results/calibration/merge_weight.md).
@term("merge", 10.0)
def _merge(s: StepChange) -> np.ndarray:
    return s.merged_now.astype(np.float64)


def utility_terms(step: StepChange) -> dict[str, np.ndarray]:
    """Every registered term's unweighted values (V,)."""
    return {name: t.value(step) for name, t in TERMS.items()}


def weighted_utility(terms: dict[str, np.ndarray], cfg: RewardConfig) -> dict[str, np.ndarray]:
    """Each term times its weight; the utility is the sum of the returned arrays."""
    return {name: cfg.weight(name) * terms[name] for name in TERMS}


def svo_rewards(utility: np.ndarray, observed: np.ndarray, ego_rows: np.ndarray, merger_row: int,
                phis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    ego = np.where(present, utility[np.maximum(ego_rows, 0)], 0.0) if len(utility) else np.zeros(len(ego_rows))
    reward = np.cos(phis) * ego + np.sin(phis) * social
    return reward, ego, social
