"""The PettingZoo env on real SUMO: API, determinism, meta-actions, crashes, merges, other nets."""

from __future__ import annotations

import math
from collections.abc import Iterator

import libsumo
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import cosim
from cosim.environment.control import Action, ActionError, agent_masks
from cosim.environment.merge_env import MergeEnv
from cosim.environment.policies import scripted_policy
from cosim.environment.tracker import EpisodeTracker
from cosim.errors import SimulationError
from cosim.sumo.snapshot import KIND_AV, Snapshot

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

# The env's mechanics on the free-flow scene: AVs spread over three lanes. The dilemma has tests of its own.


FREE = "configs/free_flow.yaml"
SMALL = {"scenario.n_avs": 3, "scenario.n_hvs": 6}


@pytest.fixture
def env() -> Iterator[MergeEnv]:
    e = cosim.parallel_env(FREE, SMALL)
    yield e
    e.close()


def run_episode(env: MergeEnv, seed: int, actions_of) -> list[tuple]:
    obs, _ = env.reset(seed=seed)
    trace = [{a: o.copy() for a, o in obs.items()}]
    while env.agents:
        obs, rew, term, trunc, info = env.step(actions_of(env))
        trace.append(({a: o.copy() for a, o in obs.items()}, rew, term, trunc))
    return trace


def test_parallel_api(env: MergeEnv) -> None:
    parallel_api_test(env, num_cycles=30)


def test_same_seed_same_episode() -> None:
    def fixed_actions(env: MergeEnv) -> dict[str, int]:
        step = int(round(env.snapshot.time))
        return {a: (step + i) % 5 for i, a in enumerate(env.agents)}

    traces = []
    for _ in range(2):
        e = cosim.parallel_env(FREE, SMALL)
        try:
            traces.append(run_episode(e, 7, fixed_actions))
        finally:
            e.close()
    first, second = traces
    assert len(first) == len(second) > 1
    for a, b in zip(first[1:], second[1:], strict=True):
        assert a[1] == b[1] and a[2] == b[2] and a[3] == b[3]
        for agent in a[0]:
            np.testing.assert_array_equal(a[0][agent], b[0][agent])
    # A different seed is a different scene.
    e = cosim.parallel_env(FREE, SMALL)
    try:
        other = run_episode(e, 8, fixed_actions)
    finally:
        e.close()
    assert any(not np.array_equal(first[0][a], other[0][a]) for a in first[0])


def test_reset_without_seed_counts_up(env: MergeEnv) -> None:
    _, info = env.reset(seed=3)
    assert info["av_0"]["seed"] == 3
    _, info = env.reset()
    assert info["av_0"]["seed"] == 4


def _only(env: MergeEnv, agent: str, action: Action) -> dict[str, int]:
    return {a: int(action if a == agent else Action.IDLE) for a in env.agents}


def _through_rank(env: MergeEnv, agent: str) -> int:
    """Lane counted from the rightmost through lane: comparable across edges (the merge edge has an
    acceleration lane at index 0, so raw lane indices shift by one there)."""
    snap = env.snapshot
    r = snap.row_of(agent)
    return list(np.flatnonzero(env.zone.through[snap.edge[r]])).index(int(snap.lane[r]))


@pytest.mark.parametrize("direction", [Action.LANE_LEFT, Action.LANE_RIGHT])
def test_lane_changes_move_one_lane(env: MergeEnv, direction: Action) -> None:
    env.reset(seed=0)
    delta = 1 if direction == Action.LANE_LEFT else -1
    n_lanes = int(env.zone.through[env.snapshot.edge[env.snapshot.row_of("av_0")]].sum())
    agent = next(a for a in env.agents if 0 <= _through_rank(env, a) + delta < n_lanes)
    rank = _through_rank(env, agent)
    _, _, _, _, info = env.step(_only(env, agent, direction))
    assert _through_rank(env, agent) == rank + delta
    assert not info[agent]["invalid_action"]
    assert info[agent]["reward_terms"]["lane_change"] < 0


def test_lane_change_toward_no_lane_is_flagged_noop(env: MergeEnv) -> None:
    env.reset(seed=0)
    snap = env.snapshot
    # An AV in its edge's leftmost or rightmost through lane (seed 0 has one).
    for agent in env.agents:
        n_lanes = int(env.zone.through[snap.edge[snap.row_of(agent)]].sum())
        rank = _through_rank(env, agent)
        if rank in (0, n_lanes - 1):
            break
    action = Action.LANE_LEFT if rank == n_lanes - 1 else Action.LANE_RIGHT
    _, _, _, _, info = env.step(_only(env, agent, action))
    assert _through_rank(env, agent) == rank
    assert info[agent]["invalid_action"]
    assert info[agent]["reward_terms"]["invalid_action"] < 0
    assert info[agent]["reward_terms"]["lane_change"] == 0


def test_action_masks_of_a_hand_built_situation() -> None:
    """On the dilemma net's merge edge (lane 0 the acceleration lane, 1 and 2 through lanes): the leftmost through
    lane cannot go left, the lane beside the acceleration lane cannot go right; nor can the approach's right lane,
    nor anyone inside a junction; accelerate is masked at the top target speed, decelerate at 0; an AV not on the
    road may only idle."""
    env = cosim.parallel_env("configs/default.yaml")
    try:
        index, desc = env.road.index_of, env.net.desc
        assert desc.accel_lanes == (0,) and env.net.through_lanes(desc.merge_edge) == (1, 2)
        junction = next(e for e in env.road.internal if env.road.internal[e][0].from_edge == desc.highway[0])
        edges = [index[desc.merge_edge], index[desc.merge_edge], index[desc.highway[0]], index[junction]]
        snap = Snapshot.build(ids=["av_0", "av_1", "av_2", "av_3"], kind=[KIND_AV] * 4, edge=edges, lane=[2, 1, 0, 0])
        av = env.cfg.av
        masks = agent_masks(snap, env.zone, ["av_0", "av_1", "av_2", "av_3", "av_9"],
                            np.array([av.max_speed, 0.0, 20.0, 20.0, 20.0]), av)
    finally:
        env.close()
    # columns: LANE_LEFT, IDLE, LANE_RIGHT, ACCELERATE, DECELERATE
    assert {a: m.tolist() for a, m in masks.items()} == {
        "av_0": [0, 1, 1, 0, 1], "av_1": [1, 1, 0, 1, 0], "av_2": [1, 1, 0, 1, 1], "av_3": [0, 1, 0, 1, 1],
        "av_9": [0, 1, 0, 0, 0]}
    assert all(m.dtype == np.int8 for m in masks.values())


def test_infos_mask_exactly_the_actions_that_would_change_nothing() -> None:
    """Random play on the dilemma: every live agent's infos carry its mask (also `action_masks()`), and a lane
    change the mask forbade is exactly one the env flags invalid."""
    env = cosim.parallel_env("configs/default.yaml")
    rng = np.random.default_rng(0)
    seen = {0: 0, 1: 0}
    try:
        for seed in (1, 2):
            _, infos = env.reset(seed=seed)
            while env.agents:
                masks = {a: infos[a]["action_mask"] for a in env.agents}
                assert set(masks) == set(env.agents) and all(m.shape == (5,) and m[Action.IDLE] for m in
                                                             masks.values())
                assert all(np.array_equal(m, masks[a]) for a, m in env.action_masks().items())
                actions = {a: int(rng.choice([Action.LANE_LEFT, Action.LANE_RIGHT, Action.IDLE])) for a in env.agents}
                _, _, _, _, infos = env.step(actions)
                for a, act in actions.items():
                    if act != Action.IDLE:
                        assert infos[a]["invalid_action"] == (masks[a][act] == 0), (seed, a, act)
                        seen[int(masks[a][act])] += 1
    finally:
        env.close()
    assert seen[0] > 0 and seen[1] > 0  # both kinds happened


def test_accelerate_and_decelerate_change_speed(env: MergeEnv) -> None:
    env.reset(seed=0)
    v0 = env.snapshot.speed[env.snapshot.row_of("av_1")]
    env.step(_only(env, "av_1", Action.ACCELERATE))
    v1 = env.snapshot.speed[env.snapshot.row_of("av_1")]
    step = env.cfg.av.speed_step
    assert v1 == pytest.approx(min(v0 + step, env.cfg.av.max_speed), abs=1e-6)
    env.step(_only(env, "av_1", Action.DECELERATE))
    env.step(_only(env, "av_1", Action.DECELERATE))
    v3 = env.snapshot.speed[env.snapshot.row_of("av_1")]
    assert v3 == pytest.approx(v1 - 2 * step, abs=1e-6)
    # Idle holds the target speed.
    env.step(_only(env, "av_1", Action.IDLE))
    assert env.snapshot.speed[env.snapshot.row_of("av_1")] == pytest.approx(v3, abs=1e-6)


def test_acceleration_limit_is_applied(env: MergeEnv) -> None:
    cfg = env.cfg
    env.reset(seed=0)
    v0 = env.snapshot.speed[env.snapshot.row_of("av_2")]
    # Three accelerate actions at once would ask for +3 steps; in one period the AV gains at most accel * T.
    env._target["av_2"] = v0 + 3 * cfg.av.speed_step
    env.step(_only(env, "av_2", Action.IDLE))
    gained = env.snapshot.speed[env.snapshot.row_of("av_2")] - v0
    assert gained == pytest.approx(min(cfg.av.accel * cfg.sim.decision_period, 3 * cfg.av.speed_step,
                                       cfg.av.max_speed - v0), abs=1e-6)


@pytest.mark.parametrize("on_collision", ["end", "remove"])
def test_provoked_collision_ends_the_right_agents(on_collision: str) -> None:
    env = cosim.parallel_env(FREE, {"scenario.n_avs": 3, "scenario.n_hvs": 0, "sim.on_collision": on_collision})
    try:
        env.reset(seed=0)
        snap = env.snapshot
        rows = {a: snap.row_of(a) for a in env.agents}
        front, bystander, rear = sorted(env.agents, key=lambda a: -snap.lane_pos[rows[a]])
        r = rows[front]
        edge = env.road.edge_ids[snap.edge[r]]
        # The bystander steps aside, then the rear AV is put 0.5 m behind the front one, in its lane
        # (moveTo takes the front-bumper position; jumping over a vehicle in the lane would count as a crash).
        aside = next(lane for lane in list(np.flatnonzero(env.zone.through[snap.edge[r]])) if lane != snap.lane[r])
        libsumo.vehicle.moveTo(bystander, f"{edge}_{aside}", snap.lane_pos[rows[bystander]])
        libsumo.vehicle.moveTo(rear, f"{edge}_{snap.lane[r]}", snap.lane_pos[r] - snap.length[r] - 0.5)
        ended: dict[str, bool] = {}
        for _ in range(5):
            acts = {a: int(Action.IDLE) for a in env.agents}
            acts.update({a: int(act) for a, act in ((front, Action.DECELERATE), (rear, Action.ACCELERATE))
                         if a in env.agents})
            t0 = env.snapshot.time
            _, _, term, trunc, info = env.step(acts)
            ended.update({a: t for a, t in term.items() if t})
            if front in ended:
                break
        left = list(env.agents)
        crash_time = env.snapshot.time
        period = env.cfg.sim.decision_period
    finally:
        env.close()
    assert ended.get(front) and ended.get(rear)
    assert info[front]["reward_terms"]["collision"] == -env.cfg.reward.weights.collision
    assert info[bystander]["reward_terms"]["collision"] == 0
    (c,) = info[front]["episode"]["collisions"].split(";") if on_collision == "end" else [None]
    if on_collision == "end":
        # The paper's rule: the episode ends at the SUMO step of the collision; the bystander is cut, not ended.
        assert left == [] and trunc[bystander] and not term[bystander]
        assert crash_time < t0 + period - 1e-9
        assert f"{rear}>{front} rear_end fault={rear} av" in c
    else:
        assert left == [bystander], "an AV outside the crash keeps driving"
        assert crash_time == pytest.approx(t0 + period)


def test_merge_is_detected() -> None:
    env = cosim.parallel_env(FREE, SMALL)
    try:
        env.reset(seed=1)
        policy = scripted_policy()
        merged_step = None
        k = 0
        while env.agents:
            _, _, _, _, info = env.step(policy(env))
            k += 1
            r = env.snapshot.row_of("merger")
            on_through = r >= 0 and env.zone.on_through_lane(env.snapshot.edge[r:r + 1],
                                                             env.snapshot.lane[r:r + 1])[0]
            if merged_step is None and on_through:
                merged_step = k
                assert next(iter(info.values()))["merged"]
        summary = next(iter(info.values()))["episode"]
    finally:
        env.close()
    assert merged_step is not None
    assert summary["merged"] and not summary["merge_failed"]
    assert 0 < summary["time_to_merge"] <= merged_step * env.cfg.sim.decision_period + 0.2


@pytest.mark.parametrize("end_on_stuck", [True, False])
def test_stuck_merging_vehicle_fails_the_merge(end_on_stuck: bool) -> None:
    env = cosim.parallel_env(FREE, {**SMALL, "sim.end_on_stuck": end_on_stuck})
    try:
        env.reset(seed=1)
        libsumo.vehicle.setLaneChangeMode("merger", 0)  # it never leaves the acceleration lane
        while env.agents:
            _, _, term, trunc, info = env.step({a: int(Action.IDLE) for a in env.agents})
        summary = next(iter(info.values()))["episode"]
    finally:
        env.close()
    assert summary["merge_failed"] and not summary["merged"]
    # The AVs' own episodes did not end: they are cut (truncated), not terminated.
    assert all(trunc[a] != term[a] for a in trunc) and any(trunc.values())
    # Cut once it is stuck, or (the default) it waits at the lane's end to the horizon, as SUMO's driver would.
    assert (summary["length"] < env.max_steps) == end_on_stuck
    assert summary["ended_by"] == ("merger_stuck" if end_on_stuck else "horizon")


def test_time_limit_truncates() -> None:
    env = cosim.parallel_env(FREE, {**SMALL, "sim.av_driver": "sumo"})  # SUMO's safe drivers: no crash
    try:
        env.reset(seed=2)
        steps = 0
        while env.agents:
            _, _, term, trunc, _ = env.step({a: int(Action.IDLE) for a in env.agents})
            steps += 1
    finally:
        env.close()
    assert steps == env.max_steps
    assert all(trunc[a] != term[a] for a in trunc)


def test_reward_social_mean_divides_the_social_part_by_the_vehicles_counted() -> None:
    social = {}
    for how in ("sum", "mean"):
        env = cosim.parallel_env(FREE, {**SMALL, "reward.phi": math.pi / 4, "reward.social": how})
        try:
            env.reset(seed=0)
            _, _, _, _, info = env.step({a: int(Action.ACCELERATE) for a in env.agents})
        finally:
            env.close()
        social[how] = {a: i["social_utility"] for a, i in info.items()}
    assert social["sum"].keys() == social["mean"].keys()
    for a, mean in social["mean"].items():
        assert mean != 0.0  # the merging vehicle at least is counted
        count = social["sum"][a] / mean
        assert count >= 1.0 and count == pytest.approx(round(count))


def test_reward_is_the_svo_combination_of_reported_utilities() -> None:
    for phi in (0.0, math.pi / 4, math.pi / 2):
        env = cosim.parallel_env(FREE, {**SMALL, "reward.phi": phi})
        try:
            env.reset(seed=0)
            _, rew, _, _, info = env.step({a: int(Action.ACCELERATE) for a in env.agents})
        finally:
            env.close()
        for a, r in rew.items():
            i = info[a]
            assert r == pytest.approx(math.cos(phi) * i["ego_utility"] + math.sin(phi) * i["social_utility"])
            assert i["ego_utility"] == pytest.approx(sum(i["reward_terms"].values()))
            assert i["reward_terms"]["speed"] > 0


def test_second_generated_net_runs_unchanged(two_lane_net) -> None:
    env = cosim.parallel_env(FREE, {**SMALL, "net.file": str(two_lane_net)})
    try:
        parallel_api_test(env, num_cycles=10)
        trace = run_episode(env, 0, scripted_policy())
    finally:
        env.close()
    assert len(trace) > 1
    assert env.net.desc.accel_lanes == (0,) and env.road.num_lanes("hw_in") == 2


def test_second_live_env_in_one_process_is_refused(env: MergeEnv) -> None:
    with pytest.raises(SimulationError, match="worker processes"):
        cosim.parallel_env(FREE, SMALL)
    env.close()
    cosim.parallel_env(FREE, SMALL).close()  # fine once the first is closed


def test_render_shows_scene_and_velocity_map() -> None:
    env = cosim.parallel_env(FREE, SMALL, render_mode="rgb_array")
    try:
        env.reset(seed=0)
        frame = env.render()
    finally:
        env.close()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) >= 4  # background, road, AVs, HVs at least


def test_lane_change_does_not_follow_the_av_onto_the_acceleration_lane() -> None:
    # Lane indices shift by one where the acceleration lane starts: a lane change just before the junction
    # must leave the AV on the same through lane after it, not on the acceleration lane.
    env = cosim.parallel_env(FREE, {"scenario.n_avs": 1, "scenario.n_hvs": 0})
    try:
        env.reset(seed=0)
        hw_in = env.net.desc.highway[0]
        libsumo.vehicle.moveTo("av_0", f"{hw_in}_1", env.road.edge_length(hw_in) - 10.0)
        env.step({"av_0": int(Action.LANE_RIGHT)})
        seen = []
        for _ in range(3):
            env.step({"av_0": int(Action.IDLE)})
            r = env.snapshot.row_of("av_0")
            seen.append((env.road.edge_ids[env.snapshot.edge[r]], int(env.snapshot.lane[r])))
    finally:
        env.close()
    assert seen[-1] == (env.net.desc.merge_edge, 1), seen  # hw_in lane 0 continues as the merge edge's lane 1



def test_episode_summary_is_the_trackers_row_over_every_vehicle() -> None:
    env = cosim.parallel_env(FREE, {**SMALL, "scenario.inflow": 1800.0})
    try:
        env.reset(seed=4)
        at_reset = set(env.snapshot.ids)
        mine = EpisodeTracker(env.zone, env.chainage)  # fed from outside, as an evaluation would
        mine.observe(env.snapshot)
        policy = scripted_policy()
        while env.agents:
            actions = policy(env)
            _, _, _, _, info = env.step(actions)
            mine.observe(env.snapshot, actions)
    finally:
        env.close()
    summary = next(iter(info.values()))["episode"]
    # The keys the trainer's logs read, and one implementation behind them all.
    for key in ("seed", "length", "time", "crashed", "merged", "merge_failed", "time_to_merge", "mean_distance",
                "av_distance", "hv_distance", "merger_distance"):
        assert key in summary, key
    row = mine.row()
    assert {k: summary[k] for k in row} == pytest.approx(row, nan_ok=True)
    assert summary["seed"] == 4 and summary["length"] > 0
    # Vehicles inserted after the reset (the inflow) count too.
    assert set(mine.distance) > at_reset
    assert summary["mean_distance"] == pytest.approx(np.mean(list(mine.distance.values())))


@pytest.mark.parametrize("bad", [1.7, "1", None, np.array([1, 2]), np.array([1]), 5, -1, True, np.float64(1.0)])
def test_step_refuses_what_is_not_an_action_naming_the_agent(env: MergeEnv, bad: object) -> None:
    env.reset(seed=0)
    time = env.snapshot.time
    actions = {**dict.fromkeys(env.agents, int(Action.IDLE)), "av_1": bad}
    with pytest.raises(ActionError, match=r"agent 'av_1'.*0\.\.4 \(0 LANE_LEFT, 1 IDLE.*4 DECELERATE\)") as caught:
        env.step(actions)
    assert isinstance(caught.value, ValueError)  # what gymnasium-style callers catch
    assert env.snapshot.time == time  # refused before SUMO moved: the episode goes on
    # numpy integers, 0-d arrays and Action members are actions (SB3 and SuperSuit pass numpy ones).
    _, _, term, trunc, _ = env.step({"av_0": np.int64(3), "av_1": np.array(1), "av_2": Action.LANE_LEFT})
    assert set(term) == set(trunc) == {"av_0", "av_1", "av_2"}


def test_step_refuses_an_unknown_agent_and_ignores_one_that_is_done(env: MergeEnv) -> None:
    env.reset(seed=0)
    idle = dict.fromkeys(env.agents, int(Action.IDLE))
    with pytest.raises(ActionError, match=r"unknown agent 'bogus'.*\['av_0', 'av_1', 'av_2'\].*0 LANE_LEFT"):
        env.step({**idle, "bogus": 1})
    with pytest.raises(ActionError, match=r"no action for live agents \['av_2'\]"):
        env.step({"av_0": 1, "av_1": 1})
    libsumo.vehicle.remove("av_0")  # av_0 leaves: done at the next step
    _, _, term, _, _ = env.step(idle)
    assert term["av_0"] and "av_0" not in env.agents
    # A done agent's action, None as PettingZoo's AEC form gives it, is ignored.
    _, _, term, _, _ = env.step({**dict.fromkeys(env.agents, int(Action.IDLE)), "av_0": None})
    assert "av_0" not in term


def test_a_closed_env_says_so() -> None:
    env = cosim.parallel_env(FREE, SMALL)
    env.reset(seed=0)
    env.close()
    with pytest.raises(RuntimeError, match=r"step\(\) after close\(\): this env is closed"):
        env.step(dict.fromkeys(env.possible_agents, 1))
    with pytest.raises(RuntimeError, match=r"reset\(\) after close\(\): this env is closed"):
        env.reset(seed=0)
    env.close()  # closing twice is fine


@pytest.mark.parametrize("bad", [3.0, "3", -1, True, 2**31, np.float64(3.0)],
                         ids=["float", "str", "negative", "bool", "above 32 bits", "numpy float"])
def test_reset_refuses_a_seed_sumo_would_not_take(env: MergeEnv, bad: object) -> None:
    from cosim.errors import SeedError

    with pytest.raises(SeedError, match=r"^seed: expected an integer in \[0, 2147483647\]") as caught:
        env.reset(seed=bad)
    assert isinstance(caught.value, ValueError)  # what gymnasium-style callers catch
    assert not env.agents  # refused before an episode began
    _, info = env.reset()  # the env stays usable, from the config's seed
    assert info["av_0"]["seed"] == env.cfg.sim.seed


def test_a_numpy_seed_gives_a_plain_int_summary() -> None:
    import json

    env = cosim.parallel_env(FREE, {**SMALL, "sim.horizon": 2.0})
    try:
        _, info = env.reset(seed=np.int64(5))
        while env.agents:
            _, _, _, _, info = env.step(dict.fromkeys(env.agents, int(Action.IDLE)))
    finally:
        env.close()
    summary = next(iter(info.values()))["episode"]
    assert type(summary["seed"]) is int and summary["seed"] == 5
    assert json.loads(json.dumps(summary))["seed"] == 5


def test_the_seed_sequence_starts_again_at_0_past_sumos_last_seed(env: MergeEnv) -> None:
    from cosim.config import SEED_MAX

    env.reset(seed=SEED_MAX)
    _, info = env.reset()  # the seed after SUMO's last, which the user never gave: 0, not a SeedError
    assert info["av_0"]["seed"] == 0
