"""Net-relative keys resolved on a net: the default config means today's dilemma on its net and the same
dilemma, scaled, on another; twins are one quantity; what a net cannot take is capped with a note naming the
key (no SUMO run here: cosim/sumo/test_nets.py runs the resolved scenarios)."""

from pathlib import Path

import pytest

from cosim.config import load_config
from cosim.errors import ConfigError
from cosim.sumo.net import load_net
from cosim.sumo.resolve import resolve
from sumo_net.build import build_merge_net

ROOT = Path(__file__).resolve().parents[3]
DEFAULT = ROOT / "configs" / "default.yaml"


@pytest.fixture(scope="module")
def dilemma():
    cfg = load_config(DEFAULT)
    return cfg, load_net(cfg.net.file)


def test_the_default_config_on_its_own_net_is_the_dilemma_in_metres_and_metres_per_second(dilemma) -> None:
    cfg, net = dilemma
    r = resolve(cfg, net)
    assert r.notes == ()  # the default config fits its own net
    c = r.config
    assert net.speed_limit == pytest.approx(33.33) and net.ramp_speed_limit == pytest.approx(22.22)
    sc = c.scenario
    assert sc.stream_speed == pytest.approx((0.69 * 33.33, 0.81 * 33.33))  # 23-27 m/s
    assert sc.merger_speed == pytest.approx((0.8 * 22.22, 22.22))
    assert sc.stream_head == pytest.approx((0.0, 0.67 * net.accel_length))
    assert sc.av_speed_offset == pytest.approx((-0.03 * 33.33, 0.09 * 33.33))
    assert (sc.place_from, sc.place_to) == pytest.approx((0.0, net.chainage.merge_end))
    assert sc.n_hvs == 10 and sc.hv_density is None  # 16 veh/km on the left lane's 620 m
    assert c.av.max_speed == pytest.approx(33.33) and c.av.speed_step == pytest.approx(2.5, abs=0.01)
    assert c.hv.max_speed == pytest.approx(33.33) and c.merger.max_speed == pytest.approx(0.9 * 33.33)
    assert c.observation.speed_scale == pytest.approx(15.0, abs=0.01)
    # Nothing relative is left for downstream code; resolving again changes nothing.
    assert c.scenario.stream_speed_factor is None and c.av.max_speed_factor is None
    assert resolve(c, net) == r


def test_speeds_follow_the_limits_of_another_net(tmp_path: Path) -> None:
    # 130 km/h highway, 50 km/h ramp: the drivers may go 130 km/h, everything scales with the limits.
    net = load_net(build_merge_net(tmp_path, lanes=2, upstream_length=400, highway_speed=36.11, ramp_speed=13.89))
    c = resolve(load_config(DEFAULT, {"net.file": str(net.road.net_file)}), net).config
    assert c.scenario.stream_speed == pytest.approx((0.69 * 36.11, 0.81 * 36.11))
    assert c.scenario.merger_speed == pytest.approx((0.8 * 13.89, 13.89))
    assert c.av.max_speed == pytest.approx(36.11) and c.hv.max_speed == pytest.approx(36.11)
    assert c.observation.speed_scale == pytest.approx(0.45 * 36.11)


def test_a_relative_key_and_its_absolute_twin_are_one_quantity(dilemma) -> None:
    cfg, _ = dilemma
    # Both in one layer: an error naming both.
    with pytest.raises(ConfigError, match=r"scenario.stream_speed: set together with stream_speed_factor"):
        load_config({"scenario": {"stream_speed": [20, 24], "stream_speed_factor": [0.6, 0.7]}})
    with pytest.raises(ConfigError, match=r"--set scenario.merger_pos=\[0, 10\]: set together with merger_time"):
        load_config(DEFAULT, ["scenario.merger_time=[2, 3]", "scenario.merger_pos=[0, 10]"])
    # A later layer replaces the earlier one's twin: an override over the file, a file over its base.
    c = load_config(DEFAULT, ["scenario.stream_speed=[20, 24]", "scenario.n_hvs=4", "av.max_speed=30"])
    assert c.scenario.stream_speed == (20, 24) and c.scenario.stream_speed_factor is None
    assert c.scenario.n_hvs == 4 and c.scenario.hv_density is None and c.av.max_speed_factor is None
    ff = load_config(ROOT / "configs" / "free_flow.yaml")  # base: default.yaml, its merging vehicle by distance
    assert ff.scenario.merger_distance == (115.0, 115.0) and ff.scenario.merger_time is None
    # Setting the relative one to null falls back on the built-in default where no twin is given.
    assert load_config(DEFAULT, ["scenario.stream_speed_factor=null"]).scenario.stream_speed_factor == (0.69, 0.81)
    # The saved form of a config (a run's config.yaml) loads back the same.
    assert load_config(c.to_dict()).to_dict() == c.to_dict()


def test_absolute_values_the_net_cannot_take_are_capped_with_a_note_naming_the_key(tmp_path: Path) -> None:
    # A 60 km/h ramp and a 1-lane highway: yesterday's absolute scenario.
    net = load_net(build_merge_net(tmp_path, lanes=1, upstream_length=300, ramp_speed=16.67))
    cfg = load_config(DEFAULT, {"net.file": str(net.road.net_file), "scenario.merger_speed": [18.0, 22.0],
                                "scenario.merger_pos": [0.0, 200.0], "scenario.n_hvs": 10,
                                "scenario.stream_speed": [23.0, 40.0]})
    r = resolve(cfg, net)
    notes = dict(n.split(": ", 1) for n in r.notes)
    assert set(notes) == {"scenario.merger_speed", "scenario.merger_pos", "scenario.n_hvs", "scenario.stream_speed"}
    assert r.config.scenario.merger_speed == pytest.approx((16.67, 16.67))
    assert r.config.scenario.merger_pos[1] < net.road.edge_length("ramp")
    assert r.config.scenario.n_hvs == 0 and "0 fit for sure on its 0 lane(s)" in notes["scenario.n_hvs"]
    # The relative default asks for no HV where there is no lane beside the stream: no note.
    assert not resolve(load_config(DEFAULT, {"net.file": str(net.road.net_file)}), net).notes
