"""Rollout workers: W processes, one PettingZoo ParallelEnv each, stepped in lock-step by the learner.

Contract:
- `WorkerPool(env_factory, workers, seed)` starts W processes (forkserver, else spawn) that each call the
  picklable `env_factory()` once (libsumo allows one simulation per process) and report the env's spec.
- `reset()` returns observations (W, N, F, C, H, W) and an alive mask (W, N); `step(actions (W, N))`
  returns one `StepResult` per worker. Agent i is `possible_agents[i]`. A worker whose episode ended
  resets by itself: its `next_obs` is then the new episode's first observation and `episode` holds the
  finished episode's info. Observations are copied out of the env's read-only views.
- A worker whose env raises (or whose process dies) is replaced by a fresh process and reset; its
  `StepResult.lost` is True: the running episode is lost, its remaining steps never reach the learner and
  it is not counted as an episode (steps of it collected in earlier updates were already trained on).
  More than `max_restarts` replacements over the pool's life raise `cosim.errors.SimulationError`.
This module imports neither torch nor SUMO, so workers start fast; the env factory imports what it needs.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from cosim.config import EVAL_SEED_START
from cosim.errors import ConfigError, NetError, SimulationError

log = logging.getLogger(__name__)

EnvFactory = Callable[[], Any]  # () -> pettingzoo.ParallelEnv; must be picklable (e.g. functools.partial)


@dataclass(frozen=True)
class EnvSpec:
    agents: tuple[str, ...]  # possible_agents, fixed order: index i <-> agents[i]
    obs_shape: tuple[int, ...]  # (F, C, H, W)
    obs_dtype: str  # numpy dtype name: float32 | float16 | uint8
    n_actions: int


@dataclass
class StepResult:
    next_obs: np.ndarray  # (N, F, C, H, W) observation for the next decision (zeros where not alive)
    alive: np.ndarray  # (N,) bool: agent acts at the next decision
    reward: np.ndarray  # (N,) float32 reward of this step (0 for agents that did not act)
    terminated: np.ndarray  # (N,) bool: crashed / left; no bootstrap
    truncated: np.ndarray  # (N,) bool: time limit; bootstrap from final_obs
    final_obs: dict[int, np.ndarray] = field(default_factory=dict)  # agent index -> (F, C, H, W) if truncated
    reward_terms: dict[str, np.ndarray] = field(default_factory=dict)  # term name -> (N,) float32
    episode: dict[str, Any] | None = None  # the finished episode's info when this step ended it
    lost: bool = False  # the env failed: the worker was restarted, the running episode is lost


# A worker's episodes count up from its first seed: leave room for a million of them below evaluation's seeds.
_FIRST_SEEDS = EVAL_SEED_START - 1_000_000


def _seed(seed: int, worker: int, generation: int) -> int:
    """First-episode seed per worker and per (re)start, so a crashing episode is not replayed; always below
    the evaluation seeds."""
    return int(np.random.SeedSequence([seed, worker, generation]).generate_state(1)[0]) % _FIRST_SEEDS


class _EnvRunner:
    """Worker-side wrapper: dict-keyed PettingZoo steps <-> index-keyed arrays, with auto-reset."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.agents = tuple(env.possible_agents)
        self.index = {a: i for i, a in enumerate(self.agents)}
        space = env.observation_space(self.agents[0])
        self.spec = EnvSpec(self.agents, tuple(space.shape), np.dtype(space.dtype).name,
                            int(env.action_space(self.agents[0]).n))
        self.length = 0

    def _pack(self, obs: dict[str, np.ndarray], alive: list[str]) -> tuple[np.ndarray, np.ndarray]:
        out = np.zeros((len(self.agents), *self.spec.obs_shape), dtype=self.spec.obs_dtype)  # (N, F, C, H, W)
        mask = np.zeros(len(self.agents), dtype=bool)
        for a in alive:
            out[self.index[a]] = obs[a]
            mask[self.index[a]] = True
        return out, mask

    def reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        obs, _ = self.env.reset(seed=seed)
        self.length = 0
        return self._pack(obs, [a for a in self.env.agents if a in obs])

    def step(self, actions: np.ndarray) -> StepResult:
        acting = list(self.env.agents)
        obs, rew, term, trunc, infos = self.env.step({a: int(actions[self.index[a]]) for a in acting})
        self.length += 1
        n = len(self.agents)
        reward, terminated, truncated = np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool)
        final_obs: dict[int, np.ndarray] = {}
        terms: dict[str, np.ndarray] = {}
        episode = None
        for a in acting:
            i = self.index[a]
            reward[i] = float(rew.get(a, 0.0))
            terminated[i] = bool(term.get(a, False))
            truncated[i] = bool(trunc.get(a, False)) and not terminated[i]  # a crash at the limit is a crash
            if truncated[i]:
                final_obs[i] = np.array(obs[a])  # copy: the env's view is only valid until the next step
            info = infos.get(a, {})
            for name, value in info.get("reward_terms", {}).items():
                terms.setdefault(name, np.zeros(n, np.float32))[i] = value
            episode = info.get("episode", episode)
        alive = [a for a in acting if a in self.env.agents and a in obs and not (term.get(a) or trunc.get(a))]
        if alive:
            next_obs, mask = self._pack(obs, alive)
            episode = None  # only reported when the episode is over
        else:  # episode over: report it and start the next one (seeded by the env's own sequence)
            episode = dict(episode) if episode is not None else {"length": self.length}
            next_obs, mask = self.reset(None)
        return StepResult(next_obs, mask, reward, terminated, truncated, final_obs, terms, episode)


def _worker_main(conn: Connection, env_factory: EnvFactory) -> None:
    """Process entry: build the env, then serve ("reset", seed) / ("step", actions) / ("close", None)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the learner's to handle
    env = None
    try:
        env = env_factory()
        runner = _EnvRunner(env)
        conn.send(("ok", runner.spec))
        while True:
            cmd, arg = conn.recv()
            if cmd == "close":
                break
            conn.send(("ok", runner.reset(arg) if cmd == "reset" else runner.step(arg)))
    except EOFError:  # the learner went away
        pass
    except (ConfigError, NetError) as exc:  # bad input fails the same way in every restart: stop the run
        conn.send(("fatal", exc))
    except BaseException as exc:  # report any env failure; the learner restarts this worker
        try:
            conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
        except (BrokenPipeError, OSError):
            pass
    finally:
        if env is not None:
            try:
                env.close()
            except Exception:  # the env may be broken already
                pass
        conn.close()


class WorkerFailure(Exception):
    """A worker's env raised or its process died (internal: the pool restarts it)."""


class _Worker:
    def __init__(self, ctx: Any, env_factory: EnvFactory, name: str) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child, env_factory), name=name, daemon=True)
        self.proc.start()
        child.close()

    def send(self, cmd: str, arg: Any) -> None:
        try:
            self.conn.send((cmd, arg))
        except (BrokenPipeError, OSError) as exc:
            raise WorkerFailure(f"{self.proc.name}: pipe closed ({exc})") from None

    def recv(self) -> Any:
        try:
            status, payload = self.conn.recv()
        except (EOFError, OSError):
            raise WorkerFailure(f"{self.proc.name}: process died (exit code {self.proc.exitcode})") from None
        if status == "fatal":
            raise payload
        if status == "error":
            raise WorkerFailure(f"{self.proc.name}: env raised {payload}")
        return payload

    def close(self, timeout: float = 5.0) -> None:
        try:
            self.conn.send(("close", None))
        except (BrokenPipeError, OSError):
            pass
        self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(timeout)
        self.conn.close()


class WorkerPool:
    """W env worker processes stepped synchronously; failed workers are replaced (see module doc)."""

    def __init__(self, env_factory: EnvFactory, workers: int, seed: int = 0, max_restarts: int = 100,
                 start_method: str | None = None) -> None:
        method = start_method or ("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
        self.ctx = mp.get_context(method)
        self.env_factory = env_factory
        self.seed = seed
        self.max_restarts = max_restarts
        self.restarts = 0
        self.generation = [0] * workers
        self.workers: list[_Worker] = []
        specs = []
        try:
            for w in range(workers):
                self.workers.append(_Worker(self.ctx, env_factory, f"rollout-{w}"))
            for w in range(workers):  # the env factories run in parallel
                specs.append(self._recv_spec(w))
        except BaseException:
            self.close()
            raise
        if any(s != specs[0] for s in specs):
            self.close()
            raise SimulationError(f"rollout workers built envs with different specs: {set(specs)}")
        self.spec: EnvSpec = specs[0]

    def __len__(self) -> int:
        return len(self.workers)

    def _recv_spec(self, w: int) -> EnvSpec:
        while True:
            try:
                return self.workers[w].recv()
            except WorkerFailure as exc:
                self._replace(w, exc)

    def _replace(self, w: int, reason: Exception) -> None:
        self.restarts += 1
        log.warning("rollout worker %d failed (%s); restarting it (restart %d of at most %d)", w,
                    str(reason).splitlines()[0], self.restarts, self.max_restarts)
        if self.restarts > self.max_restarts:
            raise SimulationError(f"rollout worker {w} failed {self.restarts} times in total (train.max_restarts "
                                  f"= {self.max_restarts}); last failure: {reason}")
        self.workers[w].close(timeout=1.0)
        self.generation[w] += 1
        self.workers[w] = _Worker(self.ctx, self.env_factory, f"rollout-{w}")

    def _reset_one(self, w: int) -> tuple[np.ndarray, np.ndarray]:
        """Reset worker w, replacing it until a reset succeeds."""
        while True:
            try:
                self.workers[w].send("reset", _seed(self.seed, w, self.generation[w]))
                return self.workers[w].recv()
            except WorkerFailure as exc:
                self._replace(w, exc)
                self._recv_spec(w)

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        """Observations (W, N, F, C, H, W) and alive mask (W, N) of fresh episodes in every worker."""
        for w, worker in enumerate(self.workers):
            try:
                worker.send("reset", _seed(self.seed, w, self.generation[w]))
            except WorkerFailure:
                pass  # picked up below
        results = []
        for w, worker in enumerate(self.workers):
            try:
                results.append(worker.recv())
            except WorkerFailure as exc:
                self._replace(w, exc)
                self._recv_spec(w)
                results.append(self._reset_one(w))
        return np.stack([r[0] for r in results]), np.stack([r[1] for r in results])

    def step(self, actions: np.ndarray) -> list[StepResult]:
        """Step every worker with its row of `actions` (W, N); one result per worker (see module doc)."""
        failed: dict[int, Exception] = {}
        for w, worker in enumerate(self.workers):
            try:
                worker.send("step", actions[w])
            except WorkerFailure as exc:
                failed[w] = exc
        results: list[StepResult | None] = []
        for w, worker in enumerate(self.workers):
            if w in failed:
                results.append(None)
                continue
            try:
                results.append(worker.recv())
            except WorkerFailure as exc:
                failed[w] = exc
                results.append(None)
        for w, exc in failed.items():
            self._replace(w, exc)
            self._recv_spec(w)
            obs, alive = self._reset_one(w)
            n = len(self.spec.agents)
            results[w] = StepResult(obs, alive, np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool),
                                    lost=True)
        return results  # type: ignore[return-value]

    def close(self) -> None:
        for worker in self.workers:
            worker.close()
        self.workers = []
