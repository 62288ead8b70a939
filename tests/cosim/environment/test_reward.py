"""The SVO reward on a hand-built scene equals the paper's formula at phi = 0, pi/4, pi/2."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cosim
from cosim.config import ObservationConfig, RewardConfig, RewardWeights, load_config
from cosim.environment.reward import (
    TERMS,
    StepChange,
    av_gaps,
    step_utility,
    svo_rewards,
    term,
    utility_terms,
    weighted_utility,
)
from cosim.environment.velocity_map import RoadRaster, VelocityMapper
from cosim.errors import ConfigError
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

# Two AVs, two HVs, the merging vehicle. av_0 sees av_1 and hv_0; hv_1 is 300 m away; the merger is
# out of av_0's window too, but counts anyway (the paper's k in V~ ∪ {M}).


SCENE = Snapshot.build(
    ids=["av_0", "av_1", "hv_0", "hv_1", "merger"],
    kind=[KIND_AV, KIND_AV, KIND_HV, KIND_HV, KIND_MERGER],
    x=[0.0, 20.0, -15.0, 300.0, 0.0],
    y=[0.0, 3.2, 0.0, 0.0, -100.0],
    speed=[20.0, 25.0, 18.0, 30.0, 15.0],
)
UTILITY = np.array([0.5, 0.8, 0.4, 0.9, -1.0])


def observed() -> np.ndarray:
    road = RoadRaster(grid=np.ones((10, 10), dtype=bool), origin=(-1000.0, -1000.0), resolution=200.0)
    mapper = VelocityMapper(ObservationConfig(speed_scale=15.0), road, n_agents=2)
    return mapper.observed(SCENE, SCENE.rows_of(["av_0", "av_1"]))


@pytest.mark.parametrize("phi", [0.0, math.pi / 4, math.pi / 2])
def test_svo_reward_matches_formula(phi: float) -> None:
    obs = observed()
    assert obs[0].tolist() == [False, True, True, False, False]
    rows = SCENE.rows_of(["av_0", "av_1"])
    reward, ego, social = svo_rewards(UTILITY, obs, rows, merger_row=4, phis=np.array([phi, phi]))
    # av_0: own 0.5; others it sees: av_1 0.8 + hv_0 0.4; plus the merger -1.0.
    expected_0 = math.cos(phi) * 0.5 + math.sin(phi) * (0.8 + 0.4 - 1.0)
    assert reward[0] == pytest.approx(expected_0)
    assert ego[0] == 0.5 and social[0] == pytest.approx(0.2)
    # av_1 computed the same way from its own window.
    seen = [j for j in range(5) if obs[1, j] or j == 4]
    assert 1 not in seen
    expected_1 = math.cos(phi) * 0.8 + math.sin(phi) * UTILITY[seen].sum()
    assert reward[1] == pytest.approx(expected_1)


def test_phi_zero_is_egoistic_and_pi_half_ignores_self() -> None:
    obs = observed()
    rows = SCENE.rows_of(["av_0", "av_1"])
    r0, _, _ = svo_rewards(UTILITY, obs, rows, 4, np.zeros(2))
    assert r0.tolist() == [0.5, 0.8]
    u = UTILITY.copy()
    u[0] = 100.0  # av_0's own utility no longer matters to itself at pi/2
    r1, _, _ = svo_rewards(u, obs, rows, 4, np.full(2, math.pi / 2))
    r2, _, _ = svo_rewards(UTILITY, obs, rows, 4, np.full(2, math.pi / 2))
    assert r1[0] == pytest.approx(r2[0])


def test_absent_agent_and_gone_merger() -> None:
    obs = observed()
    rows = np.array([0, -1])
    reward, ego, social = svo_rewards(UTILITY, obs, rows, merger_row=-1, phis=np.full(2, math.pi / 4))
    assert reward[1] == 0.0 and ego[1] == 0.0 and social[1] == 0.0
    assert social[0] == pytest.approx(0.8 + 0.4)  # no merger term once it is gone


def test_the_social_part_as_a_mean_does_not_grow_with_the_vehicles_counted() -> None:
    obs = observed()
    rows = SCENE.rows_of(["av_0", "av_1"])
    phis = np.full(2, math.pi / 4)
    _, _, summed = svo_rewards(UTILITY, obs, rows, merger_row=4, phis=phis)
    reward, ego, social = svo_rewards(UTILITY, obs, rows, merger_row=4, phis=phis, mean=True)
    assert social[0] == pytest.approx((0.8 + 0.4 - 1.0) / 3)  # av_1, hv_0 and the merger
    assert reward[0] == pytest.approx(math.cos(math.pi / 4) * 0.5 + math.sin(math.pi / 4) * social[0])
    counted = obs.sum(axis=1) + ~obs[:, 4]  # the merger counts whether observed or not
    np.testing.assert_allclose(social * counted, summed)
    # A second observed vehicle of the same utility leaves the mean as it was and adds to the sum.
    wider = np.concatenate([obs, obs[:, 2:3]], axis=1)
    u = np.append(UTILITY, UTILITY[2])
    scene_rows = np.array([0, 1])
    assert svo_rewards(u, wider, scene_rows, 4, phis, mean=True)[2][0] == pytest.approx(
        (0.8 + 0.4 + 0.4 - 1.0) / 4)
    assert svo_rewards(u, wider, scene_rows, 4, phis)[2][0] == pytest.approx(0.8 + 0.4 + 0.4 - 1.0)
    alone = svo_rewards(UTILITY, np.zeros_like(obs), rows, -1, phis, mean=True)[2]
    assert alone.tolist() == [0.0, 0.0]  # nobody else: no social part, not a division by zero


def test_utility_terms_and_weights() -> None:
    terms = utility_terms(StepChange(
        progress=np.array([33.0, 16.5, 0.0]), speed_change=np.array([0.0, -3.0, 1.5]),
        lane_changed=np.array([True, False, False]), invalid=np.array([False, True, False]),
        crashed=np.array([False, False, True]), merged_now=np.array([False, False, True]),
        max_speed=33.0, max_accel=3.0, period=1.0,
    ))
    assert terms["speed"].tolist() == [1.0, 0.5, 0.0]
    assert terms["accel"].tolist() == [0.0, -1.0, -0.5]
    assert terms["lane_change"].tolist() == [-1.0, 0.0, 0.0]
    assert terms["invalid_action"].tolist() == [0.0, -1.0, 0.0]
    assert terms["collision"].tolist() == [0.0, 0.0, -1.0]
    assert terms["merge"].tolist() == [0.0, 0.0, 1.0]
    cfg = RewardConfig(weights={"speed": 2.0})
    weighted = weighted_utility(terms, cfg)
    assert list(weighted) == list(TERMS) == ["speed", "lane_change", "invalid_action", "accel", "collision", "merge",
                                             "headway"]
    assert terms["headway"].tolist() == [0.0, 0.0, 0.0]  # no gaps given: a step of the paper's reward
    assert weighted["speed"].tolist() == [2.0, 1.0, 0.0]
    assert weighted["collision"].tolist() == [0.0, 0.0, -RewardWeights().collision]


def test_a_steps_utility_counts_each_vehicle_from_its_own_previous_row_and_a_newcomer_from_insertion() -> None:
    cfg = load_config("configs/default.yaml", {"reward.weights.headway": 0.0, "av.max_speed": 30.0})
    period, vmax, accel = cfg.sim.decision_period, cfg.av.max_speed, cfg.av.accel
    prev = Snapshot.build(ids=["hv_0", "av_0", "gone"], kind=[KIND_HV, KIND_AV, KIND_HV],
                          distance=[50.0, 100.0, 10.0], speed=[20.0, 10.0, 5.0])
    # Rows reordered, "gone" left, "new" inserted during the step (4 m driven since, at 8 m/s).
    snap = Snapshot.build(ids=["new", "av_0", "hv_0"], kind=[KIND_HV, KIND_AV, KIND_HV],
                          distance=[4.0, 100.0 + vmax * period / 2, 70.0], speed=[8.0, 10.0 + accel * period, 20.0])
    u = step_utility(prev, snap, lane_changed=np.array([False, True, False]), invalid=np.zeros(3, bool),
                     merged_now=np.zeros(3, bool), cfg=cfg)
    w = cfg.reward.weights
    assert u["speed"] == pytest.approx(w.speed * np.array([4.0, vmax * period / 2, 20.0]) / (vmax * period))
    assert u["accel"] == pytest.approx([0.0, -w.accel, 0.0])  # the newcomer's speed change counts from its own
    assert u["lane_change"].tolist() == [0.0, -w.lane_change, 0.0]
    assert u["headway"].tolist() == [0.0] * 3


def test_headway_costs_an_av_closer_than_1_2_s_to_its_leader_on_its_lane() -> None:
    # Lane 0 of edge 0: av_0 (front at 10 m) behind hv_0 (front at 30 m, 5 m long: a 15 m gap), hv_0 behind av_1
    # (front at 100 m: 65 m); av_2 alone on lane 1; hv_1 on lane 0 of edge 1 leads no one of edge 0; av_3 stands
    # alone on edge 2.
    snap = Snapshot.build(
        ids=["av_0", "hv_0", "av_1", "av_2", "hv_1", "av_3"],
        kind=[KIND_AV, KIND_HV, KIND_AV, KIND_AV, KIND_HV, KIND_AV],
        edge=[0, 0, 0, 0, 1, 2], lane=[0, 0, 0, 1, 0, 0], lane_pos=[10.0, 30.0, 100.0, 50.0, 5.0, 1.0],
        speed=[25.0, 20.0, 30.0, 30.0, 30.0, 0.0],
    )
    assert snap.leader_gaps().tolist() == [15.0, 65.0, np.inf, np.inf, np.inf, np.inf]
    gaps = av_gaps(snap, RewardWeights(headway=1.0))
    assert gaps.tolist() == [15.0, np.inf, np.inf, np.inf, np.inf, np.inf]  # only AVs are charged
    assert av_gaps(snap, RewardWeights()) is None  # weight 0: the paper's reward, nothing computed
    step = StepChange(progress=np.zeros(6), speed_change=np.zeros(6), lane_changed=np.zeros(6, bool),
                      invalid=np.zeros(6, bool), crashed=np.zeros(6, bool), merged_now=np.zeros(6, bool),
                      max_speed=33.0, max_accel=3.0, period=1.0, speed=snap.speed, gap=gaps)
    headway = utility_terms(step)["headway"]
    assert headway[0] == pytest.approx(math.log(15.0 / (1.2 * 25.0)))  # 0.6 s behind: ln(0.5)
    assert headway[1:].tolist() == [0.0] * 5
    far = StepChange(**{**step.__dict__, "gap": np.array([40.0, *[np.inf] * 5])})  # 1.6 s: no cost
    assert utility_terms(far)["headway"].tolist() == [0.0] * 6
    touching = StepChange(**{**step.__dict__, "gap": np.array([-0.5, *[np.inf] * 5])})  # overlap: bounded
    assert utility_terms(touching)["headway"][0] == pytest.approx(math.log(0.1 / 30.0))


def test_the_terms_are_the_weights_fields() -> None:
    # The registry and the config section name the same terms in the same order (the order of summation): a field
    # without a function fails here, a function without a field already at registration (below).
    assert list(TERMS) == list(RewardWeights.model_fields)
    schema = RewardConfig.model_json_schema()["$defs"]["RewardWeights"]["properties"]
    assert list(schema) == list(TERMS)
    assert all(prop["description"].endswith("[-]") and "default" in prop for prop in schema.values())
    assert {name: prop["default"] for name, prop in schema.items()} == {
        "speed": 1.0, "lane_change": 0.05, "invalid_action": 0.1, "accel": 0.05, "collision": 5.0, "merge": 10.0,
        "headway": 0.0}


def test_a_new_term_is_its_function_and_its_field(monkeypatch: pytest.MonkeyPatch) -> None:
    # A function without a field is refused when it is registered (at import, for a term in the reward module):
    # it would have no weight, no config key and no line in the key reference. Refusing there, rather than only in
    # the registry-equals-fields test above, stops a user's own term too, with the fix in the message.
    with pytest.raises(ValueError, match="add the field constant to cosim.config.RewardWeights"):
        @term("constant")
        def _constant(s: StepChange) -> np.ndarray:
            return np.ones_like(s.progress)
    assert "constant" not in TERMS
    with pytest.raises(ValueError, match="registered already"):
        term("speed")
    # With its field, the field's key weighs the function and every agent's infos report the term, weighted, on
    # real SUMO: a registered term (its function swapped for a constant 1) stands in for a new one.
    monkeypatch.setitem(TERMS, "speed", lambda s: np.ones_like(s.progress))
    env = cosim.parallel_env("configs/smoke.yaml", {"reward.weights.speed": 2.0})
    try:
        env.reset(seed=3)
        _, _, _, _, infos = env.step({a: 1 for a in env.agents})
    finally:
        env.close()
    assert infos and all(info["reward_terms"]["speed"] == 2.0 for info in infos.values())
    # A key that names no term is an error naming it and listing the terms.
    with pytest.raises(ConfigError) as caught:
        load_config("configs/smoke.yaml", {"reward.weights.constant": 2.0})
    assert str(caught.value) == ("reward.weights.constant: unknown term; the terms: speed, lane_change, "
                                 "invalid_action, accel, collision, merge, headway")


def test_headway_on_real_sumo_charges_the_avs_that_follow_closely() -> None:
    # The default scene's dense stream: AVs accelerating into it come closer than 1.2 s to their leaders; the term
    # never rewards, and an AV's cost is its own gap's, as SUMO reports the gap.
    env = cosim.parallel_env("configs/default.yaml", {"reward.weights.headway": 1.0})
    costs = []
    try:
        env.reset(seed=10_000_003)
        while env.agents:
            _, _, _, _, infos = env.step({a: 3 for a in env.agents})  # faster
            for a, info in infos.items():
                if a in env.agents and env.snapshot.row_of(a) >= 0:
                    costs.append((info["reward_terms"]["headway"], env.snapshot, a))
    finally:
        env.close()
    assert all(c <= 0 for c, _, _ in costs) and any(c < 0 for c, _, _ in costs)
    for cost, snap, a in costs:
        row = snap.row_of(a)
        gap, speed = snap.leader_gaps()[row], snap.speed[row]
        expected = min(0.0, math.log(max(gap, 0.1) / (1.2 * speed))) if np.isfinite(gap) and speed > 0 else 0.0
        assert cost == pytest.approx(expected)
