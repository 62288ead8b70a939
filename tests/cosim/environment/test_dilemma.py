"""The default scenario on real SUMO is a merge dilemma: the AVs decide whether the merging vehicle gets in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test

import cosim
from cosim.environment.merge_env import MergeEnv
from cosim.environment.policies import POLICIES
from cosim.sumo.outputs import TRIPINFO_FILE, read_tripinfo

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SEEDS = range(10_000_000, 10_000_030)  # evaluation seeds, fixed


def play(env: MergeEnv, policy: str, seed: int) -> dict:
    act = POLICIES[policy](seed)
    env.reset(seed=seed)
    infos: dict = {}
    while env.agents:
        _, _, _, _, infos = env.step(act(env))
    return next(iter(infos.values()))["episode"]


def test_parallel_api_on_the_dilemma() -> None:
    env = cosim.parallel_env("configs/default.yaml")
    try:
        parallel_api_test(env, num_cycles=25)
    finally:
        env.close()


def test_aec_form_passes_the_pettingzoo_api_test() -> None:
    aec = cosim.env("configs/default.yaml")
    try:
        api_test(aec, num_cycles=25)
    finally:
        aec.close()


def test_courteous_avs_let_the_merging_vehicle_in_idle_ones_do_not() -> None:
    env = cosim.parallel_env("configs/default.yaml")
    try:
        merged = {p: np.mean([play(env, p, s)["merged"] for s in SEEDS]) for p in ("idle", "scripted", "courteous")}
    finally:
        env.close()
    # Measured on these seeds: idle 0.07, scripted 0.17, courteous 0.97.
    assert merged["courteous"] >= merged["idle"] + 0.5 and merged["courteous"] >= merged["scripted"] + 0.5
    assert merged["idle"] <= 0.4 and merged["scripted"] <= 0.4


def test_a_crash_ends_the_episode_and_is_attributed() -> None:
    env = cosim.parallel_env("configs/default.yaml")
    try:
        # Idle AVs keep their speed: those faster than the stream run into it.
        for seed in SEEDS:
            ep = play(env, "idle", seed)
            if ep["crashed"]:
                break
        snap = env.snapshot
    finally:
        env.close()
    assert ep["crashed"] and ep["length"] < env.max_steps
    first = ep["collisions"].split(";")[0].split()
    collider, victim = first[1].split(">")
    assert first[2] == "rear_end" and first[3] == f"fault={collider}" and collider.startswith("av_")
    assert ep["cause_av"] and not ep["cause_hv_into_av"]
    # The wrecks stay where they crashed, and the episode stopped at the collision's SUMO step.
    rows = snap.rows_of([collider, victim])
    assert (rows >= 0).all() and snap.crashed[rows].all()
    assert float(first[0]) == pytest.approx(snap.time)  # the collision's own SUMO step, not the decision's end


def test_flow_metrics_cover_the_same_window_whatever_the_ending(tmp_path: Path) -> None:
    env = cosim.parallel_env("configs/default.yaml", {"sim.outputs": True, "sim.output_dir": str(tmp_path)})
    outcomes = {}
    try:
        for policy in ("idle", "courteous"):
            for seed in SEEDS:
                ep = play(env, policy, seed)
                env.flush_outputs()
                out = env.sumo_outputs.pop(seed)
                if ep["crashed"] == (policy == "idle"):
                    trips = read_tripinfo(tmp_path / f"episode_{seed}" / TRIPINFO_FILE, ep["time"])
                    outcomes[policy] = (ep, out, env.window_distance, trips)
                    break
    finally:
        env.close()
    crash, crash_out, crash_d, crash_trips = outcomes["idle"]
    full, full_out, full_d, full_trips = outcomes["courteous"]
    assert crash["time"] < full["time"]  # the crash ended its episode early ...
    window = full["time"]
    # ... but SUMO ran it on to the horizon: the trips still on the road last the whole window.
    for trips in (crash_trips, full_trips):
        assert max(t["duration"] for t in trips) == pytest.approx(window)
    assert crash_out.throughput_vph == pytest.approx(crash_out.detector_count * 3600 / window)
    for d, out in ((crash_d, crash_out), (full_d, full_out)):  # our odometers and SUMO's agree over the window
        assert max(abs(d[v] - out.distance[v]) for v in d) < 0.05
