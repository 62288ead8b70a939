"""The merge under traffic demand as a PettingZoo env, on real SUMO: the API test with AVs that come and go, names
never reused, observation slots handed on clean, collisions taken off while the run goes on, the plan's demand."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from cosim.config import SEED_MAX, load_config
from cosim.environment.control import Action, ActionError
from cosim.environment.demand_env import DemandEnv
from cosim.errors import ConfigError
from cosim.sumo.demand import plan_demand, resolve_demand
from cosim.sumo.net import load_net
from cosim.sumo.resolve import resolve
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER

pytestmark = pytest.mark.sumo

SHORT = {"demand.enabled": True, "demand.warmup": 30.0, "demand.window": 60.0, "demand.av_penetration": 0.3}


def _env(**over: object) -> DemandEnv:
    return DemandEnv(load_config("configs/default.yaml", {**SHORT, **over}))


def test_the_plan_draws_the_demand_it_is_given() -> None:
    cfg = load_config("configs/default.yaml", {**SHORT, "demand.window": 3570.0, "demand.mainline_vph": 1200.0,
                                               "demand.ramp_vph": 600.0, "demand.av_penetration": 0.25})
    net = load_net(cfg.net.file)
    cfg = resolve(cfg, net).config
    d = resolve_demand(cfg, net)
    plan = plan_demand(cfg, net, d, 3)
    assert plan == plan_demand(cfg, net, d, 3) and plan != plan_demand(cfg, net, d, 4)
    kinds = np.array([a.kind for a in plan])
    hours = d.horizon / 3600
    # An hour at 2 x 1,200 veh/h on the highway and 600 on the ramp (Poisson: within 4 standard deviations).
    assert abs(np.sum(kinds != KIND_MERGER) - 2400 * hours) < 4 * np.sqrt(2400 * hours)
    assert abs(np.sum(kinds == KIND_MERGER) - 600 * hours) < 4 * np.sqrt(600 * hours)
    avs = [a for a in plan if a.kind == KIND_AV]
    assert abs(len(avs) / np.sum(kinds != KIND_MERGER) - 0.25) < 0.04
    assert [a.vid for a in avs] == [f"av_{i}" for i in range(len(avs))] and len(avs) <= d.max_avs
    assert all(a.route == "ramp_0" for a in plan if a.kind == KIND_MERGER)
    assert [a.depart for a in plan] == sorted(a.depart for a in plan)
    seven = load_config(cfg, {"demand.av_count": 7})
    counted = plan_demand(seven, net, resolve_demand(seven, net), 3)
    assert sum(a.kind == KIND_AV for a in counted) == 7 and sum(a.kind == KIND_HV for a in counted) > 0


def test_the_demand_env_passes_the_pettingzoo_api_test() -> None:
    env = _env()
    try:
        parallel_api_test(env, num_cycles=200)
    finally:
        env.close()


def test_avs_come_and_go_in_slots_and_a_crash_leaves_the_run_going() -> None:
    env = _env()
    try:
        assert env.possible_agents == [f"av_{i}" for i in range(env.demand.max_avs)]
        obs, _ = env.reset(seed=5)
        seen, finished, steps, max_present, at_top = set(env.agents), set(), 0, len(env.agents), False
        while env.agents:
            # AVs that accelerate without end run into the traffic ahead.
            obs, rew, term, trunc, infos = env.step(dict.fromkeys(env.agents, int(Action.ACCELERATE)))
            steps += 1
            masks = env.action_masks()
            for a in env.agents:
                assert a not in finished  # a name is never reused
                assert obs[a].shape == env.observation_space(a).shape
                # Each live agent's mask in its infos, newcomers' too; accelerating without end reaches the top.
                assert np.array_equal(infos[a]["action_mask"], masks[a]) and masks[a][Action.IDLE] == 1
            at_top |= any(m[Action.ACCELERATE] == 0 for m in masks.values())
            finished |= {a for a in term if term[a] or trunc[a]}
            seen |= set(env.agents)
            max_present = max(max_present, len(env.agents))
            assert len(env.slot) <= env.demand.slots and len(set(env.slot.values())) == len(env.slot)
        assert env.steps == env.max_steps  # the run went on to its horizon
        assert len(seen) > max_present  # AVs came and went, their slots handed on
        assert any(info.get("crashed") for info in infos.values()) or env.last_record["crashed"].size
        assert env.last_summary["avs_released"] == len(seen) and at_top
        assert (env.out_dir / "record.npz").is_file() and env.last_outputs.passages
    finally:
        env.close()


@pytest.mark.parametrize("exit_as", ["truncated", "terminated"])
def test_an_av_that_leaves_the_net_is_cut_there_with_the_map_it_acted_on(exit_as: str) -> None:
    env = _env(**{"demand.exit": exit_as})
    try:
        obs, _ = env.reset(seed=5)
        left = 0
        while env.agents and env.steps < env.max_steps - 1:  # the horizon's truncation is another test's
            acted = {a: obs[a].copy() for a in env.agents}
            obs, _, term, trunc, infos = env.step(dict.fromkeys(env.agents, int(Action.IDLE)))
            for a in acted:
                if (term[a] or trunc[a]) and not infos[a]["crashed"]:  # drove out of the net
                    left += 1
                    if exit_as == "truncated":  # bootstrapped from the map it last acted on, never zeros
                        assert trunc[a] and not term[a]
                        assert np.array_equal(obs[a], acted[a]) and obs[a].any()
                    else:
                        assert term[a] and not trunc[a] and not obs[a].any()
                elif infos[a]["crashed"]:
                    assert term[a] and not trunc[a]
        assert left >= 3
    finally:
        env.close()


def test_too_few_observation_slots_is_one_line_naming_the_key() -> None:
    env = _env(**{"demand.max_avs_present": 1, "demand.av_penetration": 0.9})
    try:
        with pytest.raises(ConfigError, match=r"demand.max_avs_present: 2 AVs present at once .* 1 observation slots"):
            env.reset(seed=1)
            while env.agents:
                env.step(dict.fromkeys(env.agents, int(Action.IDLE)))
    finally:
        env.close()


def test_an_unknown_agent_is_an_action_error_as_in_the_episode_env() -> None:
    env = _env()
    try:
        env.reset(seed=5)
        while not env.agents:  # AVs enter after a while
            env.step({})
        actions = dict.fromkeys(env.agents, 1)
        for bogus in ("bogus", f"av_{len(env.possible_agents)}"):
            with pytest.raises(ActionError, match=f"unknown agent '{bogus}'"):
                env.step({**actions, bogus: 1})
    finally:
        env.close()


def test_the_seed_sequence_starts_again_at_0_past_sumos_last_seed() -> None:
    env = _env()
    try:
        env.reset(seed=SEED_MAX)
        _, infos = env.reset()  # the next seed of the sequence, which SUMO cannot take: 0
        assert env.episode_seed == 0
    finally:
        env.close()
