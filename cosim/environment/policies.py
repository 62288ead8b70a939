"""Hand-written AV policies for scenario runs and baselines: a dict from name to builder.

Contract: a policy is called as `policy(env) -> {agent: action}` for the env's live agents; the rule-based
ones read the env's public snapshot and net geometry (they are baselines, not learners):
- `idle` keeps every AV's lane and target speed; `random` draws actions uniformly.
- `scripted`, the egoistic reference: cruise at `cruise_factor` times the highway's speed limit at the merge
  (`Net.speed_limit`), keep a `headway` [s] to the leader in the AV's lane (plus the distance needed to match a
  slower leader's speed at `brake` [m/s^2]), never change lane.
- `courteous`: scripted, except for the AV best placed to let a merging vehicle in, the nearest AV behind
  it in the lane it must enter (up to `reach` seconds at cruise speed behind) while it has not merged: that
  AV moves one lane left where the left lane has room, else slows down below the merging vehicle's speed (not
  below `min_speed_factor` times the limit) so that a gap opens in front of it. Under demand, with many
  merging vehicles, each gets its own AV (the one furthest on first).
Positions are chainages along the highway (`cosim.sumo.net.Chainage`), so leaders on the next edge count.
Speeds follow the net's limit, so a baseline means the same on a 60 km/h and a 130 km/h road.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.environment.control import Action
from cosim.environment.merge_env import MergeEnv
from cosim.sumo.snapshot import KIND_MERGER, Snapshot

Policy = Callable[[MergeEnv], dict[str, int]]


def idle_policy(seed: int = 0) -> Policy:
    return lambda env: dict.fromkeys(env.agents, int(Action.IDLE))


def random_policy(seed: int = 0) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda env: {a: int(rng.integers(len(Action))) for a in env.agents}


class _Road:
    """Chainage [m], lane rank and the leader gap of every vehicle of one snapshot."""

    def __init__(self, env: MergeEnv, snap: Snapshot) -> None:
        self.snap = snap
        self.s = env.chainage.of(snap)  # (V,) front bumper, NaN off the axis
        self.rank = env.zone.lane_rank(snap)  # (V,) -1 off the through lanes

    def gap_ahead(self, r: int, rank: int, behind: float = 0.0) -> tuple[float, float]:
        """(gap [m], speed [m/s]) of the nearest vehicle in lane `rank` whose front is ahead of vehicle r's
        front minus `behind` [m] (inf, inf without one); gap is bumper to bumper."""
        snap, s = self.snap, self.s
        ahead = (self.rank == rank) & (s > s[r] - behind)
        ahead[r] = False
        if not ahead.any():
            return np.inf, np.inf
        k = np.flatnonzero(ahead)[np.argmin(s[ahead])]
        return float(s[k] - snap.length[k] - s[r]), float(snap.speed[k])

    def follower_gap(self, r: int, rank: int) -> tuple[float, float]:
        """(gap [m], speed [m/s]) behind vehicle r to the nearest vehicle in lane `rank` whose front is behind
        r's front (inf, 0 without one)."""
        snap, s = self.snap, self.s
        behind = (self.rank == rank) & (s <= s[r])
        behind[r] = False
        if not behind.any():
            return np.inf, 0.0
        k = np.flatnonzero(behind)[np.argmax(s[behind])]
        return float(s[r] - snap.length[r] - s[k]), float(snap.speed[k])


def _follow(v: float, gap: float, v_lead: float, cruise: float, headway: float, brake: float) -> int:
    """Decelerate when the gap is shorter than a safe one, accelerate toward `cruise` when it is ample."""
    need = 2.0 + v * headway + max(0.0, (v * v - v_lead * v_lead) / (2.0 * brake))
    if gap < need:
        return int(Action.DECELERATE)
    if v < cruise - 0.5 and gap > need + 2.5 * (1.0 + headway):
        return int(Action.ACCELERATE)
    return int(Action.IDLE)


# 0.81 x 33.33 m/s = 27 m/s on the dilemma net, the stream's upper speed.
def scripted_policy(seed: int = 0, cruise_factor: float = 0.81, headway: float = 1.0, brake: float = 2.0) -> Policy:
    def act(env: MergeEnv) -> dict[str, int]:
        road = _Road(env, env.snapshot)
        cruise = cruise_factor * env.net.speed_limit
        return {a: _scripted(road, road.snap.row_of(a), cruise, headway, brake) for a in env.agents}

    return act


def _scripted(road: _Road, r: int, cruise: float, headway: float, brake: float) -> int:
    if r < 0 or road.rank[r] < 0:  # gone, or crossing a junction: hold on
        return int(Action.IDLE)
    gap, v_lead = road.gap_ahead(r, int(road.rank[r]))
    return _follow(float(road.snap.speed[r]), gap, v_lead, cruise, headway, brake)


# reach 4.45 s at 27 m/s = 120 m and min_speed 0.24 x 33.33 = 8 m/s on the dilemma net.
def courteous_policy(seed: int = 0, cruise_factor: float = 0.81, headway: float = 1.0, brake: float = 2.0,
                     reach: float = 4.45, min_speed_factor: float = 0.24) -> Policy:
    def act(env: MergeEnv) -> dict[str, int]:
        road = _Road(env, env.snapshot)
        snap = road.snap
        cruise_speed = cruise_factor * env.net.speed_limit
        reach_m, min_speed = reach * cruise_speed, min_speed_factor * env.net.speed_limit
        actions = {a: _scripted(road, snap.row_of(a), cruise_speed, headway, brake) for a in env.agents}
        target = env.zone.target_rank
        rows = {a: snap.row_of(a) for a in env.agents}
        # Every merging vehicle still on the ramp or its acceleration lane, the one furthest on first (under
        # demand there are many); each gets the nearest free AV behind it in the lane it must enter.
        waiting = [int(m) for m in np.flatnonzero(snap.kind == KIND_MERGER)
                   if road.rank[m] < 0 and np.isfinite(road.s[m])]
        taken: set[str] = set()
        for m in sorted(waiting, key=lambda m: -road.s[m]):
            behind = {a: road.s[m] - road.s[r] for a, r in rows.items() if a not in taken
                      and r >= 0 and road.rank[r] == target and -5.0 <= road.s[m] - road.s[r] <= reach_m}
            if not behind:
                continue
            guide = min(behind, key=behind.__getitem__)
            taken.add(guide)
            actions[guide] = _open_gap(env, road, rows[guide], m, actions[guide], headway, min_speed)
        return actions

    return act


def _open_gap(env: MergeEnv, road: _Road, r: int, m: int, action: int, headway: float, min_speed: float) -> int:
    """The guide AV (row r) makes room for merging vehicle m: one lane left where that lane has room, else
    slower than the merging vehicle (not below `min_speed`)."""
    snap = road.snap
    v = float(snap.speed[r])
    left = env.zone.target_rank + 1
    if env.zone.rank.max() >= left:  # a lane to the left: go there if it has room
        gap_f, _ = road.gap_ahead(r, left, behind=snap.length[r])
        gap_b, v_b = road.follower_gap(r, left)
        if gap_f > 2.0 + v * headway and gap_b > 2.0 + v_b * headway + max(0.0, v_b - v) * 2.0:
            return int(Action.LANE_LEFT)
    if action != int(Action.DECELERATE) and v > max(min_speed, float(snap.speed[m]) - 2.0):
        return int(Action.DECELERATE)
    return action


POLICIES: dict[str, Callable[..., Policy]] = {
    "idle": idle_policy,
    "random": random_policy,
    "scripted": scripted_policy,
    "courteous": courteous_policy,
}
