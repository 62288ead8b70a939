"""`cosim bench`: our env against a bare libsumo loop, same machine, same scenario, one run.

(a) bare: `simulationStep` x one decision period + one read of every vehicle's state (plain getters, and
    subscriptions for comparison), and the getters' read made into the AVs' VelocityMaps (the default preset);
    (b) env.step with random actions, default preset; (c) the same with the `paper` preset; (d) env.reset vs a
    bare `libsumo.load`. (a) replays each of (b)'s episodes right after it, and (d)'s loads alternate with the env's
    resets, so that b/a and the reset ratio are taken on the same stretch of the machine's time; (c) runs after
    them, so c/a is not. Prints agent-decisions/s, b/a and c/a against the bare loop with the VelocityMap, the
    reset ratio, and memory per observation and per stored transition. `measure` returns the figures
    (scripts/bench_train.py takes the bare loop's from it). Training speed: scripts/bench_train.py.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cosim.config import OBSERVATION_PRESETS, Config, load_config
from cosim.environment.merge_env import MergeEnv
from cosim.sumo.scenario import kind_of
from cosim.sumo.snapshot import Snapshot

log = logging.getLogger(__name__)


def _env_episode(env: MergeEnv, seed: int, rng: np.random.Generator) -> tuple[float, int, int]:
    """One episode of env.step with random actions after a reset (not timed): (seconds, agent-decisions,
    decisions)."""
    env.reset(seed=seed)
    n_agents = decisions = 0
    t0 = time.perf_counter()
    while env.agents:
        n_agents += len(env.agents)
        env.step({a: int(rng.integers(5)) for a in env.agents})
        decisions += 1
    return time.perf_counter() - t0, n_agents, decisions


def _bare_loops(env: MergeEnv) -> dict[str, Callable[[int], float]]:
    """The bare loops of (a), by name, each a function decisions -> seconds that replays the env's last episode
    (its route file and seed; SUMO's models drive its AVs) for that many decisions: SUMO's steps and one
    read of every vehicle's state (getters, or subscriptions); `velocity_map`: the getters' read made into the AVs'
    VelocityMaps too (`env`'s mapper, what an observation needs and nothing else of the env). They reload this
    process's one libsumo simulation, the env's: its next reset loads its own episode again."""
    import libsumo as ls

    veh = ls.vehicle
    var = ls.constants
    codes = [var.VAR_POSITION, var.VAR_ANGLE, var.VAR_SPEED, var.VAR_ROAD_ID, var.VAR_LANE_INDEX,
             var.VAR_LANEPOSITION, var.VAR_DISTANCE]
    mapper, agents, steps = env.mapper, env.possible_agents, env.cfg.steps_per_decision

    def loop(read: Callable[[], object], subscribe: bool = False) -> Callable[[int], float]:
        def replay(decisions: int) -> float:
            _bare_load(env)
            ls.simulationStep()
            mapper.reset()
            if subscribe:  # every vehicle departs at t = 0; SUMO refreshes the results at every step
                for v in veh.getIDList():
                    veh.subscribe(v, codes)
            t0 = time.perf_counter()
            for _ in range(decisions):
                for _ in range(steps):
                    ls.simulationStep()
                read()
            return time.perf_counter() - t0
        return replay

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

    return {"getters": loop(getters), "subscriptions": loop(veh.getAllSubscriptionResults, subscribe=True),
            "velocity_map": loop(mapped)}


def _bare_load(env: MergeEnv) -> float:
    """Seconds of a bare `libsumo.load` of the env's last episode (its route file and seed)."""
    import libsumo as ls

    t0 = time.perf_counter()
    ls.load([*env.session.args, "-r", str(env.route_file), "--seed", str(env.episode_seed)])
    return time.perf_counter() - t0


def measure(cfg: Config, episodes: int = 20, resets: int = 40) -> dict[str, Any]:
    """Our env and the bare loop on the same episodes (module doc): seconds per decision and per reset, agent-decisions
    per second, observation shapes and dtypes, the scenario as resolved on the net. With the default preset, each of
    the env's episodes is replayed by the bare loops at once, and each env reset is followed by a bare load of the
    same episode: the ratios are taken on the same stretch of the machine's time, which other work on the machine
    shifts alike (measured one after the other, they varied 1.1-1.8x from run to run on a loaded machine)."""
    results: dict[str, Any] = {}
    for preset in ("default", "paper"):
        rng = np.random.default_rng(0)
        sizes = {f"observation.{k}": v for k, v in OBSERVATION_PRESETS[preset].items()}
        env = MergeEnv(load_config(cfg, {"observation.preset": preset, **sizes}))
        try:
            bare_loops = _bare_loops(env) if preset == "default" else {}
            seconds = {name: 0.0 for name in ("env", *bare_loops)}
            n_agents = decisions = 0
            for ep in range(episodes):
                dt, agents, length = _env_episode(env, ep, rng)
                seconds["env"] += dt
                n_agents += agents
                decisions += length
                for name, replay in bare_loops.items():
                    seconds[name] += replay(length)
            results[preset] = {"step_s": seconds["env"] / decisions, "agent_decisions_per_s": n_agents / seconds["env"],
                               "shape": list(env.mapper.shape), "dtype": np.dtype(env.mapper.dtype).name}
            if preset == "default":
                bare = {name: seconds[name] / decisions for name in bare_loops}
                reset_s = load_s = 0.0
                for k in range(resets):
                    t0 = time.perf_counter()
                    env.reset(seed=1000 + k)
                    reset_s += time.perf_counter() - t0
                    load_s += _bare_load(env)
                bare["load"] = load_s / resets
                scenario = {"net": env.cfg.net.file, "n_avs": env.cfg.scenario.n_avs,
                            "n_hvs": env.cfg.scenario.n_hvs, "steps_per_decision": env.cfg.steps_per_decision,
                            "decisions": decisions, "episodes": episodes}
        finally:
            env.close()
    return {"scenario": scenario, "bare": bare, "env": results, "reset_s": reset_s / resets}


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
