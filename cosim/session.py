"""The one module that talks to libsumo: start, reset (load), step, snapshot, AV commands, close.

Contract: a `SumoSession` owns the process's single libsumo simulation (libsumo silently replaces a
running simulation when started twice, so a second live session in one process raises
`SimulationError`; use worker processes). Each decision step the env calls `advance` (several SUMO steps
with the AVs' speed commands applied, collisions and arrivals collected) and then `snapshot`, which reads
every vehicle's state once into numpy arrays. Nothing outside this module imports libsumo.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from cosim.errors import SimulationError
from cosim.snapshot import KIND_AV, Snapshot

log = logging.getLogger(__name__)

_LIVE: dict[int, SumoSession] = {}  # pid -> the live session of that process


def _libsumo():
    # Imported on first use, not at module import: no side effects for users who only read configs.
    import libsumo

    return libsumo


class SumoSession:
    def __init__(self, net_file: Path, step_length: float, extra_args: Sequence[str] = (),
                 mingap_factor: float = 0.0, edge_index: dict[str, int] | None = None,
                 kind_of: Callable[[str], int] | None = None) -> None:
        other = _LIVE.get(os.getpid())
        if other is not None:
            raise SimulationError(
                "a simulation is already live in this process: libsumo runs one simulation per process "
                "and would silently replace it. Close the other env first (env.close()), or run several "
                "envs in worker processes (multiprocessing), one env per process."
            )
        _LIVE[os.getpid()] = self
        self.net_file = Path(net_file)
        self.step_length = step_length
        self._edge_index = edge_index or {}
        self._kind_of = kind_of or (lambda vid: KIND_AV)
        self.args = [
            "-n", str(self.net_file),
            "--step-length", str(step_length),
            # Crashes are ours to handle: report them, keep both vehicles where they are.
            "--collision.action", "warn",
            "--collision.check-junctions", "true",
            "--collision.mingap-factor", str(mingap_factor),
            "--time-to-teleport", "-1",
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
            *extra_args,
        ]
        self._started = False
        self._sizes: dict[str, tuple[float, float]] = {}
        self._commanded: dict[str, float] = {}
        self._crashed: set[str] = set()  # every vehicle in a collision this episode
        self._crashed_period: set[str] = set()  # ... of which newly in the last `advance`
        self._arrived: set[str] = set()

    # -- lifecycle ----------------------------------------------------------------------------------
    def load(self, route_file: Path, seed: int) -> None:
        """Start SUMO (first call) or reload it with this episode's routes and seed: a reproducible reset."""
        ls = _libsumo()
        args = [*self.args, "-r", str(route_file), "--seed", str(seed)]
        try:
            if self._started:
                ls.load(args)
            else:
                ls.start(["sumo", *args])
                self._started = True
        except ls.TraCIException as exc:
            raise SimulationError(f"SUMO failed to start with net {self.net_file}: {exc}") from None
        except ls.FatalTraCIError as exc:
            raise SimulationError(f"SUMO failed to start with net {self.net_file}: {exc}") from None
        self._sizes.clear()
        self._commanded.clear()
        self._crashed.clear()
        self._crashed_period.clear()
        self._arrived.clear()
        self._sim_step()  # insert the t = 0 vehicles
        for vid in ls.vehicle.getIDList():
            self._on_insert(vid)

    def close(self) -> None:
        if self._started:
            try:
                _libsumo().close()
            except Exception as exc:  # closing a crashed SUMO must not hide the original error
                log.debug("libsumo.close failed: %s", exc)
            self._started = False
        if _LIVE.get(os.getpid()) is self:
            del _LIVE[os.getpid()]

    @property
    def time(self) -> float:
        return _libsumo().simulation.getTime()

    # -- stepping -----------------------------------------------------------------------------------
    def _sim_step(self) -> None:
        ls = _libsumo()
        try:
            ls.simulationStep()
        except (ls.TraCIException, ls.FatalTraCIError) as exc:
            raise SimulationError(f"SUMO failed during simulationStep: {exc}") from None
        collided = ls.simulation.getCollidingVehiclesIDList()
        new = [v for v in collided if v not in self._crashed]
        for vid in new:
            # A wreck stops where it is; the env decides when to take it off the road.
            ls.vehicle.setSpeedMode(vid, 0)
            ls.vehicle.setLaneChangeMode(vid, 0)
            ls.vehicle.setSpeed(vid, 0.0)
            self._commanded.pop(vid, None)
        self._crashed.update(new)
        self._arrived.update(ls.simulation.getArrivedIDList())
        for vid in ls.simulation.getDepartedIDList():
            self._on_insert(vid)

    def _on_insert(self, vid: str) -> None:
        ls = _libsumo()
        vtype = ls.vehicle.getTypeID(vid)
        self._sizes[vid] = (ls.vehicletype.getLength(vtype), ls.vehicletype.getWidth(vtype))
        if self._kind_of(vid) == KIND_AV:
            # The env drives AVs: no SUMO lane changing, no safety checks, so AVs can crash.
            ls.vehicle.setLaneChangeMode(vid, 0)
            ls.vehicle.setSpeedMode(vid, 0)
            self._commanded[vid] = ls.vehicle.getSpeed(vid)

    def advance(self, n_steps: int, target_speed: dict[str, float], accel: float, decel: float,
                max_speed: float) -> None:
        """Run `n_steps` SUMO steps; each step moves every live AV's speed toward its target within
        [-decel, +accel] * step and [0, max_speed], since SUMO ignores these limits at speed mode 0."""
        ls = _libsumo()
        before = set(self._crashed)
        self._arrived.clear()
        dv_up, dv_down = accel * self.step_length, decel * self.step_length
        for _ in range(n_steps):
            for vid, target in target_speed.items():
                v = self._commanded.get(vid)
                if v is None:  # crashed or gone
                    continue
                v = min(max(v + min(max(target - v, -dv_down), dv_up), 0.0), max_speed)
                self._commanded[vid] = v
                ls.vehicle.setSpeed(vid, v)
            self._sim_step()
            for vid in self._arrived:
                self._commanded.pop(vid, None)
        self._crashed_period = self._crashed - before

    def change_lane(self, vid: str, direction: int, duration: float) -> None:
        """Immediate lane change by +1 (left) or -1 (right); lane change mode 0 skips SUMO's gap checks."""
        _libsumo().vehicle.changeLaneRelative(vid, direction, duration)

    def remove(self, vids: Sequence[str]) -> None:
        ls = _libsumo()
        live = set(ls.vehicle.getIDList())
        for vid in vids:
            if vid in live:
                ls.vehicle.remove(vid)
            self._commanded.pop(vid, None)

    # -- state --------------------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """Every vehicle's state, read once with plain getters (in libsumo as fast as subscriptions)."""
        ls = _libsumo()
        veh = ls.vehicle
        ids = tuple(veh.getIDList())
        n = len(ids)
        x = np.empty(n)
        y = np.empty(n)
        angle = np.empty(n)
        speed = np.empty(n)
        edge = np.empty(n, dtype=np.int32)
        lane = np.empty(n, dtype=np.int32)
        lane_pos = np.empty(n)
        dist = np.empty(n)
        length = np.empty(n)
        width = np.empty(n)
        eidx = self._edge_index
        sizes = self._sizes
        for i, vid in enumerate(ids):
            x[i], y[i] = veh.getPosition(vid)
            angle[i] = veh.getAngle(vid)
            speed[i] = veh.getSpeed(vid)
            edge[i] = eidx.get(veh.getRoadID(vid), -1)
            lane[i] = veh.getLaneIndex(vid)
            lane_pos[i] = veh.getLanePosition(vid)
            dist[i] = veh.getDistance(vid)
            length[i], width[i] = sizes[vid]
        # SUMO: angle in degrees clockwise from north, position at the front bumper.
        heading = np.radians(90.0 - angle)
        x -= 0.5 * length * np.cos(heading)
        y -= 0.5 * length * np.sin(heading)
        crashed = np.fromiter((vid in self._crashed_period for vid in ids), dtype=bool, count=n)
        kind = np.fromiter((self._kind_of(v) for v in ids), dtype=np.int8, count=n)
        return Snapshot(time=self.time, ids=ids, kind=kind, x=x, y=y, heading=np.remainder(heading, 2 * math.pi),
                        speed=speed, edge=edge, lane=lane, lane_pos=lane_pos, distance=dist, length=length,
                        width=width, crashed=crashed, arrived=frozenset(self._arrived))
