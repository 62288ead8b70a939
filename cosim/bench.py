"""`cosim bench`: our env against a bare libsumo loop, same machine, same scenario, one run.

(a) bare: `simulationStep` x one decision period + one read of every vehicle's state (plain getters, and
    subscriptions for comparison), and the getters' read made into the AVs' VelocityMaps (the default preset);
    (b) env.step with random actions, default preset; (c) the same with the `paper` preset; (d) env.reset vs a
    bare `libsumo.load`. Prints agent-decisions/s, b/a and c/a against the bare loop with the VelocityMap, the reset
    ratio, and memory per observation and per stored transition. `measure` returns the figures
    (scripts/bench_train.py takes the bare loop's from it). Training speed: scripts/bench_train.py.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cosim.config import OBSERVATION_PRESETS, Config, load_config
from cosim.environment.merge_env import MergeEnv
from cosim.files import atomic_copy
from cosim.sumo.scenario import kind_of
from cosim.sumo.snapshot import Snapshot

log = logging.getLogger(__name__)


def _env_rate(env: MergeEnv, episodes: int, keep_routes: Path | None = None) -> tuple[float, float, list[int]]:
    """(seconds per env.step, agent-decisions per second, each episode's decisions) with random actions; resets not
    timed. With `keep_routes`, each episode's route file is kept there for the bare loop to replay."""
    rng = np.random.default_rng(0)
    n_agents = 0
    lengths = []
    dt = 0.0
    for ep in range(episodes):
        env.reset(seed=ep)
        if keep_routes is not None:
            atomic_copy(env.route_file, keep_routes / f"episode_{ep}.rou.xml")
        lengths.append(0)
        t0 = time.perf_counter()
        while env.agents:
            n_agents += len(env.agents)
            env.step({a: int(rng.integers(5)) for a in env.agents})
            lengths[-1] += 1
        dt += time.perf_counter() - t0
    return dt / sum(lengths), n_agents / dt, lengths


def _reset_time(env: MergeEnv, resets: int) -> float:
    t0 = time.perf_counter()
    for k in range(resets):
        env.reset(seed=1000 + k)
    return (time.perf_counter() - t0) / resets


def _bare(base_args: list[str], routes: Path, steps_per_decision: int, lengths: list[int], resets: int,
          env: MergeEnv) -> dict[str, float]:
    """Seconds per decision of a bare loop over the env's episodes (same vehicles and seeds, each as many decisions as
    the env's random actions played, `lengths`): SUMO's steps
    and one read of every vehicle's state (getters, or subscriptions); `velocity_map`: the getters' read made into
    the AVs' VelocityMaps too (`env`'s mapper, what an observation needs and nothing else of the env)."""
    import libsumo as ls

    def args(ep: int) -> list[str]:
        return [*base_args, "-r", str(routes / f"episode_{ep}.rou.xml"), "--seed", str(ep)]

    ls.start(["sumo", *args(0)])
    veh = ls.vehicle
    var = ls.constants
    codes = [var.VAR_POSITION, var.VAR_ANGLE, var.VAR_SPEED, var.VAR_ROAD_ID, var.VAR_LANE_INDEX,
             var.VAR_LANEPOSITION, var.VAR_DISTANCE]
    mapper, agents = env.mapper, env.possible_agents
    out = {}
    try:
        def run(read: Callable[[], object], subscribe: bool = False) -> float:
            dt = 0.0
            for ep, decisions in enumerate(lengths):
                ls.load(args(ep))
                ls.simulationStep()
                mapper.reset()
                if subscribe:  # every vehicle departs at t = 0; SUMO refreshes the results at every step
                    for v in veh.getIDList():
                        veh.subscribe(v, codes)
                t0 = time.perf_counter()
                for _ in range(decisions):
                    for _ in range(steps_per_decision):
                        ls.simulationStep()
                    read()
                dt += time.perf_counter() - t0
            return dt / sum(lengths)

        def getters() -> list[tuple]:
            return [(*veh.getPosition(v), veh.getAngle(v), veh.getSpeed(v), veh.getRoadID(v), veh.getLaneIndex(v),
                     veh.getLanePosition(v), veh.getDistance(v)) for v in veh.getIDList()]

        def mapped() -> None:
            ids = veh.getIDList()
            a = np.array([(*veh.getPosition(v), veh.getAngle(v), veh.getSpeed(v), veh.getLaneIndex(v),
                           veh.getLanePosition(v), veh.getDistance(v)) for v in ids], dtype=np.float64)
            heading = np.radians(90.0 - a[:, 2])
            n = len(ids)
            snap = Snapshot(0.0, tuple(ids), np.fromiter((kind_of(v) for v in ids), np.int8, n), a[:, 0], a[:, 1],
                            heading, a[:, 3], np.zeros(n, np.int32), a[:, 4].astype(np.int32), a[:, 5], a[:, 6],
                            np.full(n, 5.0), np.full(n, 1.8), np.zeros(n, bool))
            mapper.update(snap, snap.rows_of(agents))

        out["getters"] = run(getters)
        out["subscriptions"] = run(veh.getAllSubscriptionResults, subscribe=True)
        out["velocity_map"] = run(mapped)
        t0 = time.perf_counter()
        for k in range(resets):
            ls.load(args(k % len(lengths)))
        out["load"] = (time.perf_counter() - t0) / resets
    finally:
        ls.close()
    return out


def measure(cfg: Config, episodes: int = 20, resets: int = 40) -> dict[str, Any]:
    """Our env and the bare loop on the same episodes (module doc): seconds per decision and per reset, agent-decisions
    per second, observation shapes and dtypes, the scenario as resolved on the net."""
    tmp = Path(tempfile.mkdtemp(prefix="cosim_bench_"))
    try:
        results: dict[str, Any] = {}
        for preset in ("default", "paper"):
            sizes = {f"observation.{k}": v for k, v in OBSERVATION_PRESETS[preset].items()}
            env = MergeEnv(load_config(cfg, {"observation.preset": preset, **sizes}))
            try:
                step_s, rate, lengths = _env_rate(env, episodes, tmp if preset == "default" else None)
                results[preset] = {"step_s": step_s, "agent_decisions_per_s": rate, "shape": list(env.mapper.shape),
                                   "dtype": np.dtype(env.mapper.dtype).name}
                if preset == "default":
                    reset_s = _reset_time(env, resets)
                    scenario = {"net": env.cfg.net.file, "n_avs": env.cfg.scenario.n_avs,
                                "n_hvs": env.cfg.scenario.n_hvs, "steps_per_decision": env.cfg.steps_per_decision,
                                "decisions": sum(lengths), "episodes": episodes}
                    # SUMO is closed first: the bare loop takes this process's one libsumo simulation.
                    env.session.close()
                    bare = _bare(list(env.session.args), tmp, env.cfg.steps_per_decision, lengths, resets, env)
            finally:
                env.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"scenario": scenario, "bare": bare, "env": results, "reset_s": reset_s}


def bench(cfg: Config, episodes: int = 20, resets: int = 40) -> dict[str, Any]:
    """Measure and print (module doc); returns the measurements (`measure`)."""
    m = measure(cfg, episodes, resets)
    sc, bare = m["scenario"], m["bare"]
    print(f"scenario: {sc['net']}, {sc['n_avs']} AVs + {sc['n_hvs']} HVs, {sc['steps_per_decision']} SUMO steps"
          f" per decision, {sc['episodes']} episodes, {sc['decisions']} decisions in all")
    print(f"(a) bare libsumo, getters      : {bare['getters'] * 1e3:7.3f} ms/decision")
    print(f"(a) bare libsumo, subscriptions: {bare['subscriptions'] * 1e3:7.3f} ms/decision")
    print(f"(a) bare libsumo + VelocityMap : {bare['velocity_map'] * 1e3:7.3f} ms/decision (getters, the AVs' maps)")
    a = bare["velocity_map"]
    for tag, preset in (("b", "default"), ("c", "paper")):
        r = m["env"][preset]
        shape, dtype = r["shape"], r["dtype"]
        obs_bytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        print(f"({tag}) env.step, {preset:7s} {tuple(shape)}: {r['step_s'] * 1e3:7.3f} ms/decision, "
              f"{r['agent_decisions_per_s']:8.0f} agent-decisions/s, {tag}/a = {r['step_s'] / a:5.2f}")
        print(f"    memory: {obs_bytes / 1024:8.1f} KiB per observation ({dtype}), "
              f"{2 * obs_bytes / 1024:8.1f} KiB per stored transition (s, s'), "
              f"{obs_bytes / shape[0] / 1024:6.1f} KiB if only the newest frame is stored")
    print(f"(d) reset: env {m['reset_s'] * 1e3:6.2f} ms vs bare libsumo.load {bare['load'] * 1e3:6.2f} ms, "
          f"ratio {m['reset_s'] / bare['load']:4.2f}")
    return m
