"""What the episode env and the demand env share: one SUMO, one resolved config, and `step` as a template of hooks.

Contract: `SumoEnv(config, render_mode, gui)` resolves the config on its net once (`setting`,
`cosim.sumo.setting.Setting`, and from it `cfg`, `net`, `resolution_notes`; `zone`) and holds the SUMO session; a
subclass sets `possible_agents`, its `mapper` (`_spaces` makes the observation space from it), `max_steps` and
`ROUTE_FILE`, and writes its own `reset`, which starts with `_begin_reset(seed)` (the closed-env guard, the seed checked
or the next of the sequence, the temporary folder). `step(actions)` is the template, as HighwayEnv's `AbstractEnv.step`
is: `checked_actions` (an `ActionError` for anything but an action of every live agent) -> `_act` (meta-actions into
target speeds and lane changes, shared) -> `_simulate` (one decision period, shared) -> `_observe` -> `_reward` ->
`_end`; the last three are the subclass's. Target speeds are kept per agent name (`_target`); `action_masks()` reads
them. `close()` releases the process's SUMO slot and the temporary folder; a closed env stays closed (`reset` and `step`
raise a RuntimeError that says so).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from cosim.config import SEED_MAX, Config, check_seed
from cosim.environment.control import N_ACTIONS, agent_masks, checked_actions, decide
from cosim.environment.episode import MergeZone
from cosim.environment.velocity_map import VelocityMapper
from cosim.scratch import run_folder
from cosim.sumo.scenario import kind_of
from cosim.sumo.session import Gui, SumoSession
from cosim.sumo.setting import Setting
from cosim.sumo.snapshot import Snapshot

Step = tuple[dict, dict, dict, dict, dict]  # observations, rewards, terminations, truncations, infos


class SumoEnv(ParallelEnv):
    ROUTE_FILE: ClassVar[str]  # the route file's name in the env's temporary folder

    def __init__(self, config: Config, render_mode: str | None = None, gui: Gui | None = None) -> None:
        """`gui`: run sumo-gui over TraCI instead of libsumo, for people to watch (`cosim replay --gui`)."""
        modes = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in modes:
            raise ValueError(f"render_mode: expected None{''.join(f' or {m!r}' for m in modes)}, got {render_mode!r}")
        self.render_mode = render_mode
        # Everything below reads the config resolved on this net: net-relative keys in absolute units.
        self.setting = Setting.of(config, warn=True)
        self.net, self.cfg, self.resolution_notes = self.setting.net, self.setting.config, self.setting.notes
        config = self.cfg
        self.road, self.chainage = self.net.road, self.net.chainage
        self.zone = MergeZone.from_net(self.net)
        self.agents: list[str] = []
        self._act_space = gymnasium.spaces.Discrete(N_ACTIONS)
        self._target: dict[str, float] = {}  # [m/s] each agent's target speed
        self._stop_on: frozenset[int] = frozenset()  # collisions of these vehicle kinds stop a decision period
        self._next_seed = config.sim.seed
        self._tmp: Path | None = None  # this env's temporary folder, made at the first reset, removed at close
        self._snap: Snapshot | None = None
        self._closed = False  # close() released the process's SUMO slot: this env cannot run again
        self.last_summary: dict[str, Any] | None = None  # the summary of the episode (or run) that ended last
        self.session = SumoSession(Path(config.net.file), config.sim.step_length, self.road.index_of, kind_of,
                                   config.sim.sumo_args, config.sim.collision_mingap_factor,
                                   drive_avs=config.sim.av_driver == "env", gui=gui, shield=config.av.shield)

    def _spaces(self, mapper: VelocityMapper) -> None:
        self.mapper = mapper
        self._obs_space = gymnasium.spaces.Box(low=0, high=mapper.high, shape=mapper.shape, dtype=mapper.dtype)

    # -- PettingZoo API -----------------------------------------------------------------------------
    # One space object for all agents, as PettingZoo asks (no functools.cache: it would keep the env alive).
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Discrete:
        return self._act_space

    def step(self, actions: Mapping[str, Any]) -> Step:
        self._check_open("step()")
        acting = list(self.agents)
        actions = checked_actions(actions, acting, self.possible_agents)
        prev = self.snapshot
        lane_changed, invalid = self._act(prev, acting, actions)
        self._simulate(acting)
        snap = self._observe(acting, actions)
        rewards, extra = self._reward(prev, snap, acting, lane_changed, invalid)
        return self._end(snap, acting, rewards, extra)

    def action_masks(self) -> dict[str, np.ndarray]:
        """Each live agent's action mask after the last reset/step, as in its infos["action_mask"]: (N_ACTIONS,)
        int8, 1 where the action would change something (`cosim.environment.control.action_mask`)."""
        return self._masks(self.snapshot, self.agents)

    @property
    def snapshot(self) -> Snapshot:
        """The state of every vehicle after the last reset/step (for baselines, metrics and tools)."""
        if self._snap is None:
            raise RuntimeError("no snapshot before reset()")
        return self._snap

    @property
    def route_file(self) -> Path:
        """The SUMO route file of the episode (vehicles, vTypes, routes), rewritten at every reset."""
        if self._tmp is None:
            raise RuntimeError("no route file before reset()")
        return self._tmp / self.ROUTE_FILE

    def flush_outputs(self) -> None:
        """Complete SUMO's outputs of the last episode (the episode env's; a demand run's are complete at its end)."""

    def close(self) -> None:
        self.session.close()
        self._closing()
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

    # -- what reset and step share ------------------------------------------------------------------
    def _begin_reset(self, seed: int | None) -> int:
        """The episode's seed (a plain int in SUMO's range, or `SeedError` naming `seed`; None: the next of the
        sequence that starts at sim.seed), with the temporary folder made."""
        if self._closed:  # restarting would take a SUMO slot that another env of this process may hold now
            raise RuntimeError("reset() after close(): this env is closed; make a new one (cosim.parallel_env)")
        seed = check_seed("seed", self._next_seed if seed is None else seed)
        self._next_seed = (seed + 1) % (SEED_MAX + 1)  # past SUMO's last seed, the sequence starts again at 0
        self.episode_seed = seed
        if self._tmp is None:  # named after its owner: a kill -9 leaves nothing that the next run does not remove
            self._tmp = Path(tempfile.mkdtemp(prefix="env_", dir=run_folder()))
        return seed

    def _check_open(self, call: str) -> None:
        if self._snap is None:
            raise RuntimeError(f"{call} after close(): this env is closed; make a new one (cosim.parallel_env)"
                               if self._closed else f"{call} before reset()")

    def _masks(self, snap: Snapshot, agents: list[str]) -> dict[str, np.ndarray]:
        return agent_masks(snap, self.zone, agents, np.array([self._target[a] for a in agents]), self.cfg.av)

    def _act(self, prev: Snapshot, acting: list[str], actions: Mapping[str, int]
             ) -> tuple[dict[str, bool], dict[str, bool]]:
        """Meta-actions into target speeds and lane changes of the acting agents on the road; returns (lane_changed,
        invalid) by agent. Nothing with SUMO driving the AVs."""
        lane_changed, invalid = dict.fromkeys(acting, False), dict.fromkeys(acting, False)
        rows = prev.rows_of(acting)
        present = [a for a, r in zip(acting, rows, strict=True) if r >= 0]
        if not present or not self.session.drive_avs:
            return lane_changed, invalid
        rows = rows[rows >= 0]
        # AVs may use the highway's through lanes only, never the acceleration lane.
        d = decide(np.array([actions[a] for a in present]), prev.lane[rows], self.zone.through[prev.edge[rows]],
                   np.array([self._target[a] for a in present]), self.cfg.av)
        for a, speed, change, bad in zip(present, d.target_speed, d.lane_change, d.invalid, strict=True):
            self._target[a] = float(speed)
            if change:
                self.session.change_lane(a, int(change))
            lane_changed[a], invalid[a] = bool(change), bool(bad)
        return lane_changed, invalid

    def _simulate(self, acting: list[str]) -> None:
        """One decision period of SUMO, the acting agents driven toward their targets."""
        av = self.cfg.av
        targets = {a: self._target[a] for a in acting} if self.session.drive_avs else {}
        self.session.advance(self.cfg.steps_per_decision, targets, av.accel, av.decel, av.max_speed, self._stop_on)

    # -- the subclass's hooks -----------------------------------------------------------------------
    def _observe(self, acting: list[str], actions: Mapping[str, int]) -> Snapshot:
        """The state after the period: the snapshot, and whatever the env keeps of it (maps, metrics)."""
        raise NotImplementedError

    def _reward(self, prev: Snapshot, snap: Snapshot, acting: list[str], lane_changed: dict[str, bool],
                invalid: dict[str, bool]) -> tuple[dict[str, float], dict[str, dict]]:
        """Each acting agent's reward, and what its infos carry of it."""
        raise NotImplementedError

    def _end(self, snap: Snapshot, acting: list[str], rewards: dict[str, float], extra: dict[str, dict]) -> Step:
        """Who is done, the observations and infos, the episode's summary where it ended."""
        raise NotImplementedError

    def _closing(self) -> None:
        """What the env completes when it closes (SUMO is closed already)."""
