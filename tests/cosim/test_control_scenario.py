"""Meta-action decisions (pure) and the seeded episode plan (pure, on the real default net)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.config import AVConfig, load_config
from cosim.control import Action, decide
from cosim.errors import ConfigError
from cosim.netdesc import load_net_description
from cosim.roadnet import load_roadnet
from cosim.scenario import MERGER_ID, plan_episode, write_episode
from cosim.snapshot import KIND_AV, KIND_HV, KIND_MERGER

ROOT = Path(__file__).resolve().parents[2]
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


@pytest.fixture(scope="module")
def net():
    road = load_roadnet(ROOT / "sumo_net" / "merge" / "merge.net.xml")
    return road, load_net_description(road)


def test_plan_is_seeded_interleaved_and_complete(net) -> None:
    road, desc = net
    cfg = load_config(ROOT / "configs" / "default.yaml")
    a, b, c = (plan_episode(cfg, desc, road, s) for s in (5, 5, 6))
    assert a == b and a != c
    kinds = [sp.kind for sp in a]
    assert kinds.count(KIND_AV) == cfg.scenario.n_avs and kinds.count(KIND_HV) == cfg.scenario.n_hvs
    assert kinds.count(KIND_MERGER) == 1 and any(sp.vid == MERGER_ID and sp.route == "ramp" for sp in a)
    offsets = desc.highway_offsets(road)
    hw = [sp for sp in a if sp.kind != KIND_MERGER]
    s = np.array([offsets[desc.highway[int(sp.route[3:])]] + sp.pos for sp in hw])
    assert s.min() >= cfg.scenario.place_from and s.max() <= cfg.scenario.place_to + 1e-6
    lo, hi = cfg.scenario.speed_range
    assert all(lo <= sp.speed <= hi for sp in hw)
    # AVs are not all at the front or all at the back: HVs between them.
    order = [sp.kind for sp in sorted(hw, key=lambda sp: s[hw.index(sp)])]
    first, last = order.index(KIND_AV), len(order) - 1 - order[::-1].index(KIND_AV)
    assert KIND_HV in order[first:last]
    # Same lane: front-to-front spacing at least min_gap.
    for lane_s in {}.fromkeys((sp.route, sp.lane) for sp in hw):
        pos = sorted(s[i] for i, sp in enumerate(hw) if (sp.route, sp.lane) == lane_s)
        assert all(b - a >= cfg.scenario.min_gap - 1e-6 for a, b in zip(pos, pos[1:], strict=False))


def test_episode_file_holds_vehicles_and_inflow(net, tmp_path: Path) -> None:
    road, desc = net
    cfg = load_config(ROOT / "configs" / "default.yaml", {"scenario.inflow": 900.0})
    path = tmp_path / "ep.rou.xml"
    write_episode(plan_episode(cfg, desc, road, 0), cfg, desc, path)
    text = path.read_text()
    assert text.count("<vehicle ") == cfg.scenario.n_avs + cfg.scenario.n_hvs + 1
    assert 'carFollowModel="IDM"' in text and 'laneChangeModel="LC2013"' in text
    assert '<flow id="inflow"' in text and 'probability="0.250000"' in text


def test_too_many_vehicles_is_a_clear_error(net) -> None:
    road, desc = net
    cfg = load_config(ROOT / "configs" / "default.yaml", {"scenario.n_hvs": 200})
    with pytest.raises(ConfigError, match="do not fit"):
        plan_episode(cfg, desc, road, 0)


def test_placement_window_off_the_highway_is_a_clear_error(net) -> None:
    road, desc = net
    cfg = load_config(ROOT / "configs" / "default.yaml", {"scenario.place_to": 5000.0})
    with pytest.raises(ConfigError, match="place_from / place_to"):
        plan_episode(cfg, desc, road, 0)
