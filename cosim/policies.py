"""Hand-written AV policies for scenario runs and baselines: a dict from name to builder.

Contract: a policy is called as `policy(env) -> {agent: action}` for the env's live agents. `scripted`
reads the env's public snapshot (it is a baseline, not a learner): cruise at `cruise_speed`, brake when
the gap to the leader in the AV's lane is under two seconds, never change lane.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.control import Action
from cosim.env import MergeEnv

Policy = Callable[[MergeEnv], dict[str, int]]


def idle_policy(seed: int = 0) -> Policy:
    return lambda env: dict.fromkeys(env.agents, int(Action.IDLE))


def random_policy(seed: int = 0) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda env: {a: int(rng.integers(len(Action))) for a in env.agents}


def scripted_policy(seed: int = 0, cruise_speed: float = 27.0, headway: float = 2.0) -> Policy:
    def act(env: MergeEnv) -> dict[str, int]:
        snap = env.snapshot
        actions = {}
        for agent in env.agents:
            r = snap.row_of(agent)
            if r < 0:
                actions[agent] = int(Action.IDLE)
                continue
            same = (snap.edge == snap.edge[r]) & (snap.lane == snap.lane[r]) & (snap.lane_pos > snap.lane_pos[r])
            gap = (snap.lane_pos[same] - snap.lane_pos[r]).min(initial=np.inf)
            if gap < headway * snap.speed[r] + snap.length[r]:
                actions[agent] = int(Action.DECELERATE)
            elif snap.speed[r] < cruise_speed - 1.0:
                actions[agent] = int(Action.ACCELERATE)
            else:
                actions[agent] = int(Action.IDLE)
        return actions

    return act


POLICIES: dict[str, Callable[..., Policy]] = {
    "idle": idle_policy,
    "random": random_policy,
    "scripted": scripted_policy,
}
