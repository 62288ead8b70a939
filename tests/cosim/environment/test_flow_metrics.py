"""A demand run's window metrics against cases computed by hand, on real SUMO with hand-written traffic on the
dilemma net: what the detectors count (and that warm-up traffic is not counted), a ramp queue of known length,
the delay of a vehicle that never entered; and the level of service and the capacities (pure)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from cosim.config import SafetyConfig, load_config
from cosim.environment.episode import MergeZone
from cosim.environment.flow_metrics import level_of_service, window_metrics
from cosim.environment.flow_record import FlowRecorder
from cosim.sumo.demand import freeway_capacity, ramp_capacity, resolve_demand
from cosim.sumo.flow_outputs import flow_output_args, flow_sites, read_flow_outputs
from cosim.sumo.net import load_net
from cosim.sumo.outputs import SSM_FILE, Conflict
from cosim.sumo.resolve import resolve
from cosim.sumo.scenario import kind_of, routes_xml, vtype_xml
from cosim.sumo.session import SumoSession

WARMUP, HORIZON = 60.0, 180.0  # [s] a 2-minute window after a 1-minute warm-up


def run_by_hand(tmp_path: Path, vehicles: list[tuple[float, str]], ramp_lc: str = "",
                safety: SafetyConfig | None = None) -> dict:
    """Play the hand-written `vehicles` ((depart, XML) pairs) on the dilemma net with the demand run's detectors
    (and with `safety` SUMO's SSM device) and record; returns the window's metrics, SUMO's parsed outputs and what
    `window_metrics` needs besides them."""
    cfg = resolve(load_config("configs/demand.yaml", {"demand.warmup": WARMUP, "demand.window": HORIZON - WARMUP}),
                  net := load_net(load_config("configs/default.yaml").net.file)).config
    types = vtype_xml("car", cfg.hv, 1.0, 0.0, 1.0)
    # A ramp driver that never changes lane: it queues behind whoever stops ahead of it.
    types += vtype_xml("ramp", cfg.merger, 1.0, 0.0, 1.0).replace('id="ramp"', 'id="ramp"' + ramp_lc)
    tmp_path.mkdir(parents=True, exist_ok=True)
    routes = tmp_path / "hand.rou.xml"
    routes.write_text("<routes>\n" + types + routes_xml(net.desc) + "\n".join(v for _, v in sorted(vehicles))
                      + "\n</routes>\n")
    sites = flow_sites(net, cfg.demand.influence_area)
    session = SumoSession(Path(cfg.net.file), 0.1, net.road.index_of, kind_of)
    record = FlowRecorder(MergeZone.from_net(net), net.chainage, (WARMUP, HORIZON))
    try:
        session.load(routes, 1, flow_output_args(tmp_path / "out", sites, WARMUP, HORIZON, 30.0, safety))
        while session.snapshot().time < HORIZON - 0.05:
            session.advance(10, {}, 3.0, 5.0, 33.0)
            record.observe(session.snapshot(), session.pending())
        end = session.snapshot().time  # a step past the horizon: SUMO's first step came with the load
    finally:
        session.close()
    out = read_flow_outputs(tmp_path / "out", WARMUP, HORIZON, end, ssm=safety is not None)
    rest = {"rec": record.arrays(), "demand": resolve_demand(cfg, net), "sites": sites, "lanes_after": 2,
            "vehicle_gap": 7.5, "interval": 30.0, "safety": safety}
    return {"row": window_metrics(out, **rest), "out": out, "end": end, "rest": rest}


def _car(vid: str, t: float, route: str = "hw_0", lane: int = 0, vtype: str = "car", extra: str = "") -> tuple:
    return t, (f'<vehicle id="{vid}" type="{vtype}" route="{route}" depart="{t:g}" departLane="{lane}" '
               f'departSpeed="max"{">" + extra + "</vehicle>" if extra else "/>"}')


def test_the_detectors_count_the_window_only_and_by_origin(tmp_path: Path) -> None:
    cars = [_car(f"hv_w{k}", 2.0 * k) for k in range(3)]  # leave the merge area during the warm-up: not counted
    cars += [_car(f"hv_m{k}", 70.0 + 2 * k, lane=1) for k in range(4)]  # mainline, in the window
    cars += [_car(f"merger_{k}", 62.0 + 3 * k, route="ramp_0") for k in range(2)]  # ramp, in the window
    got = run_by_hand(tmp_path, cars)
    row, out = got["row"], got["out"]
    assert sorted(v for _, v in out.passages) == ["hv_m0", "hv_m1", "hv_m2", "hv_m3", "merger_0", "merger_1"]
    hours = (HORIZON - WARMUP) / 3600
    assert row["throughput_total_vph"] == pytest.approx(6 / hours)
    assert row["throughput_ramp_vph"] == pytest.approx(2 / hours)
    assert row["throughput_mainline_vph"] == pytest.approx(4 / hours)
    # 6 vehicles wanted to enter in the window (the warm-up's 3 do not count), none waited, both ramp ones merged.
    assert row["vehicles"] == 6 and row["merging_vehicles"] == 2 and row["merge_rate_pct"] == 100.0
    assert row["ramp_queue_max_veh"] == 0 and row["collisions_window"] == 0
    # Each drove the whole of its route (the trip is unfinished only if still on it at the end).
    assert row["distance_mean_m"] > 1000


def test_the_window_counts_the_ssm_devices_conflicts_in_it_by_party(tmp_path: Path) -> None:
    cars = [_car(f"hv_m{k}", 62.0 + 2 * k, lane=1) for k in range(3)] + [_car("merger_0", 64.0, route="ramp_0")]
    got = run_by_hand(tmp_path, cars, safety=SafetyConfig())
    assert (tmp_path / "out" / SSM_FILE).is_file() and got["out"].conflicts is not None  # SUMO's device rode
    assert {"conflicts_window", "conflicts_av_window", "conflicts_merger_window"} <= set(got["row"])

    def conflict(ego: str, foe: str, t: float) -> Conflict:  # a TTC of 0.5 s at `t`
        return Conflict(ego, foe, t - 1, t + 1, 0.5, t, math.nan, math.nan, math.nan, math.nan)

    # During the warm-up, in the window (an AV with a ramp vehicle, two HVs), after the horizon.
    hand = [conflict("av_1", "hv_0", 30.0), conflict("av_2", "merger_4", 100.0), conflict("hv_1", "hv_2", 150.0),
            conflict("merger_5", "hv_3", 200.0)]
    row = window_metrics(dataclasses.replace(got["out"], conflicts=hand), **got["rest"])
    assert (row["conflicts_window"], row["conflicts_av_window"], row["conflicts_merger_window"]) == (2, 1, 1)
    # Without the device (training's runs), no conflict columns rather than zeros.
    assert "conflicts_window" not in window_metrics(got["out"], **{**got["rest"], "safety": None})


def test_a_ramp_queue_of_known_length_and_the_delay_of_a_vehicle_that_never_entered(tmp_path: Path) -> None:
    # The first ramp vehicle stops at the end of the acceleration lane for good; 4 behind it that never change
    # lane stop behind it: a queue of 5 vehicles, 5 x 5 m + 4 gaps x 2.5 m = 35 m. More arrive every 2 s until
    # the ramp is full; the last, due at 149 s, never enters: its delay is the 31 s it waited.
    never_lc = ' lcStrategic="-1" lcSpeedGain="0" lcKeepRight="0" lcCooperative="0"'
    stop = '<stop lane="hw_merge_0" endPos="115" duration="10000"/>'
    cars = [_car("merger_0", 61.0, route="ramp_0", vtype="ramp", extra=stop)]
    cars += [_car(f"merger_{k}", 61.0 + 2 * k, route="ramp_0", vtype="ramp") for k in range(1, 5)]
    five = run_by_hand(tmp_path / "five", cars, ramp_lc=never_lc)["row"]
    assert five["ramp_queue_max_veh"] == 5 and five["ramp_queue_max_m"] == pytest.approx(35.0, abs=0.5)
    assert five["ramp_backlog_mean_veh"] == 0 and five["merge_rate_pct"] == 0.0
    # Once formed (within the first interval), the queue holds: the window's mean is close to 5.
    assert 4.0 < five["ramp_queue_mean_veh"] <= 5.0

    late = [*cars, *(_car(f"merger_{k}", 61.0 + 2 * k, route="ramp_0", vtype="ramp") for k in range(5, 45))]
    full = run_by_hand(tmp_path / "full", late, ramp_lc=never_lc)
    trips = {t.vid: t for t in full["out"].trips}
    last = trips["merger_44"]  # due at 61 + 88 = 149 s
    assert not last.departed and last.intended == pytest.approx(149.0)
    assert last.depart_delay == pytest.approx(full["end"] - 149.0)  # it waited from when it was due to the end
    row = full["row"]
    on_lanes = round(238.16 / 7.5)  # the ramp and the acceleration lane hold about 32 vehicles
    assert row["ramp_queue_max_veh"] >= on_lanes - 2 + row["ramp_backlog_mean_veh"]
    waiting = [t for t in full["out"].trips if not t.departed]
    assert len(waiting) >= 45 - on_lanes - 2 and row["ramp_backlog_mean_veh"] > 0
    # The window's delay counts every vehicle that wanted to enter in it, those still waiting included.
    due = [t for t in full["out"].trips if WARMUP <= t.intended < HORIZON]
    assert row["vehicles"] == len(due) == 45
    assert row["delay_total_vehh"] == pytest.approx(sum(t.depart_delay + t.time_loss for t in due) / 3600)
    assert row["delay_total_vehh"] * 3600 >= sum(t.depart_delay for t in waiting) > 0


def test_level_of_service_and_capacities() -> None:
    # HCM ramp-junction bounds [pc/mi/ln] 10 / 20 / 28 / 35, here per km: 6.2 / 12.4 / 17.4 / 21.7.
    assert [level_of_service(d, False) for d in (5.0, 10.0, 15.0, 20.0, 25.0)] == ["A", "B", "C", "D", "E"]
    assert level_of_service(5.0, over_capacity=True) == "F"
    assert freeway_capacity(33.33) == 2400 and freeway_capacity(22.22) == pytest.approx(2200, abs=1)
    assert freeway_capacity(27.78) == pytest.approx(2321, abs=1)
    assert [ramp_capacity(v / 2.23694) for v in (15, 25, 35, 45, 55)] == [1800, 1900, 2000, 2100, 2200]
    assert level_of_service(float("nan"), False) == "-"  # no density measured
