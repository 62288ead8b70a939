"""Individual utility as named, weighted terms, and the paper's decentralised SVO reward (pure functions).

Contract:
- `utility_terms(...)` gives each vehicle's unweighted terms (V,) from one decision step: `speed`
  (progress / (max speed * period), in [0, 1]), `accel` (-|speed change| / (AV accel * period), every
  vehicle, so forcing humans to brake costs the social part), `lane_change` and `invalid_action` (-1, AVs
  only), `collision` (-1 if crashed), `merge` (+1 for the merging vehicle on the step it merges).
- `svo_rewards(u, observed, ego_rows, merger_row, phis)` is the paper's Eq. (3):
  R_i = cos(phi_i) u_i + sin(phi_i) (sum of u over the others i observes + u_M), where, as in the paper's
  sum over k in V~ ∪ {M}, the merging vehicle counts whether observed or not.
"""

from __future__ import annotations

import numpy as np

from cosim.config import REWARD_TERMS, RewardConfig


def utility_terms(progress: np.ndarray, speed_change: np.ndarray, lane_changed: np.ndarray,
                  invalid: np.ndarray, crashed: np.ndarray, merged_now: np.ndarray, *, max_speed: float,
                  max_accel: float, period: float) -> dict[str, np.ndarray]:
    """All inputs (V,) over the snapshot's vehicles; progress [m] and speed_change [m/s] over the period."""
    return {
        "speed": np.clip(progress / (max_speed * period), 0.0, 1.0),
        "lane_change": -lane_changed.astype(np.float64),
        "invalid_action": -invalid.astype(np.float64),
        "accel": -np.abs(speed_change) / (max_accel * period),
        "collision": -crashed.astype(np.float64),
        "merge": merged_now.astype(np.float64),
    }


def weighted_utility(terms: dict[str, np.ndarray], cfg: RewardConfig) -> dict[str, np.ndarray]:
    """Each term times its weight; the utility is the sum of the returned arrays."""
    return {name: cfg.weight(name) * terms[name] for name in REWARD_TERMS}


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
