"""SUMO's own outputs: file writing and parsing, and agreement with our snapshots on real SUMO."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import cosim
from cosim.config import SafetyConfig
from cosim.environment.control import Action
from cosim.environment.policies import POLICIES
from cosim.environment.tracker import EpisodeTracker
from cosim.errors import SimulationError
from cosim.sumo.net import load_net
from cosim.sumo.outputs import (
    DETECTOR_FILE,
    SSM_FILE,
    TRIPINFO_FILE,
    conflict_counts,
    detector_site,
    episode_folder,
    episode_output_args,
    read_detectors,
    read_episode_outputs,
    read_ssm,
    read_tripinfo,
)

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

TRIPS = """<tripinfos>
    <tripinfo id="a" duration="20.00" routeLength="500.00" timeLoss="2.00" vaporized=""/>
    <tripinfo id="b" arrival="8.00" duration="10.00" routeLength="100.50" timeLoss="4.00" vaporized="traci"/>
</tripinfos>
"""
LOOPS = """<detector>
    <interval begin="0.00" end="20.00" id="loop_0" nVehContrib="3" nVehEntered="4"/>
    <interval begin="0.00" end="20.00" id="loop_1" nVehContrib="2" nVehEntered="2"/>
</detector>
"""


# SSM output as SUMO 1.28 writes it (no trajectories): the pair av_0/hv_2 twice, ego and foe swapped, overlapping;
# merger/hv_5 once, its worst TTC after the episode's end (12 s below); hv_7/hv_8 with a DRAC conflict only; an
# encounter of av_1/hv_3 whose values all stay on the safe side of the thresholds.
SSM = """<SSMLog>
    <conflict begin="0.00" end="9.00" ego="av_0" foe="hv_2">
        <minTTC time="7.90" position="1,2" type="2" value="0.80" speed="20.00"/>
        <maxDRAC time="7.80" position="1,2" type="2" value="3.00" speed="20.00"/>
        <PET time="NA" position="NA" type="NA" value="NA" speed="NA"/>
    </conflict>
    <conflict begin="1.20" end="9.50" ego="hv_2" foe="av_0">
        <minTTC time="7.90" position="1,2" type="3" value="0.80" speed="20.00"/>
        <maxDRAC time="8.00" position="1,2" type="3" value="3.60" speed="20.00"/>
        <PET time="NA" position="NA" type="NA" value="NA" speed="NA"/>
    </conflict>
    <conflict begin="10.00" end="15.00" ego="merger" foe="hv_5">
        <minTTC time="13.00" position="1,2" type="2" value="1.00" speed="5.00"/>
        <maxDRAC time="11.00" position="1,2" type="2" value="1.00" speed="5.00"/>
        <PET time="11.50" position="1,2" type="4" value="1.20" speed="5.00"/>
    </conflict>
    <conflict begin="2.00" end="6.00" ego="hv_7" foe="hv_8">
        <minTTC time="NA" position="NA" type="NA" value="NA" speed="NA"/>
        <maxDRAC time="3.00" position="1,2" type="2" value="5.00" speed="9.00"/>
        <PET time="NA" position="NA" type="NA" value="NA" speed="NA"/>
    </conflict>
    <conflict begin="2.00" end="6.00" ego="av_1" foe="hv_3">
        <minTTC time="4.00" position="1,2" type="2" value="2.50" speed="9.00"/>
        <maxDRAC time="3.00" position="1,2" type="2" value="1.00" speed="9.00"/>
        <PET time="NA" position="NA" type="NA" value="NA" speed="NA"/>
    </conflict>
</SSMLog>
"""


def test_ssm_conflicts_are_counted_once_by_measure_and_by_party(tmp_path: Path) -> None:
    (tmp_path / SSM_FILE).write_text(SSM)
    conflicts = read_ssm(tmp_path / SSM_FILE)
    assert [sorted(c.vehicles()) for c in conflicts] == [["av_0", "hv_2"], ["av_1", "hv_3"], ["hv_7", "hv_8"],
                                                       ["hv_5", "merger"]]
    first = conflicts[0]  # both records of the pair, their span and each measure's worse value
    assert (first.begin, first.end, first.ttc, first.drac, first.drac_time) == (0.0, 9.5, 0.8, 3.6, 8.0)
    assert math.isnan(first.pet) and math.isnan(first.pet_time)
    safety = SafetyConfig()  # TTC < 1.5 s, DRAC > 3.4 m/s^2, PET < 2 s
    late = conflict_counts(conflicts, safety, until=20.0)
    assert late == {"conflicts": 3, "conflicts_ttc": 2, "conflicts_drac": 2, "conflicts_pet": 1, "conflicts_av": 1,
                    "conflicts_merger": 1, "min_ttc": 0.8, "max_drac": 5.0, "min_pet": 1.2}
    # Up to 12 s the merging vehicle's worst TTC (13 s) is not in, its PET (11.5 s) is.
    early = conflict_counts(conflicts, safety, until=12.0)
    assert [early[k] for k in ("conflicts", "conflicts_ttc", "conflicts_pet", "conflicts_merger")] == [3, 1, 1, 1]
    # Before any worst value: nothing; stricter thresholds: fewer.
    none = conflict_counts(conflicts, safety, until=2.0)
    assert none["conflicts"] == 0 and math.isnan(none["min_ttc"]) and math.isnan(none["max_drac"])
    strict = conflict_counts(conflicts, SafetyConfig(ttc=0.9, drac=4.0, pet=1.0), until=20.0)
    assert (strict["conflicts"], strict["conflicts_ttc"], strict["conflicts_drac"]) == (2, 1, 1)
    # A demand run's window from 7.85 s: av_0/hv_2's DRAC (8 s) and the merging vehicle's PET and TTC are in,
    # av_0/hv_2's TTC (7.9 s) too; hv_7/hv_8's DRAC (3 s) is before it.
    window = conflict_counts(conflicts, safety, until=20.0, since=7.85)
    assert [window[k] for k in ("conflicts", "conflicts_ttc", "conflicts_drac", "conflicts_pet")] == [2, 2, 1, 1]
    assert window["max_drac"] == 3.6


def test_the_ssm_device_is_asked_for_only_where_the_safety_section_wants_it(tmp_path: Path) -> None:
    site = detector_site(load_net("sumo_net/dilemma/dilemma.net.xml"), 100.0)
    args = episode_output_args(tmp_path, site, safety=SafetyConfig(ttc=1.0, drac=3.0, pet=2.5))
    assert args[args.index("--device.ssm.thresholds") + 1] == "1 3 2.5"
    assert args[args.index("--device.ssm.measures") + 1] == "TTC DRAC PET"
    assert args[args.index("--device.ssm.file") + 1] == str(tmp_path / SSM_FILE)
    for off in (None, SafetyConfig(ssm=False)):
        assert not any(a.startswith("--device.ssm") for a in episode_output_args(tmp_path, site, safety=off))


def test_a_missing_or_truncated_ssm_file_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / TRIPINFO_FILE).write_text(TRIPS)
    (tmp_path / DETECTOR_FILE).write_text(LOOPS)
    assert read_episode_outputs(tmp_path, 20.0).safety == {}  # without a safety section: not read
    with pytest.raises(SimulationError, match=rf"{tmp_path / SSM_FILE}: not found"):
        read_episode_outputs(tmp_path, 20.0, SafetyConfig())
    (tmp_path / SSM_FILE).write_text(SSM[:300])
    with pytest.raises(SimulationError, match=rf"{tmp_path / SSM_FILE}: incomplete"):
        read_episode_outputs(tmp_path, 20.0, SafetyConfig())
    assert read_episode_outputs(tmp_path, 20.0, SafetyConfig(ssm=False)).safety == {}


def test_sumo_logs_the_conflict_of_a_crash_with_its_parties(tmp_path: Path) -> None:
    """Idle AVs run into the slower stream on this seed: SUMO's SSM device has the crash's pair, at TTC 0, as one
    conflict with an AV, counted up to the episode's end; episodes.csv's columns come from the outputs' row."""
    env = cosim.parallel_env("configs/default.yaml", {"sim.outputs": True, "sim.output_dir": str(tmp_path)})
    try:
        env.reset(seed=10_000_000)
        while env.agents:
            env.step(dict.fromkeys(env.agents, int(Action.IDLE)))
        collision = env.tracker.collisions[0]
        end = env.tracker.time
        env.flush_outputs()
    finally:
        env.close()
    out = env.sumo_outputs[10_000_000]
    crash = [c for c in read_ssm(tmp_path / "episode_10000000" / SSM_FILE)
             if sorted(c.vehicles()) == sorted((collision.collider, collision.victim))]
    assert len(crash) == 1 and crash[0].ttc == 0.0 and crash[0].ttc_time == pytest.approx(collision.time, abs=0.11)
    assert out.safety["conflicts_av"] >= 1 and out.safety["min_ttc"] == 0.0 and end < 20.0
    assert out.as_row()["conflicts"] == out.safety["conflicts"]


def crossings(trajectory: dict[str, np.ndarray], s: float) -> int:
    """Vehicles whose front crosses chainage `s` (from below) between two recorded steps: what a loop counts."""
    count = 0
    vehicle, chain, step = trajectory["vehicle"], trajectory["s"], trajectory["step"]
    for v in np.unique(vehicle):
        mine = vehicle == v
        path = chain[mine][np.argsort(step[mine], kind="stable")]
        path = path[np.isfinite(path)]
        count += int(np.any((path[:-1] < s) & (path[1:] >= s)))
    return count


def test_crossings_counts_front_passes() -> None:
    traj = {"vehicle": np.array([0, 1, 0, 1, 0, 1, 2]), "step": np.array([0, 0, 1, 1, 2, 2, 2]),
            "s": np.array([90.0, 50.0, np.nan, 99.0, 120.0, 100.0, 150.0])}
    # vehicle 0 crosses through a gap (NaN), vehicle 1 reaches exactly 100, vehicle 2 appears past it
    assert crossings(traj, 100.0) == 2
    assert crossings(traj, 10.0) == 0


def test_parse_hand_written_outputs(tmp_path: Path) -> None:
    (tmp_path / TRIPINFO_FILE).write_text(TRIPS)
    (tmp_path / DETECTOR_FILE).write_text(LOOPS)
    assert read_detectors(tmp_path / DETECTOR_FILE) == 6
    assert [t["id"] for t in read_tripinfo(tmp_path / TRIPINFO_FILE, 20.0)] == ["a", "b"]
    out = read_episode_outputs(tmp_path, duration=20.0)
    assert out.detector_count == 6 and out.throughput_vph == pytest.approx(6 * 3600 / 20)
    # b was taken off the road (a removed wreck) at 8 s: it stood for the window's last 12 s.
    assert out.time_loss == (2.0 + 16.0) / 2 and out.n_trips == 2
    assert out.mean_speed == pytest.approx((500.0 / 20.0 + 100.5 / 22.0) / 2)
    assert out.distance == {"a": 500.0, "b": 100.5}


def test_incomplete_or_missing_outputs_are_clear_errors(tmp_path: Path) -> None:
    (tmp_path / TRIPINFO_FILE).write_text(TRIPS[:80])
    (tmp_path / DETECTOR_FILE).write_text(LOOPS)
    with pytest.raises(SimulationError, match="incomplete"):
        read_episode_outputs(tmp_path, 20.0)
    with pytest.raises(SimulationError, match="not found"):
        read_detectors(tmp_path / "nope.xml")


def test_episode_folder_is_never_the_previous_episodes(tmp_path: Path) -> None:
    assert episode_folder(tmp_path, 3) == tmp_path / "episode_3"
    assert episode_folder(tmp_path, 3, busy=tmp_path / "episode_2") == tmp_path / "episode_3"
    assert episode_folder(tmp_path, 3, busy=tmp_path / "episode_3") == tmp_path / "episode_3_1"
    assert episode_folder(tmp_path, 3, busy=tmp_path / "episode_3_1") == tmp_path / "episode_3"


def test_resets_with_the_same_seed_keep_both_episodes_outputs(tmp_path: Path) -> None:
    env = cosim.parallel_env("configs/default.yaml", {"sim.outputs": True, "sim.output_dir": str(tmp_path),
                                                     "sim.horizon": 5.0})
    n_trips = []
    try:
        for k in range(3):
            env.reset(seed=3)
            if k:  # the reload completed the previous episode's files; they must not be truncated first
                n_trips.append(env.sumo_outputs.pop(3).n_trips)
            while env.agents:
                env.step(dict.fromkeys(env.agents, 1))
        env.flush_outputs()
        n_trips.append(env.sumo_outputs.pop(3).n_trips)
    finally:
        env.close()
    assert len(n_trips) == 3 and len(set(n_trips)) == 1 and n_trips[0] > 0  # one seed: the same, whole episode
    assert (tmp_path / "episode_3" / TRIPINFO_FILE).is_file() and (tmp_path / "episode_3_1" / TRIPINFO_FILE).is_file()


def test_detectors_cover_every_lane_of_the_last_highway_edge(two_lane_net: Path, tmp_path: Path) -> None:
    net = load_net(two_lane_net)
    road, desc = net.road, net.desc
    site = detector_site(net, offset=1e6)  # clipped into the edge
    last = desc.highway[-1]
    assert site.edge == last and len(site.lanes) == road.num_lanes(last)
    assert site.pos < road.edge_length(last)
    args = episode_output_args(tmp_path / "ep", site)
    text = (tmp_path / "ep" / "detectors.add.xml").read_text()
    assert all(f'lane="{lane}"' in text for lane in site.lanes) and "--tripinfo-output" in args


@pytest.mark.parametrize("net", ["default", "two_lane"])
def test_sumo_throughput_agrees_with_our_snapshots(net: str, two_lane_net: Path, tmp_path: Path) -> None:
    overrides = {"sim.outputs": True, "sim.output_dir": str(tmp_path), "sim.horizon": 15.0}
    if net == "two_lane":
        overrides.update({"net.file": str(two_lane_net), "scenario.n_hvs": 6, "sim.detector_offset": 40.0})
    env = cosim.parallel_env("configs/default.yaml", overrides)
    try:
        chain = env.net.chainage
        policy = POLICIES["scripted"](0)
        tracks = {}
        for seed in (3, 4, 5):
            env.reset(seed=seed)
            if seed - 1 in tracks:  # the reload completed the previous episode's files
                assert seed - 1 in env.sumo_outputs
            tr = EpisodeTracker(env.zone, chain, record=True)
            tr.observe(env.snapshot)
            while env.agents:
                actions = policy(env)
                env.step(actions)
                tr.observe(env.snapshot, actions)
            tracks[seed] = tr
        assert 5 not in env.sumo_outputs  # still open until close
    finally:
        env.close()
    for seed, tr in tracks.items():
        out = env.sumo_outputs[seed]
        assert (tmp_path / f"episode_{seed}" / TRIPINFO_FILE).is_file()
        loops = env.net.highway_offsets[env.detectors.edge] + env.detectors.pos  # on the highway axis
        assert out.detector_count == crossings(tr.trajectory(), loops) > 0
        assert out.throughput_vph == pytest.approx(out.detector_count * 3600 / tr.time)
        assert out.n_trips == len(tr.distance)
        for vid, d in tr.distance.items():  # our odometer and SUMO's routeLength (2 decimals in the file)
            assert out.distance[vid] == pytest.approx(d, abs=0.01)


def test_sumo_drives_the_avs_when_asked(tmp_path: Path) -> None:
    env = cosim.parallel_env("configs/default.yaml", {"sim.av_driver": "sumo", "sim.outputs": True,
                                                     "sim.horizon": 10.0})
    try:
        for seed in (0, 1):
            env.reset(seed=seed)
            infos: dict = {}
            while env.agents:
                # Hard braking orders would stop env-driven AVs; SUMO ignores them.
                _, _, _, _, infos = env.step(dict.fromkeys(env.agents, 4))
            assert not next(iter(infos.values()))["episode"]["crashed"]
            snap = env.snapshot
            assert snap.speed[snap.rows_of(env.possible_agents)].min() > 10.0
            env.flush_outputs()
            assert env.sumo_outputs[seed].n_trips == len(env.tracker.distance)  # every vehicle of the episode
    finally:
        env.close()
