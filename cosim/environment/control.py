"""The paper's five meta-actions, turned into a target speed and a lane change per AV (pure functions).

Contract: `decide(actions, lanes, through, speed_targets, cfg)` maps each AV's action to its new target
speed and lane-change direction. Accelerate / decelerate move the target by `av.speed_step` within
[0, av.max_speed]; idle keeps lane and target. A lane change toward a lane that is not there, or that is
not a through lane (an acceleration lane, a lane drop), is a no-op flagged `invalid`, which the reward
may penalise. The session then ramps the actual speed toward the target within the AV's accel/decel.
`action_mask(lanes, through, speed_targets, cfg)` says, by the same rules, which actions would change something:
(N, 5) int8, 1 = can be taken; a lane change `decide` would flag `invalid` is 0, accelerate is 0 at the top target
speed `av.max_speed` and decelerate at a target of 0; idle is always 1. The env reports it in each agent's infos.
`agent_masks(snap, zone, agents, targets, av)` gives each agent's mask in a snapshot.
`checked_actions(actions, live, possible)` is what both envs' `step` accepts: every live agent's action as an int,
or `ActionError` (a `CosimError` and a `ValueError`) naming the agent and the allowed actions.
"""

from __future__ import annotations

import reprlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from cosim.config import AVConfig
from cosim.environment.episode import MergeZone
from cosim.errors import CosimError
from cosim.sumo.snapshot import Snapshot


class Action(IntEnum):
    LANE_LEFT = 0
    IDLE = 1
    LANE_RIGHT = 2
    ACCELERATE = 3
    DECELERATE = 4


N_ACTIONS = len(Action)
_LANE_DELTA = np.array([1, 0, -1, 0, 0])  # SUMO lane indices grow to the left
_SPEED_DELTA = np.array([0, 0, 0, 1, -1])
_CHANGES = np.array([Action.LANE_LEFT, Action.LANE_RIGHT])
_IDLE_ONLY = np.eye(N_ACTIONS, dtype=np.int8)[Action.IDLE]  # the mask of an agent not on the road


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
    ok = _lane_ok(wanted[:, None], lanes, usable)[:, 0]
    change = np.where(ok, wanted, 0)
    return Decision(target_speed=target, lane_change=change, invalid=(wanted != 0) & ~ok)


def _lane_ok(wanted: np.ndarray, lanes: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(N, K) bool: lane `lanes + wanted` exists on each AV's edge and may be used; wanted (N, K) or (K,) lane
    changes, lanes (N,), usable (N, L) bool."""
    dest = np.asarray(lanes)[:, None] + wanted
    inside = (dest >= 0) & (dest < usable.shape[1])
    return inside & usable[np.arange(len(dest))[:, None], np.where(inside, dest, 0)]


def action_mask(lanes: np.ndarray, usable: np.ndarray, speed_targets: np.ndarray, av: AVConfig) -> np.ndarray:
    """(N, N_ACTIONS) int8, 1 where the action would change something (module doc); the arguments as `decide`'s."""
    mask = np.empty((len(lanes), N_ACTIONS), dtype=np.int8)
    mask[:, _CHANGES] = _lane_ok(_LANE_DELTA[_CHANGES], lanes, usable)  # both lane changes in one pass
    mask[:, Action.IDLE] = 1
    mask[:, Action.ACCELERATE] = speed_targets < av.max_speed
    mask[:, Action.DECELERATE] = speed_targets > 0.0
    return mask


# -- what a step() accepts as actions --------------------------------------------------------------
ALLOWED_ACTIONS = f"an integer in 0..{N_ACTIONS - 1} ({', '.join(f'{int(a)} {a.name}' for a in Action)})"


class ActionError(CosimError, ValueError):
    """`MergeEnv.step` got something that is not an action of a live agent (a ValueError, as gymnasium's
    callers expect of a bad action)."""


def checked_action(agent: str, value: Any) -> int:
    """`value` as an action index, or `ActionError` naming `agent` and the allowed actions. Python ints (and
    `Action` members) and numpy integers, 0-d arrays included (what SB3 and SuperSuit hand over), are
    actions; floats, strings, bools, None and arrays of a shape are not, as in gymnasium's `Discrete`."""
    if type(value) is int and 0 <= value < N_ACTIONS:  # the trainer's and the evaluation's own actions
        return value
    if isinstance(value, np.ndarray):
        integral = value.shape == () and value.dtype.kind in "iu"
    else:  # a bool is an int to Python, not an action
        integral = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if integral and 0 <= int(value) < N_ACTIONS:
        return int(value)
    raise ActionError(f"step(): agent {agent!r}: action {reprlib.repr(value)} ({type(value).__name__}) is not "
                      f"allowed; expected {ALLOWED_ACTIONS}")


def checked_actions(actions: Mapping[str, Any], live: Sequence[str], possible: Sequence[str]) -> dict[str, int]:
    """Every live agent's action as an int, or `ActionError`: for actions that are not a dict, a live agent without
    one, an agent the env does not have (not in `possible`), or a value that is no action (`checked_action`). The
    actions of agents that are done are dropped unchecked: PettingZoo's AEC form steps them with None, SuperSuit's
    black death and a loop over the last observations hand them over too."""
    if not isinstance(actions, Mapping):
        raise ActionError(f"step(): expected a dict of agent -> action, got {type(actions).__name__}")
    missing = [a for a in live if a not in actions]
    if missing:
        raise ActionError(f"step(): no action for live agents {missing}; each takes {ALLOWED_ACTIONS}")
    if len(actions) > len(live):
        known = set(possible)
        unknown = [a for a in actions if a not in known]
        if unknown:
            shown = list(possible) if len(possible) <= 8 else f"{possible[0]} .. {possible[-1]}"
            raise ActionError(f"step(): unknown agent {unknown[0]!r}; this env's agents are {shown} (live now: "
                              f"{list(live)}), each taking {ALLOWED_ACTIONS}")
    return {a: checked_action(a, actions[a]) for a in live}


def agent_masks(snap: Snapshot, zone: MergeZone, agents: Sequence[str], targets: np.ndarray,
                av: AVConfig) -> dict[str, np.ndarray]:
    """Agent -> its action mask in `snap` (`cosim.environment.control.action_mask`), `targets` (len(agents),) their
    target speeds [m/s]; an agent not on the road (none live is) may only idle."""
    rows = snap.rows_of(agents)
    present = rows >= 0
    safe = np.maximum(rows, 0)
    # Edge -1 indexes the zone's extra row, which has no usable lane.
    edge = np.where(present, snap.edge[safe] if len(snap) else -1, -1)
    lane = np.where(present, snap.lane[safe] if len(snap) else 0, 0)
    mask = action_mask(lane, zone.through[edge], np.asarray(targets, dtype=np.float64), av)
    mask[~present] = _IDLE_ONLY
    return dict(zip(agents, mask, strict=True))
