"""Meta-action decisions and action masks (pure) and the seeded episode plan (pure, on the real default net)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.config import AVConfig, load_config
from cosim.environment.control import Action, action_mask, decide
from cosim.errors import ConfigError
from cosim.sumo.net import load_net
from cosim.sumo.resolve import resolve
from cosim.sumo.scenario import MERGER_ID, idm_gap, plan_episode, write_episode
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[3]
AV = AVConfig(speed_step=2.0, max_speed=30.0)


def test_decide_speed_and_lanes() -> None:
    through = np.tile([False, True, True, True], (5, 1))  # lane 0 is an acceleration lane
    d = decide(np.array([Action.LANE_LEFT, Action.IDLE, Action.LANE_RIGHT, Action.ACCELERATE, Action.DECELERATE]),
               lanes=np.array([3, 2, 1, 2, 2]), usable=through, speed_targets=np.array([20, 20, 20, 29.5, 1.0]),
               av=AV)
    assert d.target_speed.tolist() == [20, 20, 20, 30.0, 0.0]  # clipped to [0, max_speed]
    # Left from the leftmost lane and right into the acceleration lane (index 0) are no-ops.
    assert d.lane_change.tolist() == [0, 0, 0, 0, 0]
    assert d.invalid.tolist() == [True, False, True, False, False]
    d = decide(np.array([Action.LANE_LEFT, Action.LANE_RIGHT]), lanes=np.array([1, 3]),
               usable=np.tile([False, True, True, True], (2, 1)), speed_targets=np.zeros(2), av=AV)
    assert d.lane_change.tolist() == [1, -1] and not d.invalid.any()
    d = decide(np.array([Action.LANE_LEFT]), np.array([0]), np.zeros((1, 4), dtype=bool), np.zeros(1), AV)
    assert d.invalid.tolist() == [True]  # no lane change on a junction-internal edge
    with pytest.raises(ValueError, match="actions must be in 0..4"):
        decide(np.array([7]), np.array([0]), np.ones((1, 4), dtype=bool), np.zeros(1), AV)


def test_action_mask_allows_exactly_the_actions_decide_would_carry_out() -> None:
    """For random lanes, usable lanes and target speeds (the bounds included): an action is allowed iff `decide`
    changes the lane or the target speed with it; idle is always allowed."""
    rng = np.random.default_rng(0)
    n = 400
    lanes = rng.integers(0, 4, n)
    usable = rng.random((n, 4)) < 0.6
    targets = rng.choice([0.0, 1.0, 15.0, 29.5, AV.max_speed], n)
    mask = action_mask(lanes, usable, targets, AV)
    assert mask.shape == (n, 5) and mask.dtype == np.int8 and mask[:, Action.IDLE].all()
    for a in Action:
        if a == Action.IDLE:
            continue
        d = decide(np.full(n, a), lanes, usable, targets, AV)
        acts = (d.lane_change != 0) | (d.target_speed != targets)
        assert (mask[:, a] == acts).all(), a
    for a in (Action.LANE_LEFT, Action.LANE_RIGHT, Action.ACCELERATE, Action.DECELERATE):
        assert 0 < mask[:, a].sum() < n  # each is masked somewhere and allowed elsewhere


@pytest.fixture(scope="module")
def free_flow():
    cfg = load_config(ROOT / "configs" / "free_flow.yaml")
    net = load_net(cfg.net.file)
    return resolve(cfg, net).config, net, net.desc


@pytest.fixture(scope="module")
def dilemma():
    cfg = load_config(ROOT / "configs" / "default.yaml")
    net = load_net(cfg.net.file)
    return resolve(cfg, net).config, net, net.desc


def _chainage(net, sp) -> float:
    return net.highway_offsets[net.desc.highway[int(sp.route[3:])]] + sp.pos


def test_window_plan_is_seeded_interleaved_and_complete(free_flow) -> None:
    cfg, net, desc = free_flow
    a, b, c = (plan_episode(cfg, net, s) for s in (5, 5, 6))
    assert a == b and a != c
    kinds = [sp.kind for sp in a.vehicles]
    assert kinds.count(KIND_AV) == cfg.scenario.n_avs and kinds.count(KIND_HV) == cfg.scenario.n_hvs
    assert kinds.count(KIND_MERGER) == 1 and any(sp.vid == MERGER_ID and sp.route == "ramp_0" for sp in a.vehicles)
    assert a.flows == []
    hw = [sp for sp in a.vehicles if sp.kind != KIND_MERGER]
    s = np.array([_chainage(net, sp) for sp in hw])
    assert s.min() >= cfg.scenario.place_from and s.max() <= cfg.scenario.place_to + 1e-6
    limit = net.road.lane("hw_in", 0).speed  # every lane's on this net
    lo, hi = (f * limit for f in cfg.scenario.speed_range_factor)  # of each vehicle's lane's limit
    assert all(lo - 1e-9 <= sp.speed <= hi + 1e-9 for sp in hw)
    # No HV starts faster than it wants to drive (SUMO would refuse the departure).
    assert all(sp.speed <= sp.speed_factor * net.road.lane("hw_in", 0).speed + 1e-9 for sp in hw if sp.kind == KIND_HV)
    # AVs are not all at the front or all at the back: HVs between them.
    order = [sp.kind for sp in sorted(hw, key=lambda sp: s[hw.index(sp)])]
    first, last = order.index(KIND_AV), len(order) - 1 - order[::-1].index(KIND_AV)
    assert KIND_HV in order[first:last]
    # Same lane: front-to-front spacing at least min_gap.
    for lane_s in {}.fromkeys((sp.route, sp.lane) for sp in hw):
        pos = sorted(s[i] for i, sp in enumerate(hw) if (sp.route, sp.lane) == lane_s)
        assert all(b - a >= cfg.scenario.min_gap - 1e-6 for a, b in zip(pos, pos[1:], strict=False))


def test_stream_plan_is_a_dense_stream_with_a_guide_av(dilemma) -> None:
    cfg, net, desc = dilemma
    sc, hv = cfg.scenario, cfg.hv
    rank = net.target_rank()
    assert rank == 0  # the right lane: beside the acceleration lane
    merge_start = net.highway_offsets[desc.merge_edge]
    a, b = plan_episode(cfg, net, 3), plan_episode(cfg, net, 3)
    assert a == b and a != plan_episode(cfg, net, 4)
    in_time = 0
    for seed in range(20):
        plan = plan_episode(cfg, net, seed)
        vehicles = [sp for sp in plan.vehicles if sp.kind != KIND_MERGER]
        lane_rank = {sp.vid: net.through_lanes(desc.highway[int(sp.route[3:])]).index(sp.lane)
                     for sp in vehicles}
        stream = sorted((sp for sp in vehicles if lane_rank[sp.vid] == rank),
                        key=lambda sp: -_chainage(net, sp))
        others = [sp for sp in vehicles if lane_rank[sp.vid] != rank]
        assert sum(sp.kind == KIND_AV for sp in stream) == sc.n_avs and len(others) == sc.n_hvs
        assert all(sp.kind == KIND_HV for sp in others)
        head = stream[0]
        speed = head.speed
        assert head.kind == KIND_HV and head.max_speed == pytest.approx(speed)  # it drives at the stream's speed
        assert sc.stream_speed[0] <= speed <= sc.stream_speed[1]
        assert merge_start + sc.stream_head[0] <= _chainage(net, head) <= merge_start + sc.stream_head[1]
        # Each HV behind its leader at its IDM equilibrium gap at the stream's speed, times the spacing factor.
        for lead, follower in zip(stream, stream[1:], strict=False):
            gap = _chainage(net, lead) - hv.length - _chainage(net, follower)
            if follower.kind == KIND_HV:
                assert follower.speed == pytest.approx(speed)
                eq = idm_gap(speed, min(follower.speed_factor * net.road.lane(desc.merge_edge, 1).speed, hv.max_speed),
                             follower.tau, hv.min_gap)
                assert sc.stream_spacing[0] * eq - 1e-6 <= gap <= sc.stream_spacing[1] * eq + 1e-6
                assert hv.tau_range[0] <= follower.tau <= hv.tau_range[1]
            else:
                assert speed + sc.av_speed_offset[0] - 1e-9 <= follower.speed <= speed + sc.av_speed_offset[1] + 1e-9
        assert _chainage(net, stream[-1]) - hv.length >= sc.place_from
        merger = next(sp for sp in plan.vehicles if sp.kind == KIND_MERGER)
        assert merger.route == "ramp_0" and sc.merger_speed[0] <= merger.speed <= sc.merger_speed[1]
        # It starts merger_time before the acceleration lane (junction included), at its initial speed.
        merger_time = (merge_start - net.ramp_offsets[desc.ramp[0]] - merger.pos) / merger.speed
        assert sc.merger_time[0] - 1e-6 <= merger_time <= sc.merger_time[1] + 1e-6
        lags = [(merge_start - _chainage(net, sp)) / speed - merger_time for sp in stream if sp.kind == KIND_AV]
        in_time += any(sc.guide_window[0] <= lag <= sc.guide_window[1] for lag in lags)
        # On this long highway the placed stream outlasts the horizon: no flow needed behind it.
        assert plan.flows == []
    assert in_time == 20  # a guide AV meets the merging vehicle in every episode


def test_stream_on_a_short_highway_moves_down_and_goes_on(two_lane_net: Path) -> None:
    net = load_net(two_lane_net)
    cfg = resolve(load_config(ROOT / "configs" / "default.yaml", {"net.file": str(two_lane_net), "scenario.n_hvs": 4}),
                  net).config
    for seed in range(10):
        plan = plan_episode(cfg, net, seed)
        assert sum(sp.kind == KIND_AV for sp in plan.vehicles) == cfg.scenario.n_avs
        (flow,) = plan.flows  # the stream goes on, entering at the highway's start in the stream's lane
        assert flow.route == "hw_0" and flow.lane == net.through_lanes(net.desc.highway[0])[0]
        assert flow.period > 0
    with pytest.raises(ConfigError, match="do not fit in the stream"):
        plan_episode(load_config(cfg, {"scenario.n_avs": 40}), net, 0)


def test_episode_file_holds_vehicles_and_flows(free_flow, tmp_path: Path) -> None:
    cfg, net, desc = free_flow
    cfg = load_config(cfg, {"scenario.inflow": 900.0})
    path = tmp_path / "ep.rou.xml"
    write_episode(plan_episode(cfg, net, 0), cfg, net.desc, path)
    text = path.read_text()
    assert text.count("<vehicle ") == cfg.scenario.n_avs + cfg.scenario.n_hvs + 1
    assert 'carFollowModel="IDM"' in text and 'laneChangeModel="LC2013"' in text and 'speedDev="0"' in text
    assert '<flow id="inflow"' in text and 'probability="0.250000"' in text


def test_too_many_hvs_are_capped_and_too_many_avs_are_a_clear_error(free_flow) -> None:
    cfg, net, desc = free_flow
    many = resolve(load_config(cfg, {"scenario.n_hvs": 200}), net)
    (note,) = many.notes
    assert note.startswith("scenario.n_hvs: 200 HVs do not fit") and f"placing {many.config.scenario.n_hvs}" in note
    plan = plan_episode(many.config, net, 0)
    assert sum(sp.kind == KIND_HV for sp in plan.vehicles) == many.config.scenario.n_hvs > 0
    with pytest.raises(ConfigError, match="do not fit"):  # the agents are not capped: their number is the env's
        plan_episode(load_config(cfg, {"scenario.n_avs": 200}), net, 0)


def test_placement_window_off_the_highway_is_capped_with_a_note(free_flow) -> None:
    cfg, net, desc = free_flow
    capped = resolve(load_config(cfg, {"scenario.place_from": 0.0, "scenario.place_to": 5000.0}), net)
    assert capped.config.scenario.place_to == pytest.approx(net.highway_length)
    assert any(n.startswith("scenario.place_from / place_to: [0, 5000] m reaches off the highway")
               for n in capped.notes)
