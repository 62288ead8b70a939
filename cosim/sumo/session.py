"""The one module that talks to SUMO: start, reset (load), step, snapshot, AV commands, close; through
libsumo, or through TraCI to sumo-gui for people to watch (`Gui`).

Contract: a `SumoSession` owns the process's single libsumo simulation (libsumo silently replaces a
running simulation when started twice, so a second live session in one process raises
`SimulationError`; use worker processes). Each decision step the env calls `advance` (several SUMO steps
with the AVs' speed commands applied, collisions and arrivals collected; with `stop_on` it stops after the
first step with a collision involving a vehicle of those classes) and then `snapshot`, which reads every
vehicle's state once into numpy arrays, with the period's collisions (`Collision`, from SUMO's own
`simulation.getCollisions()`) and arrivals. A collided vehicle is stopped where it is and stays there until
the env removes it. `run_out(until)` hands the AVs back to SUMO's driver models and steps on to time
`until` (for flow metrics over a fixed window after an episode ended early). Nothing outside this module
imports libsumo or traci.

With `gui=Gui(...)` the same session drives sumo-gui over TraCI (libsumo's GUI mode is experimental; TraCI and
libsumo share one API, so every call below is the same, only slower: about 90 steps/s): the window shows the
merge area (`Gui.view`), vehicles in their class's colour and crashed ones in `Gui.crashed`, and `label(vid,
text)` writes a line above a vehicle (the replay's AV actions). `on_step`, when set, is called after every
SUMO step of `advance` (a video's frames); `view()` reads the state then without taking the period's
collisions and arrivals from the next `snapshot`. sumo-gui needs a display (`DISPLAY`; Xvfb where there is
none).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import shlex
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from cosim.errors import SimulationError
from cosim.sumo.snapshot import KIND_AV, Collision, Snapshot

log = logging.getLogger(__name__)

_LIVE: dict[int, SumoSession] = {}  # pid -> the live session of that process


GUI_SETTINGS = Path(__file__).with_name("gui_settings.xml")  # dark background, `label` texts shown
LABEL_PARAM = "cosim.label"  # the vehicle parameter sumo-gui shows above each vehicle (GUI_SETTINGS)
RGB = tuple[int, int, int]


@dataclass(frozen=True)
class Gui:
    """sumo-gui instead of libsumo: what its window shows first and how vehicles look."""

    view: tuple[float, float, float, float]  # [m] x0, y0, x1, y1 in network coordinates (the merge area)
    colours: Mapping[int, RGB]  # KIND_* -> its vehicles' colour
    crashed: RGB  # vehicles in a collision
    delay: float = 0.0  # [ms] sumo-gui's pause after each step, so that a person can follow
    window: tuple[int, int] = (1280, 600)  # [px]

    def args(self) -> list[str]:
        return ["--start", "--quit-on-end", "--gui-settings-file", str(GUI_SETTINGS),
                "--window-size", f"{self.window[0]},{self.window[1]}", "--delay", str(self.delay)]


def _sumo_module(gui: bool) -> ModuleType:
    """traci for sumo-gui, else libsumo: one API. Imported on first use, not at module import: no side
    effects for users who only read configs."""
    if gui:
        import traci

        return traci
    import libsumo

    return libsumo


# The AVs' SUMO modes (TraCI's setSpeedMode, setLaneChangeMode) by `av.shield`. none: speed mode 0, no safe speed
# and no limits of acceleration (the env applies av.accel and av.decel itself), and lane change mode 0, no lane
# changes of their own and a commanded one at once whatever the neighbours: AVs can crash. sumo: speed mode 31 (bits
# 0-4: the car-following model's safe speed, the vType's acceleration and deceleration, right of way; SUMO's default)
# and lane change mode 512 (bits 8-9 = 2: a commanded change only where it respects the others' speed and brake gaps;
# bits 0-7 = 0: still no strategic, cooperative, speed-gain or keep-right changes of their own).
AV_MODES: dict[str, tuple[int, int]] = {"none": (0, 0), "sumo": (31, 512)}


class SumoSession:
    def __init__(self, net_file: Path, step_length: float, edge_index: dict[str, int],
                 kind_of: Callable[[str], int], extra_args: Sequence[str] = (), mingap_factor: float = 0.0,
                 drive_avs: bool = True, gui: Gui | None = None, shield: str = "none") -> None:
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
        self._edge_index = edge_index  # edge id (normal or junction-internal) -> the snapshot's edge index
        self._kind_of = kind_of  # vehicle id -> KIND_*
        self.drive_avs = drive_avs  # False: SUMO's own models drive the AVs (the all-human baseline)
        self.av_modes = AV_MODES[shield]  # (speed mode, lane change mode) of the AVs the env drives
        self.gui = gui
        self._sumo = _sumo_module(gui is not None)
        self.on_step: Callable[[], None] | None = None  # called after each SUMO step of `advance`
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
        self._static: dict[str, tuple[int, float, float]] = {}  # vid -> (kind, length, width)
        self._commanded: dict[str, float] = {}
        self._crashed: set[str] = set()  # every vehicle in a collision this episode
        self._crashed_period: set[str] = set()  # ... of which newly in the last `advance`
        self._pairs: set[frozenset[str]] = set()  # colliding pairs seen this episode (SUMO repeats them)
        self._collisions: list[Collision] = []  # first seen since the last snapshot
        self._arrived: list[str] = []  # since the last snapshot

    # -- lifecycle ----------------------------------------------------------------------------------
    def load(self, route_file: Path, seed: int, extra_args: Sequence[str] = ()) -> None:
        """Start SUMO (first call) or reload it with this episode's routes and seed: a reproducible reset.
        `extra_args` are this episode's own options (e.g. its output files)."""
        ls = self._sumo
        # sumo-gui parses the whole command line again at a reload: its own options go every time.
        args = [*(self.gui.args() if self.gui else ()), *self.args, *extra_args, "-r", str(route_file),
                "--seed", str(seed)]
        try:
            if self._started:
                ls.load(args)
            elif self.gui is None:
                ls.start(["sumo", *args])  # libsumo ignores the binary's name
            else:
                import sumolib

                # TraCI prints a line per second until sumo-gui listens (it takes a second or two), and starts
                # sumo-gui again for each failed connection: a few times, not its default 60.
                with contextlib.redirect_stdout(io.StringIO()):
                    ls.start([sumolib.checkBinary("sumo-gui"), *args], numRetries=5)
            self._started = True
        except (ls.TraCIException, ls.FatalTraCIError) as exc:
            # libsumo's exception only says that SUMO stopped ("Could not parse commandline options."); SUMO's
            # own error line, on stderr before it, names the option or file, which may not be the net's.
            raise SimulationError(f"SUMO failed to start: {str(exc).rstrip('.')} (SUMO's own error above names "
                                  f"the cause; its options: {shlex.join(args)})") from None
        for state in (self._static, self._commanded, self._crashed, self._crashed_period, self._pairs,
                      self._collisions, self._arrived):
            state.clear()
        self._sim_step()  # inserts the t = 0 vehicles
        if self.gui is not None:
            ls.gui.setBoundary(ls.gui.DEFAULT_VIEW, *self.gui.view)  # after the load: a reload resets the view

    def end_simulation(self) -> None:
        """Close SUMO (which completes its output files) but keep this process's slot; `load` restarts it."""
        if self._started:
            try:
                self._sumo.close()
            except Exception as exc:  # closing a crashed SUMO must not hide the original error
                log.debug("closing SUMO failed: %s", exc)
            self._started = False

    def close(self) -> None:
        self.end_simulation()
        if _LIVE.get(os.getpid()) is self:
            del _LIVE[os.getpid()]

    # -- stepping -----------------------------------------------------------------------------------
    def _sim_step(self) -> None:
        ls = self._sumo
        try:
            ls.simulationStep()
        except (ls.TraCIException, ls.FatalTraCIError) as exc:
            raise SimulationError(f"SUMO failed during simulationStep: {exc}") from None
        collisions = ls.simulation.getCollisions()
        if collisions:
            self._on_collisions(collisions)
        arrived = ls.simulation.getArrivedIDList()
        for vid in arrived:
            self._commanded.pop(vid, None)
            self._static.pop(vid, None)
        self._arrived.extend(arrived)
        for vid in ls.simulation.getDepartedIDList():
            self._on_insert(vid)

    def _on_collisions(self, collisions: Sequence) -> None:
        ls = self._sumo
        now = ls.simulation.getTime()
        for c in collisions:
            pair = frozenset((c.collider, c.victim))
            if pair in self._pairs:
                continue
            self._pairs.add(pair)
            kinds = [self._static[v][0] if v in self._static else self._kind_of(v) for v in (c.collider, c.victim)]
            self._collisions.append(Collision(now, c.collider, c.victim, *kinds, c.type, c.lane))
            for vid in (c.collider, c.victim):
                if vid in self._crashed:
                    continue
                # A wreck stops where it is; the env decides when to take it off the road.
                ls.vehicle.setSpeedMode(vid, 0)
                ls.vehicle.setLaneChangeMode(vid, 0)
                ls.vehicle.setSpeed(vid, 0.0)
                if self.gui is not None:
                    ls.vehicle.setColor(vid, (*self.gui.crashed, 255))
                self._commanded.pop(vid, None)
                self._crashed.add(vid)

    def _on_insert(self, vid: str) -> None:
        ls = self._sumo
        vtype = ls.vehicle.getTypeID(vid)
        kind = self._kind_of(vid)
        self._static[vid] = (kind, ls.vehicletype.getLength(vtype), ls.vehicletype.getWidth(vtype))
        if self.gui is not None and kind in self.gui.colours:
            ls.vehicle.setColor(vid, (*self.gui.colours[kind], 255))
        if self.drive_avs and kind == KIND_AV:
            # The env drives AVs: no lane changes of SUMO's, its safety checks only with a shield (AV_MODES).
            speed_mode, lane_change_mode = self.av_modes
            ls.vehicle.setLaneChangeMode(vid, lane_change_mode)
            ls.vehicle.setSpeedMode(vid, speed_mode)
            self._commanded[vid] = speed = ls.vehicle.getSpeed(vid)
            ls.vehicle.setSpeed(vid, speed)  # held from now on, not left to the car-following model

    def advance(self, n_steps: int, target_speed: dict[str, float], accel: float, decel: float,
                max_speed: float, stop_on: frozenset[int] = frozenset()) -> None:
        """Run `n_steps` SUMO steps; each step moves every live AV's speed toward its target within
        [-decel, +accel] * step and [0, max_speed], since SUMO ignores these limits at speed mode 0.
        Stops after the first step with a new collision involving a vehicle of a class in `stop_on`."""
        ls = self._sumo
        before = set(self._crashed)
        seen = len(self._collisions)
        dv_up, dv_down = accel * self.step_length, decel * self.step_length
        # SUMO keeps the last setSpeed: only AVs still on their way to the target need a command.
        ramping = {v: t for v, t in target_speed.items() if self._commanded.get(v, t) != t}
        for _ in range(n_steps):
            for vid, target in list(ramping.items()):
                v = self._commanded.get(vid)
                if v is None:  # crashed or gone
                    del ramping[vid]
                    continue
                v = min(max(v + min(max(target - v, -dv_down), dv_up), 0.0), max_speed)
                self._commanded[vid] = v
                ls.vehicle.setSpeed(vid, v)
                if v == target:  # the last increment lands exactly on the target
                    del ramping[vid]
            self._sim_step()
            if self.on_step is not None:
                self.on_step()
            new = self._collisions[seen:]
            if stop_on and any(c.collider_kind in stop_on or c.victim_kind in stop_on for c in new):
                break
            seen = len(self._collisions)
        self._crashed_period = self._crashed - before

    def run_out(self, until: float) -> None:
        """Hand the AVs that are not wrecks back to SUMO's models (safe driving, own lane changes) and step
        on until simulation time `until` [s]; collisions are handled as during the episode."""
        ls = self._sumo
        for vid in list(self._commanded):
            ls.vehicle.setSpeedMode(vid, 31)  # SUMO's defaults: every safety check on
            ls.vehicle.setLaneChangeMode(vid, 1621)
            ls.vehicle.setSpeed(vid, -1)
        self._commanded.clear()
        half = 0.5 * self.step_length
        while ls.simulation.getTime() < until - half:
            self._sim_step()

    def change_lane(self, vid: str, direction: int) -> None:
        """Lane change by +1 (left) or -1 (right) in the next step; lane change mode 0 skips SUMO's gap
        checks. The request lasts one step: a meta-action is one change, never a lane to hold (lane indices
        shift by one where the acceleration lane starts)."""
        self._sumo.vehicle.changeLaneRelative(vid, direction, self.step_length)

    def remove(self, vids: Sequence[str]) -> None:
        ls = self._sumo
        live = set(ls.vehicle.getIDList())
        for vid in vids:
            if vid in live:
                ls.vehicle.remove(vid)
            self._commanded.pop(vid, None)
            self._static.pop(vid, None)

    def pending(self) -> tuple[str, ...]:
        """Vehicles whose departure time has come but that SUMO could not insert yet (its insertion backlog)."""
        return tuple(self._sumo.simulation.getPendingVehicles())

    # -- sumo-gui -----------------------------------------------------------------------------------

    def label(self, vid: str, text: str) -> None:
        """With a `Gui`: show `text` above vehicle `vid` in sumo-gui (a vehicle not on the road is skipped)."""
        if self.gui is not None and vid in self._static:
            self._sumo.vehicle.setParameter(vid, LABEL_PARAM, text)

    def screenshot(self, path: Path) -> None:
        """With a `Gui`: save sumo-gui's view as an image (PNG by the name's suffix). sumo-gui draws it during
        a step, so this steps the simulation once more: call it when the episode is over."""
        if self.gui is None:
            raise SimulationError("a screenshot needs sumo-gui (a session with a Gui)")
        self._sumo.gui.screenshot(self._sumo.gui.DEFAULT_VIEW, str(Path(path).resolve()))
        self._sim_step()

    # -- state --------------------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """Every vehicle's state, read once per decision with plain getters. Subscriptions would be refreshed
        by SUMO at every one of the decision's steps; `cosim bench` measures both, getters win here."""
        snap = self._read(self._crashed_period, (tuple(self._collisions), tuple(self._arrived)))
        self._collisions.clear()
        self._arrived.clear()
        return snap

    def view(self) -> Snapshot:
        """The state now, between decisions (a video's frames): `crashed` marks every vehicle in a collision
        so far this episode, and the period's collisions and arrivals stay for the next `snapshot`."""
        return self._read(self._crashed, ((), ()))

    def _read(self, crashed: set[str], events: tuple[tuple[Collision, ...], tuple[str, ...]]) -> Snapshot:
        ls = self._sumo
        veh = ls.vehicle
        ids = veh.getIDList()
        n = len(ids)
        eidx, static = self._edge_index, self._static
        # One tuple per vehicle, one array conversion: fewer numpy calls than filling arrays by index.
        rows = [(*veh.getPosition(v), veh.getAngle(v), veh.getSpeed(v), eidx.get(veh.getRoadID(v), -1),
                 veh.getLaneIndex(v), veh.getLanePosition(v), veh.getDistance(v), *static[v]) for v in ids]
        a = np.array(rows, dtype=np.float64).reshape(n, 11)
        x, y, angle, speed, edge, lane, lane_pos, dist, kind, length, width = (*a[:, :8].T, *a[:, 8:].T)
        # SUMO: angle in degrees clockwise from north, position at the front bumper.
        heading = np.radians(90.0 - angle)
        return Snapshot(
            time=ls.simulation.getTime(), ids=tuple(ids), kind=kind.astype(np.int8), collisions=events[0],
            arrived=events[1],
            x=x - 0.5 * length * np.cos(heading), y=y - 0.5 * length * np.sin(heading),
            heading=np.remainder(heading, 2 * math.pi), speed=speed, edge=edge.astype(np.int32),
            lane=lane.astype(np.int32), lane_pos=lane_pos, distance=dist, length=length, width=width,
            crashed=np.fromiter((v in crashed for v in ids), bool, n))
