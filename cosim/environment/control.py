"""The paper's five meta-actions, turned into a target speed and a lane change per AV (pure functions).

Contract: `decide(actions, lanes, through, speed_targets, cfg)` maps each AV's action to its new target
speed and lane-change direction. Accelerate / decelerate move the target by `av.speed_step` within
[0, av.max_speed]; idle keeps lane and target. A lane change toward a lane that is not there, or that is
not a through lane (an acceleration lane, a lane drop), is a no-op flagged `invalid`, which the reward
may penalise. The session then ramps the actual speed toward the target within the AV's accel/decel.
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
    dest = lanes + wanted
    inside = (dest >= 0) & (dest < usable.shape[1])
    ok = inside & usable[np.arange(len(dest)), np.where(inside, dest, 0)]
    change = np.where(ok, wanted, 0)
    return Decision(target_speed=target, lane_change=change, invalid=(wanted != 0) & ~ok)
