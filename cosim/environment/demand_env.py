"""The on-ramp merge under traffic demand, over minutes, as a PettingZoo ParallelEnv (`demand:` of the config).

Contract: the config is resolved on the net as in `MergeEnv`, then its demand (`cosim.sumo.demand`): each `reset(seed)`
plans the run's vehicles (exponential headways on every highway lane and the ramp, a share of the mainline ones
AVs, `warmup + window` seconds) and starts SUMO with the window's detectors (`cosim.sumo.flow_outputs`).
`possible_agents` names every AV a run can release, `av_0 .. av_{max_avs-1}` in order of departure, never reused;
an AV is an agent from the decision after it entered to the one at which it left the net (truncated, or
terminated with `demand.exit: terminated`) or crashed (terminated), and its
VelocityMap lives in one of `demand.slots` observation slots, the most present at once (more raise `ConfigError`
naming `demand.max_avs_present`). Agents act with the 5 meta-actions, every one each decision, and earn the SVO
reward of `cosim.environment.reward` (the merging vehicles count among the others where observed, each ramp
vehicle's merge term on the step it reaches a through lane). A collision takes the vehicles involved off the road
after its decision step (an AV in it terminates) and the run goes on. Between AVs, when none is present, the env
simulates on by itself, so `agents` is empty only once the run reaches its horizon, where every live agent is
truncated. Then SUMO is closed, its outputs parsed (`flow_outputs`) and, with the run's record
(`cosim.environment.flow_record.FlowRecorder`, also in `record.npz`), kept; `last_summary` holds the run's summary
with its window's flow metrics (`cosim.environment.flow_metrics.window_metrics`; the last step's infos carry it
too). A terminated agent's last observation is zeros (its slot may serve an AV that entered in the same step), a
truncated one's its map at the horizon, or, one that left the net, the map it last acted on (the net holds no
later one), to bootstrap from. `agent_slot(agent)` is a live agent's slot, `slot_names` the slots in order.
With `sim.av_driver: sumo` SUMO drives the AVs (the all-human baseline) and actions are ignored. Live agents'
infos carry `action_mask` as the episode env's do (`action_masks()`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cosim.config import Config
from cosim.environment.base import Step, SumoEnv
from cosim.environment.flow_metrics import window_metrics
from cosim.environment.flow_record import FlowRecorder
from cosim.environment.reward import step_utility, svo_rewards
from cosim.environment.velocity_map import VelocityMapper, rasterize_road
from cosim.errors import ConfigError
from cosim.files import atomic_path
from cosim.sumo.demand import plan_demand, write_demand
from cosim.sumo.flow_outputs import FlowOutputs, flow_output_args, flow_sites, read_flow_outputs
from cosim.sumo.scenario import av_id, kind_of
from cosim.sumo.session import Gui
from cosim.sumo.snapshot import KIND_AV, KIND_MERGER, Snapshot


class DemandEnv(SumoEnv):
    metadata = {"name": "cosim_merge_demand_v0", "render_modes": [], "is_parallelizable": True}
    ROUTE_FILE = "demand.rou.xml"

    def __init__(self, config: Config, render_mode: str | None = None, gui: Gui | None = None) -> None:
        super().__init__(config, render_mode, gui)
        config = self.cfg
        if isinstance(config.reward.phi, tuple):
            raise ConfigError("reward.phi: one angle for every AV in demand mode (AVs come and go), got a list")
        assert self.setting.demand is not None  # a demand config: the factory's choice
        self.demand = self.setting.demand
        self.sites = flow_sites(self.net, config.demand.influence_area)
        self.possible_agents = [av_id(i) for i in range(self.demand.max_avs)]
        self._spaces(VelocityMapper(config.observation, rasterize_road(self.road.lane_shapes()),
                                    max(self.demand.slots, 1)))
        self.max_steps = max(1, round(self.demand.horizon / config.sim.decision_period))
        self._phi = float(config.reward.phi)
        # Conflicts where an evaluation writes SUMO's outputs; training's runs go without the SSM device's cost.
        self._safety = config.safety if config.sim.outputs and config.safety.ssm else None
        self.last_outputs: FlowOutputs | None = None  # SUMO's outputs of the last finished run
        self.last_record: dict[str, np.ndarray] | None = None  # ... and its record
        self.sumo_outputs: dict[int, Any] = {}  # the episode envs' per-episode outputs: none here

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        seed = self._begin_reset(seed)
        write_demand(plan_demand(self.cfg, self.net, self.demand, seed), self.cfg, self.net.desc, self.route_file)
        root = Path(self.cfg.sim.output_dir) if self.cfg.sim.output_dir else self._tmp / "outputs"
        self.out_dir = root / f"run_{seed}"
        d = self.demand
        self.session.load(self.route_file, seed, flow_output_args(self.out_dir, self.sites, d.warmup, d.horizon,
                                                                   self.cfg.demand.interval, self._safety))
        self.recorder = FlowRecorder(self.zone, self.chainage, (d.warmup, d.horizon))
        self.steps, self.slot, self.gone = 0, {}, set()
        self._target: dict[str, float] = {}  # [m/s] each AV's target speed
        self._merged: set[str] = set()
        self.agents = []
        self.mapper.reset()
        self.last_outputs = self.last_record = self.last_summary = None
        snap = self.session.snapshot()
        self.recorder.observe(snap, self.session.pending())
        self._snap = snap
        self._admit(snap)
        self._update_maps(snap)
        infos: dict[str, dict] = {a: {"seed": seed} for a in self.agents}
        if not self.agents:
            self._idle_until_agents(infos)
        if self.steps >= self.max_steps:  # no AV in the whole run
            self._finish(infos)
        self._add_masks(infos)
        return {a: self._obs(a) for a in self.agents}, infos

    # -- step hooks (the template: cosim.environment.base) ------------------------------------------
    def _observe(self, acting: list[str], actions: Mapping[str, int]) -> Snapshot:
        self.steps += 1
        snap = self.session.snapshot()
        self.recorder.observe(snap, self.session.pending())
        # A ramp vehicle's merge counts once, on the step it reaches a through lane, whether or not an AV was there.
        through = self.zone.on_through_lane(snap.edge, snap.lane)
        self._merged_now = (snap.kind == KIND_MERGER) & through & ~snap.crashed & ~np.isin(snap.ids, list(self._merged))
        self._merged.update(snap.ids[i] for i in np.flatnonzero(self._merged_now))
        crashed = [snap.ids[i] for i in np.flatnonzero(snap.crashed)]
        if crashed:  # off the road after the step: the run goes on (counted by the recorder)
            self.session.remove(sorted(crashed))
        self._snap = snap
        return snap

    def _end(self, snap: Snapshot, acting: list[str], rewards: dict[str, float], extra: dict[str, dict]) -> Step:
        crashed = {snap.ids[i] for i in np.flatnonzero(snap.crashed)}
        rew, term, trunc, infos = {}, {}, {}, {}
        at_end = self.steps >= self.max_steps
        truncate_exit = self.cfg.demand.exit == "truncated"
        final: dict[str, np.ndarray] = {}  # the observations truncated agents bootstrap from
        for a in acting:
            out = snap.row_of(a) < 0
            term[a] = a in crashed or (out and not truncate_exit)
            trunc[a] = not term[a] and (at_end or out)
            if out and trunc[a]:  # maps not yet updated: the one it acted on (a copy: its slot moves on)
                final[a] = self._obs(a).copy()
            rew[a] = rewards.get(a, 0.0)
            infos[a] = {"crashed": a in crashed}
        live = [a for a in acting if not (term[a] or trunc[a])]
        if at_end:  # every agent still in its slot: the truncated ones' last observations, to bootstrap from
            self._update_maps(snap)
            final.update({a: self._obs(a) for a in acting if trunc[a] and a not in final})
        for a in acting:
            if term[a] or trunc[a]:
                self._release(a)
        new = [] if at_end else self._admit(snap)
        self.agents = live + new
        if not at_end:
            self._update_maps(snap)
        for a in new:
            rew[a], term[a], trunc[a], infos[a] = 0.0, False, False, {}
        if not self.agents and not at_end:
            self._idle_until_agents(infos, rew, term, trunc)
        if self.steps >= self.max_steps and self.last_summary is None:
            self._finish(infos)
        obs = {a: self._obs(a) for a in set(acting) | set(self.agents)}
        obs.update(final)
        self._add_masks(infos)
        return obs, rew, term, trunc, infos

    def _add_masks(self, infos: dict[str, dict]) -> None:
        for a, mask in self.action_masks().items():
            infos.setdefault(a, {})["action_mask"] = mask

    def _reward(self, prev: Snapshot, snap: Snapshot, acting: list[str], lane_changed: dict[str, bool],
                invalid: dict[str, bool]) -> tuple[dict[str, float], dict[str, dict]]:
        v_lane, v_invalid = np.zeros(len(snap), bool), np.zeros(len(snap), bool)
        for a in acting:
            r = snap.row_of(a)
            if r >= 0:
                v_lane[r], v_invalid[r] = lane_changed[a], invalid[a]
        utility = sum(step_utility(prev, snap, v_lane, v_invalid, self._merged_now, self.cfg).values())
        rows = snap.rows_of(acting)
        observed = np.zeros((len(acting), len(snap)), bool)
        slots = np.array([self.slot.get(a, -1) for a in acting], dtype=np.int64)
        if len(snap):
            full = np.full(self.mapper.n_agents, -1)
            have = slots >= 0
            full[slots[have]] = rows[have]
            observed[have] = self.mapper.observed(snap, full)[slots[have]]
        reward, _, _ = svo_rewards(utility, observed, rows, -1, np.full(len(acting), self._phi),
                                   mean=self.cfg.reward.social == "mean")
        return {a: float(r) for a, r in zip(acting, reward, strict=True)}, {}

    # -- agents and their observation slots ---------------------------------------------------------
    def _admit(self, snap: Snapshot) -> list[str]:
        """AVs in the net that are no agents yet become agents, each in a free observation slot."""
        new = [v for v in snap.ids if kind_of(v) == KIND_AV and v not in self.slot and v not in self.gone]
        free = sorted(set(range(self.mapper.n_agents)) - set(self.slot.values()))
        if len(new) > len(free):
            raise ConfigError(f"demand.max_avs_present: {len(self.slot) + len(new)} AVs present at once at t = "
                              f"{snap.time:.0f} s, more than its {self.mapper.n_agents} observation slots; raise it")
        for a, k in zip(new, free, strict=False):
            self.slot[a] = k
            self.mapper.clear(k)  # a slot another AV held: none of its frames in this one's stack
            self._target[a] = float(snap.speed[snap.row_of(a)])
        return new

    @property
    def slot_names(self) -> tuple[str, ...]:
        """The observation slots, in order: what a rollout worker indexes agents by (`agent_slot`)."""
        return tuple(f"slot_{k}" for k in range(self.mapper.n_agents))

    def agent_slot(self, agent: str) -> int:
        """The observation slot of a live agent (KeyError for one that is not)."""
        return self.slot[agent]

    def _release(self, agent: str) -> None:
        self.slot.pop(agent, None)
        self._target.pop(agent, None)
        self.gone.add(agent)

    def _update_maps(self, snap: Snapshot) -> None:
        rows = np.full(self.mapper.n_agents, -1)
        for a, k in self.slot.items():
            rows[k] = snap.row_of(a)
        self.mapper.update(snap, rows)

    def _obs(self, agent: str) -> np.ndarray:
        k = self.slot.get(agent)
        return self.mapper.observation(k) if k is not None else np.zeros(self.mapper.shape, self.mapper.dtype)

    def _idle_until_agents(self, infos: dict, rew: dict | None = None, term: dict | None = None,
                           trunc: dict | None = None) -> None:
        """No AV present: simulate on until one enters (it becomes an agent) or the horizon."""
        while not self.agents and self.steps < self.max_steps:
            self._simulate([])
            snap = self._observe([], {})
            if self.steps < self.max_steps:
                self.agents = self._admit(snap)
            self._update_maps(snap)
        for a in self.agents:
            infos[a] = {}
            if rew is not None:
                rew[a], term[a], trunc[a] = 0.0, False, False

    def _finish(self, infos: dict) -> None:
        """The horizon: SUMO closes its outputs; parse them, keep the record, and summarise the run."""
        self.session.end_simulation()
        d = self.demand
        self.last_outputs = read_flow_outputs(self.out_dir, d.warmup, d.horizon, end=self._snap.time,
                                              ssm=self._safety is not None)
        self.last_record = {**self.recorder.arrays(), "exit_lanes": np.asarray(len(self.sites.exit_lanes)),
                            "area_ids": np.asarray([a.did for a in self.sites.influence], dtype=str),
                            "area_lengths": np.asarray([a.length for a in self.sites.influence])}
        with atomic_path(self.out_dir / "record.npz") as tmp:
            np.savez_compressed(tmp, **self.last_record)
        desc = self.net.desc
        after = desc.highway[desc.highway.index(desc.merge_edge) + 1]
        flow = window_metrics(self.last_outputs, self.last_record, d, self.sites,
                              lanes_after=len(self.net.through_lanes(after)),
                              vehicle_gap=self.cfg.merger.length + self.cfg.merger.min_gap,
                              interval=self.cfg.demand.interval, safety=self._safety)
        self.last_summary = {"seed": self.episode_seed, "length": self.steps, "avs_released": len(self.gone),
                             "collisions": len(self.recorder.collisions), "out_dir": str(self.out_dir), **flow}
        for info in infos.values():
            info["episode"] = self.last_summary
