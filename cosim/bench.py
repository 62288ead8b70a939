"""`cosim bench`: our env against a bare libsumo loop, same machine, same scenario, one run.

(a) bare: `simulationStep` x one decision period + one read of every vehicle's state (plain getters, and
    subscriptions for comparison); (b) env.step with random actions, default preset; (c) the same with the
    `paper` preset; (d) env.reset vs a bare `libsumo.load`. Prints agent-decisions/s, b/a, c/a, reset ratio,
    and memory per observation and per stored transition. Training speed: scripts/bench_train.py.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cosim.config import OBSERVATION_PRESETS, Config, load_config
from cosim.environment.merge_env import MergeEnv

log = logging.getLogger(__name__)


def _env_rate(env: MergeEnv, episodes: int, keep_routes: Path | None = None) -> tuple[float, float]:
    """(seconds per env.step, agent-decisions per second) with random actions; resets not timed.
    With `keep_routes`, each episode's route file is kept there for the bare loop to replay."""
    rng = np.random.default_rng(0)
    n_steps = n_agents = 0
    dt = 0.0
    for ep in range(episodes):
        env.reset(seed=ep)
        if keep_routes is not None:
            shutil.copy(env.route_file, keep_routes / f"episode_{ep}.rou.xml")
        t0 = time.perf_counter()
        while env.agents:
            n_agents += len(env.agents)
            env.step({a: int(rng.integers(5)) for a in env.agents})
            n_steps += 1
        dt += time.perf_counter() - t0
    return dt / n_steps, n_agents / dt


def _reset_time(env: MergeEnv, resets: int) -> float:
    t0 = time.perf_counter()
    for k in range(resets):
        env.reset(seed=1000 + k)
    return (time.perf_counter() - t0) / resets


def _bare(base_args: list[str], routes: Path, steps_per_decision: int, decisions: int, episodes: int,
          resets: int) -> dict[str, float]:
    """Seconds per decision of a bare loop over the env's episodes (same vehicles, seeds and horizon)."""
    import libsumo as ls

    def args(ep: int) -> list[str]:
        return [*base_args, "-r", str(routes / f"episode_{ep}.rou.xml"), "--seed", str(ep)]

    ls.start(["sumo", *args(0)])
    veh = ls.vehicle
    var = ls.constants
    codes = [var.VAR_POSITION, var.VAR_ANGLE, var.VAR_SPEED, var.VAR_ROAD_ID, var.VAR_LANE_INDEX,
             var.VAR_LANEPOSITION, var.VAR_DISTANCE]
    out = {}
    try:
        def run(read: Callable[[], object], subscribe: bool = False) -> float:
            dt = 0.0
            for ep in range(episodes):
                ls.load(args(ep))
                ls.simulationStep()
                if subscribe:  # every vehicle departs at t = 0; SUMO refreshes the results at every step
                    for v in veh.getIDList():
                        veh.subscribe(v, codes)
                t0 = time.perf_counter()
                for _ in range(decisions):
                    for _ in range(steps_per_decision):
                        ls.simulationStep()
                    read()
                dt += time.perf_counter() - t0
            return dt / (episodes * decisions)

        def getters() -> None:
            for v in veh.getIDList():
                veh.getPosition(v), veh.getAngle(v), veh.getSpeed(v), veh.getRoadID(v)
                veh.getLaneIndex(v), veh.getLanePosition(v), veh.getDistance(v)

        out["getters"] = run(getters)
        out["subscriptions"] = run(veh.getAllSubscriptionResults, subscribe=True)
        t0 = time.perf_counter()
        for k in range(resets):
            ls.load(args(k % episodes))
        out["load"] = (time.perf_counter() - t0) / resets
    finally:
        ls.close()
    return out


def bench(cfg: Config, episodes: int = 20, resets: int = 40) -> None:
    """Measure and print (module doc)."""
    tmp = Path(tempfile.mkdtemp(prefix="cosim_bench_"))
    try:
        results = {}
        for preset in ("default", "paper"):
            sizes = {f"observation.{k}": v for k, v in OBSERVATION_PRESETS[preset].items()}
            env = MergeEnv(load_config(cfg, {"observation.preset": preset, **sizes}))
            try:
                step_s, rate = _env_rate(env, episodes, tmp if preset == "default" else None)
                results[preset] = (step_s, rate, env.mapper.shape, env.mapper.dtype)
                if preset == "default":
                    reset_s = _reset_time(env, resets)
                    sumo_args, decisions = list(env.session.args), env.max_steps
            finally:
                env.close()
        bare = _bare(sumo_args, tmp, cfg.steps_per_decision, decisions, episodes, resets)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    a = min(bare["getters"], bare["subscriptions"])
    n = cfg.scenario.n_avs
    print(f"scenario: {cfg.net.file}, {n} AVs + {cfg.scenario.n_hvs} HVs, {cfg.steps_per_decision} SUMO steps"
          f" per decision, {episodes} episodes of {decisions} decisions")
    print(f"(a) bare libsumo, getters      : {bare['getters'] * 1e3:7.3f} ms/decision")
    print(f"(a) bare libsumo, subscriptions: {bare['subscriptions'] * 1e3:7.3f} ms/decision")
    for tag, preset in (("b", "default"), ("c", "paper")):
        step_s, rate, shape, dtype = results[preset]
        obs_bytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        print(f"({tag}) env.step, {preset:7s} {shape}: {step_s * 1e3:7.3f} ms/decision, "
              f"{rate:8.0f} agent-decisions/s, {tag}/a = {step_s / a:5.2f}")
        print(f"    memory: {obs_bytes / 1024:8.1f} KiB per observation ({dtype}), "
              f"{2 * obs_bytes / 1024:8.1f} KiB per stored transition (s, s'), "
              f"{obs_bytes / shape[0] / 1024:6.1f} KiB if only the newest frame is stored")
    print(f"(d) reset: env {reset_s * 1e3:6.2f} ms vs bare libsumo.load {bare['load'] * 1e3:6.2f} ms, "
          f"ratio {reset_s / bare['load']:4.2f}")
