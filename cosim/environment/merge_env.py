"""The on-ramp merge as a PettingZoo ParallelEnv over a real SUMO (libsumo); the why is in docs/env.md.

Contract: `env.cfg` is the config resolved on the env's net (`cosim.sumo.setting.Setting`). Agents
`av_0 .. av_{N-1}` act with the 5 meta-actions (`cosim.environment.control.Action`) and observe a stacked
VelocityMap (frames, channels, height, width), read-only views valid until the next step; rewards are the SVO
rewards of `cosim.environment.reward`, each weighted term in `infos[agent]["reward_terms"]`, each live agent's
`action_mask` in its infos (`action_masks()`). An agent terminates when its AV crashes or leaves the net; every
live agent is truncated at the horizon, when the merging vehicle crashes (or, with `sim.end_on_stuck`, is stuck
at the end of the acceleration lane) and, with `sim.on_collision: end`, at the first collision involving an AV
or the merging vehicle; with `remove` the colliders leave the road and the episode goes on. The last step's
infos carry `"episode"`, the `cosim.environment.tracker.EpisodeTracker` row (`env.tracker`) with the seed, whether
the merge failed and each collision's attribution (`cosim.environment.collisions`).
`step` is `cosim.environment.base.SumoEnv`'s template (act -> simulate -> observe -> reward -> end); a bad action
is an `ActionError` (`cosim.environment.control.checked_actions`), actions of agents already done are ignored;
`reset`/`step` after `close` raise RuntimeError.
With `sim.outputs` (or `reset(options={"outputs": True})`) an episode writes SUMO's tripinfo, induction-loop and
(`safety.ssm`) SSM files into its folder (`cosim.sumo.outputs.episode_folder`); `flush_outputs()` runs an episode
that ended early on to the horizon and parses them into `env.sumo_outputs[seed]`. With `sim.av_driver: sumo`
SUMO drives the AVs and actions are ignored.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cosim.config import Config
from cosim.environment.base import Step, SumoEnv
from cosim.environment.episode import EndCheck, episode_end, merge_status
from cosim.environment.reward import TERMS, step_utility, svo_rewards
from cosim.environment.tracker import EpisodeTracker
from cosim.environment.velocity_map import VelocityMapper, rasterize_road
from cosim.errors import SimulationError
from cosim.sumo.outputs import SumoOutputs, detector_site, episode_folder, episode_output_args, read_episode_outputs
from cosim.sumo.scenario import av_id, plan_episode, write_episode
from cosim.sumo.session import Gui
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER, Snapshot

log = logging.getLogger(__name__)


class MergeEnv(SumoEnv):
    metadata = {"name": "cosim_merge_v0", "render_modes": ["rgb_array"], "is_parallelizable": True,
                "render_fps": 10}
    ROUTE_FILE = "episode.rou.xml"

    def __init__(self, config: Config, render_mode: str | None = None, gui: Gui | None = None) -> None:
        super().__init__(config, render_mode, gui)
        config = self.cfg
        plan_episode(config, self.net, config.sim.seed)  # a placement this net makes impossible fails here, at once
        self.tracker = self.new_tracker()  # this episode's metrics, renewed at reset
        self.possible_agents = [av_id(i) for i in range(config.scenario.n_avs)]
        self.road_raster = rasterize_road(self.road.lane_shapes())
        self._spaces(VelocityMapper(config.observation, self.road_raster, len(self.possible_agents)))
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._phis = np.asarray(config.phis(), dtype=np.float64)
        self.max_steps = max(1, round(config.sim.horizon / config.sim.decision_period))
        self.detectors = detector_site(self.net, config.sim.detector_offset)
        self.sumo_outputs: dict[int, SumoOutputs] = {}  # episode seed -> its parsed SUMO outputs
        # [m] odometer of every vehicle at the end of the flow window (flush_outputs), to check SUMO's against
        self.window_distance: dict[str, float] = {}
        self._pending_outputs: tuple[int, Path] | None = None  # written, not yet complete
        self._merger_alt = False  # the running episode's merging vehicle drives the merger_alt type
        self._window_end = 0.0  # [s] simulation time of the horizon in the running episode
        # Collisions of these classes end the episode (the paper's rule).
        self._stop_on = frozenset({KIND_AV, KIND_MERGER}) if config.sim.on_collision == "end" else frozenset()

    def new_tracker(self, record: bool = False) -> EpisodeTracker:
        return EpisodeTracker(self.zone, self.chainage, record=record, cut_in_window=self.cfg.sim.cut_in_window,
                              hard_braking=self.cfg.safety.hard_braking, period=self.cfg.sim.decision_period)

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        seed = self._begin_reset(seed)
        plan = plan_episode(self.cfg, self.net, seed)
        write_episode(plan, self.cfg, self.net.desc, self.route_file)
        self._merger_alt = any(sp.alt for sp in plan.vehicles if sp.kind == KIND_MERGER)
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
        self._target = {a: float(snap.speed[r]) if r >= 0 else 0.0 for a, r in zip(self.possible_agents, rows,
                                                                                       strict=True)}
        self.tracker = self.new_tracker()
        self.tracker.observe(snap)
        self._window_end = snap.time + self.max_steps * self.cfg.steps_per_decision * self.cfg.sim.step_length
        self.mapper.reset()
        self.mapper.update(snap, rows)
        self._snap = snap
        obs = {a: self.mapper.observation(i) for i, a in enumerate(self.possible_agents)}
        masks = self._masks(snap, self.agents)
        return obs, {a: {"seed": seed, "action_mask": masks[a]} for a in self.agents}

    # -- step hooks (the template: cosim.environment.base) ------------------------------------------
    def _observe(self, acting: list[str], actions: Mapping[str, int]) -> Snapshot:
        snap = self.session.snapshot()
        self._rows = rows = snap.rows_of(self.possible_agents)
        self.mapper.update(snap, rows)
        self._status = status = merge_status(snap, self.zone, self.cfg.sim.stuck_speed, self.cfg.sim.stuck_distance)
        merged_before = self.tracker.merged_at is not None
        self.tracker.observe(snap, {a: actions[a] for a in acting} if self.session.drive_avs else None, status)
        self._merged_now = self.tracker.merged_at is not None and not merged_before
        self._snap = snap
        return snap

    def _reward(self, prev: Snapshot, snap: Snapshot, acting: list[str], lane_changed: dict[str, bool],
                invalid: dict[str, bool]) -> tuple[dict[str, float], dict[str, dict]]:
        n = len(self.possible_agents)
        changed_v, invalid_v = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        for a in acting:
            changed_v[self._index[a]], invalid_v[self._index[a]] = lane_changed[a], invalid[a]
        reward, terms, ego_u, social_u = self._utilities(prev, snap, self._rows, changed_v, invalid_v,
                                                         self._status.row, self._merged_now)
        # One conversion to Python floats each, not one per agent and term.
        by_agent, reward_l, ego_l, social_l = terms.T.tolist(), reward.tolist(), ego_u.tolist(), social_u.tolist()
        extra = {a: {"reward_terms": dict(zip(TERMS, by_agent[i], strict=True)), "ego_utility": ego_l[i],
                     "social_utility": social_l[i], "invalid_action": bool(invalid_v[i])}
                 for a, i in ((a, self._index[a]) for a in acting)}
        return {a: reward_l[self._index[a]] for a in acting}, extra

    def _end(self, snap: Snapshot, acting: list[str], rewards: dict[str, float], extra: dict[str, dict]) -> Step:
        status, merged = self._status, self.tracker.merged_at is not None
        ended_by = episode_end(EndCheck(snap, status, merged, self.tracker.steps, self.max_steps, self._stop_on,
                                        self.cfg.sim.end_on_stuck))
        cut = ended_by is not None
        masks = self._masks(snap, acting)
        obs, term, trunc, infos = {}, {}, {}, {}
        for a in acting:
            i = self._index[a]
            r = self._rows[i]
            gone = r < 0 or bool(snap.crashed[r])
            term[a] = gone
            trunc[a] = cut and not gone
            obs[a] = self.mapper.observation(i)
            infos[a] = {**extra[a], "merged": merged, "action_mask": masks[a]}
        self.agents = [a for a in acting if not (term[a] or trunc[a])]
        if self.cfg.sim.on_collision == "remove" and snap.crashed.any():
            self.session.remove([v for v, c in zip(snap.ids, snap.crashed, strict=True) if c])
        if not self.agents:
            # ended_by None: nothing cut the episode, every AV's own one ended (crashed or left the net).
            summary = self.episode_summary(snap, stuck=status.stuck, ended_by=ended_by or "agents_done")
            self.last_summary = summary
            for a in acting:
                infos[a]["episode"] = summary
        return obs, rewards, term, trunc, infos

    def _utilities(self, prev: Snapshot, snap: Snapshot, rows: np.ndarray, lane_changed: np.ndarray,
                 invalid: np.ndarray, merger_row: int, merged_now: bool
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(reward, terms, ego utility, social utility): each (N,) but terms, (len(TERMS), N) the weighted terms
        of each agent, 0 for an agent not on the road."""
        v_lane, v_invalid, v_merged = (np.zeros(len(snap), dtype=bool) for _ in range(3))
        present = rows >= 0
        v_lane[rows[present]] = lane_changed[present]
        v_invalid[rows[present]] = invalid[present]
        if merged_now:
            v_merged[merger_row] = True
        weighted = step_utility(prev, snap, v_lane, v_invalid, v_merged, self.cfg)
        utility = sum(weighted.values())
        observed = self.mapper.observed(snap, rows)
        reward, ego, social = svo_rewards(utility, observed, rows, merger_row, self._phis,
                                          mean=self.cfg.reward.social == "mean")
        terms = (np.where(present, np.array(list(weighted.values()))[:, np.maximum(rows, 0)], 0.0) if len(snap)
                 else np.zeros((len(TERMS), len(rows))))
        return reward, terms, ego, social

    # -- summaries and rendering --------------------------------------------------------------------
    def episode_summary(self, snap: Snapshot, stuck: bool, ended_by: str) -> dict[str, Any]:
        """Outcome of the episode for metrics: the tracker's row (length, time, crash, merge and time to merge,
        distances [m] and speeds [m/s] by class over every vehicle seen, ...), the seed, `merge_failed` (the
        merging vehicle got `stuck`) and `ended_by` (the `cosim.environment.episode.ENDINGS` name that ended it, or
        agents_done) and `merger_alt` (the merging vehicle drove the config's `merger_alt` type: a scenario that
        mixes merging drivers is read per driver). `snap` is the last snapshot, which the tracker has seen."""
        return {"seed": self.episode_seed, **self.tracker.row(), "merge_failed": stuck, "ended_by": ended_by,
                "merger_alt": self._merger_alt}

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

    def _closing(self) -> None:
        try:
            self._collect_outputs(None if self._snap is None else self._snap.time)
        except SimulationError as exc:  # closing must not fail on an episode SUMO did not finish writing
            log.warning("%s", exc)
