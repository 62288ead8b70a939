"""The paper's five meta-actions, turned into a target speed and a lane change per AV (pure functions).

Contract: `decide(actions, lanes, through, speed_targets, cfg)` maps each AV's action to its new target
speed and lane-change direction. Accelerate / decelerate move the target by `av.speed_step` within
[0, av.max_speed]; idle keeps lane and target. A lane change toward a lane that is not there, or that is
not a through lane (an acceleration lane, a lane drop), is a no-op flagged `invalid`, which the reward
may penalise. The session then ramps the actual speed toward the target within the AV's accel/decel.
`action_mask(lanes, through, speed_targets, cfg)` says, by the same rules, which actions would change something:
(N, 5) int8, 1 = can be taken; a lane change `decide` would flag `invalid` is 0, accelerate is 0 at the top target
speed `av.max_speed` and decelerate at a target of 0; idle is always 1. The env reports it in each agent's infos.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from cosim.config import AVConfig


class Action(IntEnum):
    LANE_LEFT = 0
    IDLE = 1
    LANE_RIGHT = 2
    ACCELERATE = 3
    DECELERATE = 4


N_ACTIONS = len(Action)
_LANE_DELTA = np.array([1, 0, -1, 0, 0])  # SUMO lane indices grow to the left
_SPEED_DELTA = np.array([0, 0, 0, 1, -1])


@dataclass(frozen=True)
class Decision:
    target_speed: np.ndarray  # (N,) [m/s]
    lane_change: np.ndarray  # (N,) int: +1 left, -1 right, 0 none (only valid changes)
    invalid: np.ndarray  # (N,) bool: a lane change toward no usable lane


def decide(actions: np.ndarray, lanes: np.ndarray, usable: np.ndarray, speed_targets: np.ndarray,
           av: AVConfig) -> Decision:
    """actions, lanes, speed_targets: (N,) per AV; usable: (N, L) bool, the lanes AV i may use on its
    current edge (all False on a junction-internal edge, where no lane change is possible)."""
    actions = np.asarray(actions, dtype=np.int64)
    if actions.size and (actions.min() < 0 or actions.max() >= N_ACTIONS):
        raise ValueError(f"actions must be in 0..{N_ACTIONS - 1}, got {actions.tolist()}")
    target = np.clip(speed_targets + _SPEED_DELTA[actions] * av.speed_step, 0.0, av.max_speed)
    wanted = _LANE_DELTA[actions]
    ok = _lane_ok(wanted, lanes, usable)
    change = np.where(ok, wanted, 0)
    return Decision(target_speed=target, lane_change=change, invalid=(wanted != 0) & ~ok)


def _lane_ok(wanted: np.ndarray, lanes: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(N,) bool: lane `lanes + wanted` exists on each AV's edge and may be used (usable: (N, L) bool)."""
    dest = lanes + wanted
    inside = (dest >= 0) & (dest < usable.shape[1])
    return inside & usable[np.arange(len(dest)), np.where(inside, dest, 0)]


def action_mask(lanes: np.ndarray, usable: np.ndarray, speed_targets: np.ndarray, av: AVConfig) -> np.ndarray:
    """(N, N_ACTIONS) int8, 1 where the action would change something (module doc); the arguments as `decide`'s."""
    n = len(lanes)
    mask = np.ones((n, N_ACTIONS), dtype=np.int8)
    for a in (Action.LANE_LEFT, Action.LANE_RIGHT):
        mask[:, a] = _lane_ok(np.full(n, _LANE_DELTA[a]), lanes, usable)
    mask[:, Action.ACCELERATE] = speed_targets < av.max_speed
    mask[:, Action.DECELERATE] = speed_targets > 0.0
    return mask
