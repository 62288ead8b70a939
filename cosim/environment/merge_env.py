"""The on-ramp merge as a PettingZoo ParallelEnv over a real SUMO (libsumo).

Contract: the config is resolved on the env's net first (`cosim.sumo.resolve`: net-relative speeds, lengths
and counts in absolute units, values the net cannot take capped with a warning naming the key); `env.cfg` is
that resolved config. Agents `av_0 .. av_{N-1}` drive with the paper's 5 meta-actions
(`cosim.environment.control.Action`) and observe a stacked VelocityMap (frames, channels, height, width);
rewards are the SVO rewards of `cosim.environment.reward`, with every weighted term in
`infos[agent]["reward_terms"]`. An agent terminates when its AV crashes or leaves the net. The episode is cut
(every other live agent truncated) at the horizon, when the merging vehicle crashes (or, with
`sim.end_on_stuck`, gets stuck at the end of the acceleration lane: by default it waits there to the
horizon), and, with
`sim.on_collision: end` (the paper's rule), at the SUMO step of the first collision that involves an AV or
the merging vehicle: the other AVs' own driving did not end there, so a learner bootstraps, and an
egoistic AV gains nothing from keeping the episode alive. With `on_collision: remove` the colliders are
taken off the road after the decision step and the episode goes on. Every collision is attributed (kind,
fault, cause: `cosim.environment.collisions`) in the episode summary.
On the last step every agent's info carries `"episode"`, the episode's summary: the row of the
`cosim.environment.tracker.EpisodeTracker` the env feeds every snapshot (`env.tracker`), with the seed and whether the
merge failed. Observations are read-only views valid until the next step. Each live agent's infos carry
`action_mask` at reset and every step (`action_masks()`: `cosim.environment.control.action_mask` of its lane, edge
and target speed); the env takes any action whether or not anyone reads it.

`step` is a template of small hooks: act -> simulate -> snapshot -> observe -> reward -> end. It takes an action for
every live agent (`env.agents`): an unknown agent, a missing action or one that is not an integer in range (`Action`;
numpy integers are fine) is an `ActionError` (a `CosimError` and a `ValueError`) naming the agent and the allowed
actions; actions of agents already done are ignored. A closed env stays closed: `reset` and `step` after `close`
raise a RuntimeError that says so.

With `sim.outputs`, or for one episode with `reset(options={"outputs": True})` (training's validation episodes),
each episode writes SUMO's tripinfo and induction-loop files into its own folder
(`cosim.sumo.outputs.episode_folder`), over a window that is the same for every episode: `flush_outputs()` runs
an episode that ended early on to the horizon (wrecks stay where they crashed, the AVs drive as SUMO's
humans), completes the files and parses them into `env.sumo_outputs[seed]` (`cosim.sumo.outputs.SumoOutputs`);
a reset or close without it completes them at the time the episode ended. With `safety.ssm` (the default) SUMO's
SSM device rides along and its conflicts up to the episode's end (not the run-out's, when SUMO drives the AVs and
the wrecks stand) are counted into the outputs (`cosim.sumo.outputs.conflict_counts`). With `sim.av_driver: sumo` the
agents' actions are ignored and SUMO's own models drive the AVs (the all-human baseline).
"""

from __future__ import annotations

import copy
import logging
import reprlib
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from cosim.config import SEED_MAX, AVConfig, Config, check_seed, load_config
from cosim.environment.control import N_ACTIONS, Action, action_mask, decide
from cosim.environment.episode import EndCheck, MergeZone, episode_end, merge_status
from cosim.environment.reward import StepChange, svo_rewards, utility_terms, weighted_utility
from cosim.environment.tracker import EpisodeTracker
from cosim.environment.velocity_map import VelocityMapper, rasterize_road
from cosim.errors import CosimError, SimulationError
from cosim.sumo.outputs import SumoOutputs, detector_site, episode_folder, episode_output_args, read_episode_outputs
from cosim.sumo.resolve import on_net
from cosim.sumo.scenario import av_id, kind_of, plan_episode, write_episode
from cosim.sumo.session import Gui, SumoSession
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER, Snapshot
from cosim.workers import run_folder

log = logging.getLogger(__name__)

ALLOWED_ACTIONS = f"an integer in 0..{N_ACTIONS - 1} ({', '.join(f'{int(a)} {a.name}' for a in Action)})"


class ActionError(CosimError, ValueError):
    """`MergeEnv.step` got something that is not an action of a live agent (a ValueError, as gymnasium's
    callers expect of a bad action)."""


def checked_action(agent: str, value: Any) -> int:
    """`value` as an action index, or `ActionError` naming `agent` and the allowed actions. Python ints (and
    `Action` members) and numpy integers, 0-d arrays included (what SB3 and SuperSuit hand over), are
    actions; floats, strings, bools, None and arrays of a shape are not, as in gymnasium's `Discrete`."""
    if type(value) is int and 0 <= value < N_ACTIONS:  # the trainer's and the evaluation's own actions
        return value
    if isinstance(value, np.ndarray):
        integral = value.shape == () and value.dtype.kind in "iu"
    else:  # a bool is an int to Python, not an action
        integral = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if integral and 0 <= int(value) < N_ACTIONS:
        return int(value)
    raise ActionError(f"step(): agent {agent!r}: action {reprlib.repr(value)} ({type(value).__name__}) is not "
                      f"allowed; expected {ALLOWED_ACTIONS}")


def checked_actions(actions: Mapping[str, Any], live: Sequence[str], possible: Sequence[str]) -> dict[str, int]:
    """Every live agent's action as an int, or `ActionError`: for actions that are not a dict, a live agent without
    one, an agent the env does not have (not in `possible`), or a value that is no action (`checked_action`). The
    actions of agents that are done are dropped unchecked: PettingZoo's AEC form steps them with None, SuperSuit's
    black death and a loop over the last observations hand them over too."""
    if not isinstance(actions, Mapping):
        raise ActionError(f"step(): expected a dict of agent -> action, got {type(actions).__name__}")
    missing = [a for a in live if a not in actions]
    if missing:
        raise ActionError(f"step(): no action for live agents {missing}; each takes {ALLOWED_ACTIONS}")
    if len(actions) > len(live):
        known = set(possible)
        unknown = [a for a in actions if a not in known]
        if unknown:
            shown = list(possible) if len(possible) <= 8 else f"{possible[0]} .. {possible[-1]}"
            raise ActionError(f"step(): unknown agent {unknown[0]!r}; this env's agents are {shown} (live now: "
                              f"{list(live)}), each taking {ALLOWED_ACTIONS}")
    return {a: checked_action(a, actions[a]) for a in live}


def agent_masks(snap: Snapshot, zone: MergeZone, agents: Sequence[str], targets: np.ndarray,
                av: AVConfig) -> dict[str, np.ndarray]:
    """Agent -> its action mask in `snap` (`cosim.environment.control.action_mask`), `targets` (len(agents),) their
    target speeds [m/s]; an agent not on the road (none live is) may only idle."""
    rows = snap.rows_of(agents)
    present = rows >= 0
    safe = np.maximum(rows, 0)
    # Edge -1 indexes the zone's extra row, which has no usable lane.
    edge = np.where(present, snap.edge[safe] if len(snap) else -1, -1)
    lane = np.where(present, snap.lane[safe] if len(snap) else 0, 0)
    mask = action_mask(lane, zone.through[edge], np.asarray(targets, dtype=np.float64), av)
    mask[~present] = np.eye(N_ACTIONS, dtype=np.int8)[Action.IDLE]
    return dict(zip(agents, mask, strict=True))


class MergeEnv(ParallelEnv):
    metadata = {"name": "cosim_merge_v0", "render_modes": ["rgb_array"], "is_parallelizable": True,
                "render_fps": 10}

    def __init__(self, config: Config, render_mode: str | None = None, gui: Gui | None = None) -> None:
        """`gui`: run sumo-gui over TraCI instead of libsumo, for people to watch (`cosim replay --gui`)."""
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        # Everything below reads the config resolved on this net: net-relative keys in absolute units.
        self.net, resolved = on_net(config)
        self.cfg = config = resolved.config
        self.resolution_notes = resolved.notes
        plan_episode(config, self.net, config.sim.seed)  # a placement this net makes impossible fails here, at once
        self.road, self.chainage = self.net.road, self.net.chainage
        self.zone = MergeZone.from_net(self.net)
        self.tracker = self.new_tracker()  # this episode's metrics, renewed at reset
        self.possible_agents = [av_id(i) for i in range(config.scenario.n_avs)]
        self.agents: list[str] = []
        self.road_raster = rasterize_road(self.road.lane_shapes())
        self.mapper = VelocityMapper(config.observation, self.road_raster, len(self.possible_agents))
        self._obs_space = gymnasium.spaces.Box(low=0, high=self.mapper.high, shape=self.mapper.shape,
                                               dtype=self.mapper.dtype)
        self._act_space = gymnasium.spaces.Discrete(N_ACTIONS)
        self._phis = np.asarray(config.phis(), dtype=np.float64)
        self.max_steps = max(1, round(config.sim.horizon / config.sim.decision_period))
        self._next_seed = config.sim.seed
        self._tmp: Path | None = None  # this env's temporary folder, made at the first reset, removed at close
        self.session = SumoSession(Path(config.net.file), config.sim.step_length, self.road.index_of, kind_of,
                                   config.sim.sumo_args, config.sim.collision_mingap_factor,
                                   drive_avs=config.sim.av_driver == "env", gui=gui, shield=config.av.shield)
        self.detectors = detector_site(self.net, config.sim.detector_offset)
        self.sumo_outputs: dict[int, SumoOutputs] = {}  # episode seed -> its parsed SUMO outputs
        # [m] odometer of every vehicle at the end of the flow window (flush_outputs), to check SUMO's against
        self.window_distance: dict[str, float] = {}
        self._pending_outputs: tuple[int, Path] | None = None  # written, not yet complete
        self._snap: Snapshot | None = None
        self._window_end = 0.0  # [s] simulation time of the horizon in the running episode
        # Collisions of these classes end the episode (the paper's rule).
        self._stop_on = frozenset({KIND_AV, KIND_MERGER}) if config.sim.on_collision == "end" else frozenset()
        self._closed = False  # close() released the process's SUMO slot: this env cannot run again
        self.last_summary: dict[str, Any] | None = None  # the summary of the episode that ended last

    def new_tracker(self, record: bool = False) -> EpisodeTracker:
        return EpisodeTracker(self.zone, self.chainage, record=record, cut_in_window=self.cfg.sim.cut_in_window,
                              hard_braking=self.cfg.safety.hard_braking, period=self.cfg.sim.decision_period)

    # -- PettingZoo API -----------------------------------------------------------------------------
    # One space object for all agents, as PettingZoo asks (no functools.cache: it would keep the env alive).
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Discrete:
        return self._act_space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if self._closed:  # restarting would take a SUMO slot that another env of this process may hold now
            raise RuntimeError("reset() after close(): this env is closed; make a new one (cosim.parallel_env)")
        # A plain int (numpy's would reach the summary, which json refuses) in SUMO's range, or `SeedError`
        # (a ValueError) naming `seed`; None takes the next seed (sim.seed first).
        seed = check_seed("seed", self._next_seed if seed is None else seed)
        self._next_seed = (seed + 1) % (SEED_MAX + 1)  # past SUMO's last seed, the sequence starts again at 0
        self.episode_seed = seed
        if self._tmp is None:
            self._tmp = Path(tempfile.mkdtemp(prefix="env_", dir=run_folder()))  # named after its owner: a kill -9
            # leaves nothing that the next run does not remove
        write_episode(plan_episode(self.cfg, self.net, seed), self.cfg, self.net.desc, self.route_file)
        end_time = None if self._snap is None else self._snap.time
        extra: list[str] = []
        outputs = self.cfg.sim.outputs or bool((options or {}).get("outputs"))
        if outputs:
            out_root = Path(self.cfg.sim.output_dir) if self.cfg.sim.output_dir else self._tmp / "outputs"
            folder = episode_folder(out_root, seed, busy=None if self._pending_outputs is None
                                    else self._pending_outputs[1])
            extra = episode_output_args(folder, self.detectors, safety=self.cfg.safety)
        self.session.load(self.route_file, seed, extra)
        self._collect_outputs(end_time)  # the reload completed the previous episode's files
        if outputs:
            self._pending_outputs = (seed, folder)
        self.agents = list(self.possible_agents)
        self.last_summary = None
        snap = self.session.snapshot()
        rows = snap.rows_of(self.possible_agents)
        self._target = np.where(rows >= 0, snap.speed[np.maximum(rows, 0)], 0.0)
        self.tracker = self.new_tracker()
        self.tracker.observe(snap)
        self._window_end = snap.time + self.max_steps * self.cfg.steps_per_decision * self.cfg.sim.step_length
        self.mapper.reset()
        self.mapper.update(snap, rows)
        self._snap = snap
        obs = {a: self.mapper.observation(i) for i, a in enumerate(self.possible_agents)}
        masks = self._masks(snap, self.agents)
        return obs, {a: {"seed": seed, "action_mask": masks[a]} for a in self.agents}

    def step(self, actions: Mapping[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        if self._snap is None:
            raise RuntimeError("step() after close(): this env is closed; make a new one (cosim.parallel_env)"
                               if self._closed else "step() before reset()")
        acting = list(self.agents)
        actions = self._checked_actions(actions)
        prev = self._snap
        idx = np.array([self.possible_agents.index(a) for a in acting], dtype=np.int64)
        lane_changed, invalid = self._act(prev, acting, idx, actions)
        self._simulate(acting, idx)
        snap = self.session.snapshot()
        rows = snap.rows_of(self.possible_agents)
        self.mapper.update(snap, rows)
        status = merge_status(snap, self.zone, self.cfg.sim.stuck_speed, self.cfg.sim.stuck_distance)
        merged_before = self.tracker.merged_at is not None
        self.tracker.observe(snap, {a: actions[a] for a in acting} if self.session.drive_avs else None, status)
        merged = self.tracker.merged_at is not None
        rewards, terms, ego_u, social_u = self._rewards(prev, snap, rows, lane_changed, invalid, status.row,
                                                        merged and not merged_before)
        ended_by = episode_end(EndCheck(snap, status, merged, self.tracker.steps, self.max_steps, self._stop_on,
                                        self.cfg.sim.end_on_stuck))
        cut = ended_by is not None
        masks = self._masks(snap, acting)
        obs, rew, term, trunc, infos = {}, {}, {}, {}, {}
        for a in acting:
            i = self.possible_agents.index(a)
            r = rows[i]
            gone = r < 0 or bool(snap.crashed[r])
            term[a] = gone
            trunc[a] = cut and not gone
            obs[a] = self.mapper.observation(i)
            rew[a] = float(rewards[i])
            infos[a] = {"reward_terms": {k: float(v[i]) for k, v in terms.items()},
                        "ego_utility": float(ego_u[i]), "social_utility": float(social_u[i]),
                        "invalid_action": bool(invalid[i]), "merged": merged, "action_mask": masks[a]}
        self.agents = [a for a in acting if not (term[a] or trunc[a])]
        if self.cfg.sim.on_collision == "remove" and snap.crashed.any():
            self.session.remove([v for v, c in zip(snap.ids, snap.crashed, strict=True) if c])
        self._snap = snap
        if not self.agents:
            # ended_by None: nothing cut the episode, every AV's own one ended (crashed or left the net).
            summary = self.episode_summary(snap, stuck=status.stuck, ended_by=ended_by or "agents_done")
            self.last_summary = summary
            for a in acting:
                infos[a]["episode"] = summary
        return obs, rew, term, trunc, infos

    @property
    def route_file(self) -> Path:
        """The SUMO route file of the episode (vehicles, vTypes, routes), rewritten at every reset."""
        if self._tmp is None:
            raise RuntimeError("no route file before reset()")
        return self._tmp / "episode.rou.xml"

    @property
    def snapshot(self) -> Snapshot:
        """The state of every vehicle after the last reset/step (for baselines, metrics and tools)."""
        if self._snap is None:
            raise RuntimeError("no snapshot before reset()")
        return self._snap

    def action_masks(self) -> dict[str, np.ndarray]:
        """Each live agent's action mask after the last reset/step, as in its infos["action_mask"]: (N_ACTIONS,)
        int8, 1 where the action would change something (`cosim.environment.control.action_mask`)."""
        return self._masks(self.snapshot, self.agents)

    def _masks(self, snap: Snapshot, agents: list[str]) -> dict[str, np.ndarray]:
        idx = [self.possible_agents.index(a) for a in agents]
        return agent_masks(snap, self.zone, agents, self._target[idx], self.cfg.av)

    def _checked_actions(self, actions: Mapping[str, Any]) -> dict[str, int]:
        return checked_actions(actions, self.agents, self.possible_agents)

    # -- step hooks ---------------------------------------------------------------------------------
    def _act(self, prev: Snapshot, acting: list[str], idx: np.ndarray,
             actions: Mapping[str, int]) -> tuple[np.ndarray, np.ndarray]:
        """Apply meta-actions; returns (lane_changed, invalid), each (N,) over possible agents."""
        n = len(self.possible_agents)
        lane_changed, invalid = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        rows = prev.rows_of(acting)
        present = rows >= 0
        if not present.any() or not self.session.drive_avs:
            return lane_changed, invalid
        idx, rows = idx[present], rows[present]
        acts = np.array([int(actions[a]) for a, p in zip(acting, present, strict=True) if p])
        # AVs may use the highway's through lanes only, never the acceleration lane.
        d = decide(acts, prev.lane[rows], self.zone.through[prev.edge[rows]], self._target[idx], self.cfg.av)
        self._target[idx] = d.target_speed
        for i, change in zip(idx, d.lane_change, strict=True):
            if change:
                self.session.change_lane(self.possible_agents[i], int(change))
        lane_changed[idx] = d.lane_change != 0
        invalid[idx] = d.invalid
        return lane_changed, invalid

    def _simulate(self, acting: list[str], idx: np.ndarray) -> None:
        av = self.cfg.av
        targets = {a: float(self._target[i]) for a, i in zip(acting, idx, strict=True)}
        if not self.session.drive_avs:
            targets = {}
        self.session.advance(self.cfg.steps_per_decision, targets, av.accel, av.decel, av.max_speed, self._stop_on)

    def _rewards(self, prev: Snapshot, snap: Snapshot, rows: np.ndarray, lane_changed: np.ndarray,
                 invalid: np.ndarray, merger_row: int, merged_now: bool
                 ) -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
        period = self.cfg.sim.decision_period
        # Progress and speed change since the previous snapshot; a vehicle inserted since starts at 0 m.
        before = prev.rows_of(snap.ids)
        seen = before >= 0
        prev_d, prev_v = np.zeros(len(snap)), snap.speed.copy()
        prev_d[seen], prev_v[seen] = prev.distance[before[seen]], prev.speed[before[seen]]
        v_lane, v_invalid, v_merged = (np.zeros(len(snap), dtype=bool) for _ in range(3))
        present = rows >= 0
        v_lane[rows[present]] = lane_changed[present]
        v_invalid[rows[present]] = invalid[present]
        if merged_now:
            v_merged[merger_row] = True
        raw = utility_terms(StepChange(snap.distance - prev_d, snap.speed - prev_v, v_lane, v_invalid, snap.crashed,
                                       v_merged, self.cfg.av.max_speed, self.cfg.av.accel, period))
        weighted = weighted_utility(raw, self.cfg.reward)
        utility = sum(weighted.values())
        observed = self.mapper.observed(snap, rows)
        reward, ego, social = svo_rewards(utility, observed, rows, merger_row, self._phis)
        safe = np.maximum(rows, 0)
        terms = {k: np.where(present, v[safe], 0.0) if len(snap) else np.zeros(len(rows))
                 for k, v in weighted.items()}
        return reward, terms, ego, social

    # -- summaries and rendering --------------------------------------------------------------------
    def episode_summary(self, snap: Snapshot, stuck: bool, ended_by: str) -> dict[str, Any]:
        """Outcome of the episode for metrics: the tracker's row (length, time, crash, merge and time to merge,
        distances [m] and speeds [m/s] by class over every vehicle seen, ...), the seed, `merge_failed` (the
        merging vehicle got `stuck`) and `ended_by` (the `cosim.environment.episode.ENDINGS` name that ended it, or
        agents_done). `snap` is the last snapshot, which the tracker has seen."""
        return {"seed": self.episode_seed, **self.tracker.row(), "merge_failed": stuck, "ended_by": ended_by}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._snap is None:
            return None
        from cosim.environment.render import render_scene

        live = [self.possible_agents.index(a) for a in self.agents]
        return render_scene(self.road_raster, self._snap, self.mapper, self.cfg.observation, live[0] if live else 0)

    def flush_outputs(self) -> None:
        """Run the last episode on to its horizon if it ended early, then complete and parse its SUMO outputs
        (SUMO is restarted at the next reset)."""
        if self._pending_outputs is not None and self._snap is not None:
            window = self.tracker
            if self._snap.time < self._window_end - 0.5 * self.cfg.sim.step_length:
                self.session.run_out(self._window_end)
                window = copy.deepcopy(self.tracker)  # the episode's own metrics stop where it ended
                window.observe(self.session.snapshot())
            self.window_distance = window.distance
            self.session.end_simulation()
            self._collect_outputs(self._window_end)

    def _collect_outputs(self, end_time: float | None) -> None:
        if self._pending_outputs is None or end_time is None:
            return
        seed, folder = self._pending_outputs
        self._pending_outputs = None
        # Conflicts while the agents drove, up to the episode's end (the tracker's last time), not those of the run-out.
        self.sumo_outputs[seed] = read_episode_outputs(folder, end_time, self.cfg.safety, until=self.tracker.time)

    def close(self) -> None:
        self.session.close()
        try:
            self._collect_outputs(None if self._snap is None else self._snap.time)
        except SimulationError as exc:  # closing must not fail on an episode SUMO did not finish writing
            log.warning("%s", exc)
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        self._snap = None
        self._closed = True

    def __del__(self) -> None:  # an env dropped without close() must not keep the process's SUMO slot
        session = getattr(self, "session", None)
        if session is not None:
            session.close()
        tmp = getattr(self, "_tmp", None)
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def parallel_env(config: str | Path | Mapping[str, Any] | Config | None = None,
                 overrides: Mapping[str, Any] | list[str] | None = None,
                 render_mode: str | None = None) -> ParallelEnv:
    """The PettingZoo way: `cosim.parallel_env(config="configs/default.yaml", overrides={"reward.phi": 0.785})`;
    without a config, the built-in defaults on the bundled merge net. A config with `demand.enabled` gives the
    merge under traffic demand (`cosim.environment.demand_env.DemandEnv`), else the episode env."""
    cfg = load_config(config, overrides)
    if cfg.demand.enabled:
        from cosim.environment.demand_env import DemandEnv  # it builds on this module

        return DemandEnv(cfg, render_mode=render_mode)
    return MergeEnv(cfg, render_mode=render_mode)


def env(config: str | Path | Mapping[str, Any] | Config | None = None,
        overrides: Mapping[str, Any] | list[str] | None = None, render_mode: str | None = None) -> AECEnv:
    """The same env in PettingZoo's AEC form (agents act in turn; SUMO advances once all have acted), for
    libraries that expect it: `cosim.env(config=..., overrides=...)`."""
    return parallel_to_aec(parallel_env(config, overrides, render_mode))
