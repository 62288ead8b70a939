"""A tiny stand-in for the cosim merge env with the same spaces and PettingZoo parallel semantics.

Contract: `CueEnv` is a `pettingzoo.ParallelEnv` with agents `av_0..av_{N-1}`, `Box(0, H, (F, C, Hpx, Wpx))`
observations (read-only views into a buffer that the next step overwrites, like the real env) and `Discrete(5)`
actions. Each decision every agent sees a cue (left half of channel 0 or right half of channel 1 lit) and earns 1
for answering it with lane-left (0) or lane-right (2) respectively, so the optimal policy is learnable from the
observation. Accelerate (3) "crashes" the agent: reward -1 and terminated. Agents still running at `horizon` steps
are truncated. Infos carry `reward_terms` and, on the last step, `episode`; `social` is a reward every agent gets on
top of its own terms each step, outside `reward_terms` (as the SVO reward's part for the others); with `masked`
actions, each live agent's infos carry an `action_mask` (int8, 0 for those) at reset and every step, as the merge
env's do. `fail_once_file` makes the env fail once (across processes) at step `fail_at_step`, to test worker
restarts: raise `SimulationError`, or with `fail_by_exit` end its process (as a SUMO crash does); `fail_always`
makes every episode fail there (an input SUMO refuses). `step_sleep` [s] makes each step take that long (a slow
simulation).
`make_fake_env(**kw)` is a picklable env factory; `play_episode(env, seed)` plays one episode for
`WorkerPool.send_call`, with a `keep_alive` beat each step as evaluation's episodes do.
"""

from __future__ import annotations

import functools
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cosim.errors import SimulationError
from cosim.workers import keep_alive

_HIGH = {"float32": 1.0, "float16": 1.0, "uint8": 255}


class CueEnv(ParallelEnv):
    metadata = {"name": "cue_v0", "render_modes": []}

    def __init__(self, n_agents: int = 2, obs_shape: tuple[int, int, int, int] = (2, 4, 8, 16),
                 dtype: str = "float32", horizon: int = 8, fail_once_file: str | None = None,
                 fail_at_step: int = 3, fail_by_exit: bool = False, step_sleep: float = 0.0,
                 render_mode: str | None = None, fail_always: bool = False, masked: tuple[int, ...] = (),
                 social: float = 0.0) -> None:
        self.possible_agents = [f"av_{i}" for i in range(n_agents)]
        self.agents: list[str] = []
        self.render_mode = render_mode
        self.horizon = horizon
        self.max_steps = horizon
        self.fail_once_file = fail_once_file
        self.fail_at_step = fail_at_step
        self.fail_by_exit = fail_by_exit
        self.fail_always = fail_always
        self.step_sleep = step_sleep
        self.social = social
        self._high = _HIGH[dtype]
        self._obs_space = spaces.Box(0, self._high, shape=tuple(obs_shape), dtype=np.dtype(dtype))
        self._act_space = spaces.Discrete(5)
        self._info = {"action_mask": np.isin(np.arange(5), masked, invert=True).astype(np.int8)} if masked else {}
        self._buf = np.zeros((n_agents, *obs_shape), dtype=dtype)  # (N, F, C, H, W)
        self._rng = np.random.default_rng(0)
        self._cue = np.zeros(n_agents, dtype=np.int64)
        self._t = 0
        self._returns = np.zeros(n_agents)
        self._crashed = False

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_space

    def _observe(self) -> dict[str, np.ndarray]:
        self._cue = self._rng.choice([0, 2], size=len(self.possible_agents))
        half = self._buf.shape[-1] // 2
        self._buf[...] = 0
        for i, cue in enumerate(self._cue):  # left cue: left half of channel 0 lit, right cue: right half of 1
            if cue == 0:
                self._buf[i, :, 0, :, :half] = self._high
            else:
                self._buf[i, :, 1, :, half:] = self._high
        return {a: self._view(a) for a in self.agents}

    def _view(self, agent: str) -> np.ndarray:
        view = self._buf[self.possible_agents.index(agent)].view()
        view.flags.writeable = False
        return view

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self._t = 0
        self._returns[:] = 0
        self._crashed = False
        return self._observe(), {a: dict(self._info) for a in self.agents}

    def step(self, actions: dict[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        self._t += 1
        time.sleep(self.step_sleep)
        if self.fail_always and self._t == self.fail_at_step:
            raise SimulationError("Departure speed for vehicle 'merger' is too high (fake SUMO refusing an input)")
        if self.fail_once_file and self._t == self.fail_at_step:
            try:
                Path(self.fail_once_file).open("x").close()  # exclusive create: one process fails, once
            except FileExistsError:
                pass
            else:
                if self.fail_by_exit:
                    os._exit(1)
                raise SimulationError("fake SUMO crash")
        rewards, terms, truncs, infos = {}, {}, {}, {}
        for a in self.agents:
            i = self.possible_agents.index(a)
            act = int(actions[a])
            correct = float(act == self._cue[i])
            crash = act == 3
            rewards[a] = correct - float(crash) + self.social
            self._returns[i] += rewards[a]
            self._crashed |= crash
            terms[a] = crash
            truncs[a] = not crash and self._t >= self.horizon
            infos[a] = {"reward_terms": {"speed": correct, "collision": -float(crash)}, **self._info}
        acting = list(self.agents)
        self.agents = [a for a in acting if not (terms[a] or truncs[a])]
        obs = self._observe()
        obs.update({a: self._view(a) for a in acting if terms[a] or truncs[a]})  # final observations
        if not self.agents:
            episode = {"crashed": self._crashed, "merged": not self._crashed,
                       "mean_distance": float(self._returns.mean()), "merger_distance": 0.0, "length": self._t}
            for a in acting:
                infos[a]["episode"] = episode
        return obs, rewards, terms, truncs, infos

    def close(self) -> None:
        self.agents = []


def make_fake_env(**kwargs: Any) -> functools.partial[CueEnv]:
    """A picklable env factory for `WorkerPool` / `train(env_factory=...)`."""
    return functools.partial(CueEnv, **kwargs)


def play_episode(env: CueEnv, seed: int) -> int:
    """One episode of lane-left actions (a `WorkerPool.send_call` function); returns its length in steps."""
    env.reset(seed=seed)
    steps = 0
    while env.agents:
        env.step(dict.fromkeys(env.agents, 0))
        steps += 1
        keep_alive()
    return steps
