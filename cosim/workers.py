"""The one pool of env worker processes: W processes, one PettingZoo ParallelEnv (one SUMO) each; training's
rollouts and evaluation's episodes both run on it, observations travel through shared memory.

Contract:
- `WorkerPool(env_factory, workers, max_restarts, timeout)` starts W processes (forkserver, else spawn) that
  each call the picklable `env_factory()` once (libsumo allows one simulation per process) and report the
  env's spec. The pool then maps two shared arrays (files in /dev/shm, removed at `close`), both
  (W, N, F, C, H, W) of the env's dtype: `obs[w]`, where worker w writes the observation of every live agent
  after a reset or step (zeros for the others), and `final[w]`, where it writes the final observation of each
  agent truncated in that step. Only small results cross the pipes; nothing is pickled per observation.
- Commands go to a subset of workers and their results are collected later, so that the learner can act
  for some workers while the others step: `send_reset(ws, seeds, outputs=False)`, `send_step(ws, actions)` (actions
  (len(ws), N); agent i is `possible_agents[i]`), then `recv(ws)` -> one `StepResult` per worker, with each live
  agent's action mask from its infos (`infos[a]["action_mask"]`; all ones where the env gives none). A worker's
  shared slots stay valid until its next command. Episodes do not reset by themselves: the step that ends one
  carries the env's `episode` summary and the caller decides what comes next.
- A worker whose env raises, whose process dies or that stays silent for `timeout` seconds is killed and
  replaced by a fresh process (given `START_TIMEOUT` to start), with a WARNING naming why (a timeout names
  the setting `timeout_key` that bounds it); its result is `lost` (no agent alive): the running episode is
  lost and must not be counted. More than `max_restarts` replacements over the pool's life raise
  `SimulationError` (naming `restarts_key`), and so does a worker whose env fails to start `START_ATTEMPTS`
  times in a row (a systematic fault, not bad luck).
  Bad input (`ConfigError`, `NetError`) fails the same way in every process and is raised at once.
- `send_call(ws, fn, args)` runs the picklable `fn(env, arg)` in each worker of `ws` (a whole evaluation
  episode, say); `recv(ws, lost=...)` returns its small result, or `lost(why)` for a worker that failed. A long
  call stays within `timeout` per step by calling `keep_alive()` each step: each beat restarts the worker's
  timeout, so an episode may take any time while a stopped or hung worker is found within `timeout`.
- Temporary files are the process's (`cosim.scratch`): the pool's folder in `run_folder()`, its shared arrays
  /dev/shm/<owner>_obs_*, and every pool start first removes what killed runs left (`remove_leftovers`).
This module imports neither torch nor SUMO, so workers start fast; the env factory imports what it needs.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import re
import shutil
import signal
import tempfile
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import ConfigError, NetError, SimulationError
from cosim.scratch import SHM, owner, remove_leftovers, run_folder

log = logging.getLogger(__name__)

START_ATTEMPTS = 3
# Workers yield the CPU to the process that waits for them all (the learner acting for them, or updating): with more
# workers than cores, a fair share would leave the learner a fraction of a core while everyone waits for its actions.
WORKER_NICENESS = 10
# [s] Starting a worker (imports, SUMO's start) takes longer than a step, more so on a loaded machine: a short
# step timeout must not turn every replacement into another timeout.
START_TIMEOUT = 120.0
# [MiB] One worker process besides its observation slots: Python, numpy, libsumo and its env (about 150 MB resident
# each, measured on the default scenario).
WORKER_MIB = 160

EnvFactory = Callable[[], Any]  # () -> pettingzoo.ParallelEnv; must be picklable (e.g. functools.partial)


def check_memory(parts: Sequence[tuple[str, int]], fix: str) -> None:
    """`ConfigError` where the `parts` ((what, bytes), e.g. a batch and the worker processes) together need more than
    this machine's physical memory: refused before anything is allocated or started, each part named, then `fix`."""
    need = sum(size for _, size in parts)
    have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if need > have:
        listed = " + ".join(f"{what}: {size / 2**30:,.1f} GiB" for what, size in parts)
        raise ConfigError(f"{listed}; {need / 2**30:,.1f} GiB in all, more than this machine's {have / 2**30:,.1f} GiB "
                          f"of memory: {fix}")


# -- a worker's beats during a call -------------------------------------------------------------------------
_CALLER: Connection | None = None  # in a worker, during a `call`: its pipe to the pool


def keep_alive(wait_s: float | None = None) -> None:
    """Tell the pool, from a `send_call` function, that this worker is working: each beat restarts its
    timeout (call it every step); `wait_s`: the next beat may take that long [s] instead (loading a policy,
    say). Does nothing outside a pool's call."""
    if _CALLER is not None:
        _CALLER.send(("beat", wait_s))


@dataclass(frozen=True)
class EnvSpec:
    agents: tuple[str, ...]  # possible_agents, fixed order: index i <-> agents[i]
    obs_shape: tuple[int, ...]  # (F, C, H, W)
    obs_dtype: str  # numpy dtype name: float32 | float16 | uint8
    n_actions: int
    max_steps: int  # an episode's most decision steps (the env's `max_steps`, or PettingZoo's `max_cycles`)


@dataclass
class StepResult:
    alive: np.ndarray  # (N,) bool: the agent acts at the next decision (its observation is in obs[w])
    reward: np.ndarray  # (N,) float32 reward of this step (0 for agents that did not act)
    terminated: np.ndarray  # (N,) bool: crashed / left; no bootstrap
    truncated: np.ndarray  # (N,) bool: cut (time limit, merge failed, another's crash): bootstrap from final[w]
    action_mask: np.ndarray  # (N, A) int8: 1 = the agent may take the action next (zeros for agents not alive)
    reward_terms: dict[str, np.ndarray] = field(default_factory=dict)  # term name -> (N,) float32
    episode: dict[str, Any] | None = None  # the env's summary when this step ended the episode
    lost: bool = False  # the env failed: the worker was replaced, the running episode is lost
    error: str = ""  # why, when lost: the first line of the failure

    @classmethod
    def lost_episode(cls, n: int, n_actions: int, error: str = "") -> StepResult:
        """The result of a worker that failed: no agent alive, the running episode lost."""
        return cls(np.zeros(n, bool), np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool),
                   np.zeros((n, n_actions), np.int8), lost=True, error=error)


class _EnvRunner:
    """Worker side: dict-keyed PettingZoo steps <-> index-keyed arrays written into the shared slots."""

    def __init__(self, env: Any) -> None:
        self.env = env
        # An env whose agents come and go (the demand env) is indexed by its observation slots, others by agent.
        self.slot_of = getattr(env, "agent_slot", None)
        self.agents = tuple(env.slot_names if self.slot_of else env.possible_agents)
        self.index = {a: i for i, a in enumerate(self.agents)}
        space = env.observation_space(self.agents[0])
        max_steps = getattr(env, "max_steps", getattr(env, "max_cycles", None))
        if max_steps is None:
            raise ConfigError(f"env {type(env).__name__}: needs a `max_steps` (or `max_cycles`) attribute, the most "
                              "decision steps of an episode, to size the rollout storage")
        self.spec = EnvSpec(self.agents, tuple(space.shape), np.dtype(space.dtype).name,
                            int(env.action_space(self.agents[0]).n), int(max_steps))
        self.obs: np.ndarray | None = None  # (N, F, C, H, W) this worker's slot of the shared arrays
        self.final: np.ndarray | None = None
        self.length = 0
        self.outputs = False  # the running episode writes SUMO's outputs, added to its summary at its end

    def _at(self, agent: str) -> int:
        """The index of a live agent in the arrays."""
        return self.slot_of(agent) if self.slot_of else self.index[agent]

    def _write(self, obs: dict[str, np.ndarray], alive: Sequence[str], infos: dict[str, dict]
               ) -> tuple[np.ndarray, np.ndarray]:
        """The live agents' observations into the shared slot; returns who is alive (N,) and each live agent's
        `action_mask` (N, A) int8 from its infos (all allowed where there is none)."""
        assert self.obs is not None
        mask = np.zeros(len(self.agents), dtype=bool)
        masks = np.zeros((len(self.agents), self.spec.n_actions), np.int8)
        for a in alive:
            i = self._at(a)
            self.obs[i] = obs[a]
            mask[i] = True
            masks[i] = infos.get(a, {}).get("action_mask", 1)
        self.obs[~mask] = 0
        return mask, masks

    def reset(self, seed: int | None, outputs: bool = False) -> StepResult:
        # Only where asked: an env of another library need not know the option.
        obs, infos = self.env.reset(seed=seed, options={"outputs": True}) if outputs else self.env.reset(seed=seed)
        self.outputs = outputs
        self.length = 0
        n = len(self.agents)
        alive, masks = self._write(obs, [a for a in self.env.agents if a in obs], infos)
        return StepResult(alive, np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool), masks)

    def step(self, actions: np.ndarray) -> StepResult:
        assert self.final is not None
        acting = list(self.env.agents)
        at = {a: self._at(a) for a in acting}  # before the step, which frees the slots of those it ends
        obs, rew, term, trunc, infos = self.env.step({a: int(actions[at[a]]) for a in acting})
        self.length += 1
        n = len(self.agents)
        reward, terminated, truncated = np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool)
        terms: dict[str, np.ndarray] = {}
        episode = None
        for a in acting:
            i = at[a]
            reward[i] = float(rew.get(a, 0.0))
            terminated[i] = bool(term.get(a, False))
            truncated[i] = bool(trunc.get(a, False)) and not terminated[i]  # a crash at the limit is a crash
            if truncated[i]:
                self.final[i] = obs[a]
            info = infos.get(a, {})
            for name, value in info.get("reward_terms", {}).items():
                terms.setdefault(name, np.zeros(n, np.float32))[i] = value
            episode = info.get("episode", episode)
        # Agents that entered in this step (the demand env's) are live too.
        live = [a for a in self.env.agents if a in obs and not (term.get(a) or trunc.get(a))]
        alive, masks = self._write(obs, live, infos)
        if live:
            episode = None  # only reported when the episode is over
        elif episode is None:
            episode = {"length": self.length}
        if episode is not None and self.outputs:  # the episode env's SUMO outputs; a demand run's are in its summary
            self.env.flush_outputs()
            sumo = self.env.sumo_outputs.pop(self.env.episode_seed, None)
            episode = {**episode, **(sumo.as_row() if sumo is not None else {})}
        return StepResult(alive, reward, terminated, truncated, masks, terms, episode)


def _worker_main(conn: Connection, env_factory: EnvFactory, tmp_root: str) -> None:
    """Process entry: build the env, then serve attach / reset / step / call / close commands."""
    global _CALLER
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the learner's to handle
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.nice(WORKER_NICENESS)
    # The env's temporary files go into the pool's folder, which the pool removes even if this process is killed.
    tempfile.tempdir = tmp_root
    env = None
    try:
        env = env_factory()
        runner = _EnvRunner(env)
        conn.send(("ok", runner.spec))
        while True:
            cmd, arg = conn.recv()
            if cmd == "close":
                break
            if cmd == "attach":
                runner.obs, runner.final = (_map(path, shape, dtype, "r+")[index] for path, shape, dtype, index in arg)
                conn.send(("ok", None))
            elif cmd == "call":
                fn, fn_arg = arg
                _CALLER = conn
                try:
                    result = fn(env, fn_arg)
                finally:
                    _CALLER = None
                conn.send(("ok", result))
            else:
                conn.send(("ok", runner.reset(*arg) if cmd == "reset" else runner.step(arg)))
    except EOFError:  # the learner went away
        pass
    except (ConfigError, NetError) as exc:  # bad input fails the same way in every restart: stop the run
        conn.send(("fatal", exc))
    except BaseException as exc:  # report any env failure; the learner replaces this worker
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


def _map(path: str, shape: tuple[int, ...], dtype: str, mode: str) -> np.ndarray:
    return np.memmap(path, dtype=dtype, mode=mode, shape=shape)


def agreed_spec(specs: Sequence[EnvSpec], who: str) -> EnvSpec:
    """The one spec every worker's env reported; `SimulationError` when they differ."""
    if any(s != specs[0] for s in specs):
        raise SimulationError(f"{who} built envs with different specs: {set(specs)}")
    return specs[0]


class WorkerFailure(Exception):
    """A worker's env raised, its process died, or it stayed silent (internal: the pool replaces it)."""


def failure_line(exc: BaseException) -> str:
    """A failure's first line, without the worker's name (the same failure reads the same in any worker)."""
    line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return re.sub(r"^rollout-\d+: (env raised )?", "", line)


class _Worker:
    def __init__(self, ctx: Any, env_factory: EnvFactory, name: str, tmp_root: str) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child, env_factory, tmp_root), name=name, daemon=True)
        self.proc.start()
        child.close()

    def send(self, cmd: str, arg: Any) -> None:
        try:
            self.conn.send((cmd, arg))
        except (BrokenPipeError, OSError) as exc:
            raise WorkerFailure(f"{self.proc.name}: pipe closed ({exc})") from None

    def read(self) -> tuple[bool, Any]:
        """The next message, which has arrived: (True, seconds the next may take or None) for a beat, else
        (False, the answer)."""
        try:
            status, payload = self.conn.recv()
        except (EOFError, OSError):
            raise WorkerFailure(f"{self.proc.name}: process died (exit code {self.proc.exitcode})") from None
        if status == "fatal":
            raise payload
        if status == "error":
            raise WorkerFailure(f"{self.proc.name}: env raised {payload}")
        return status == "beat", payload

    def silent(self, seconds: float, setting: str) -> WorkerFailure:
        return WorkerFailure(f"{self.proc.name}: no answer in {seconds:g} s ({setting})")

    def recv(self, timeout: float, setting: str) -> Any:
        """The answer to the last command (not a call's: `WorkerPool.recv` hears its beats)."""
        while True:
            if not self.conn.poll(timeout):
                raise self.silent(timeout, setting)
            beat, payload = self.read()
            if not beat:
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

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()  # SIGKILL also ends a stopped (SIGSTOP) process
        self.proc.join(5.0)
        self.conn.close()


class PoolCommands:
    """The commands both backends take, as named sends to a subset of workers (`_send` per backend)."""

    def _send(self, ws: Sequence[int], cmd: str, args: Sequence[Any]) -> None:
        raise NotImplementedError

    def send_reset(self, ws: Sequence[int], seeds: Sequence[int | None], outputs: bool = False) -> None:
        """`outputs`: the episodes write SUMO's outputs (`MergeEnv.reset`'s option), and the step that ends each
        carries them (`SumoOutputs.as_row`: conflicts, throughput, ...) in its `episode` summary."""
        self._send(ws, "reset", [(seed, outputs) for seed in seeds])

    def send_step(self, ws: Sequence[int], actions: np.ndarray) -> None:
        self._send(ws, "step", list(np.asarray(actions, dtype=np.int64)))


class WorkerPool(PoolCommands):
    """W env worker processes with shared observation slots; failed workers are replaced (module doc)."""

    def __init__(self, env_factory: EnvFactory, workers: int, max_restarts: int = 100, timeout: float = 60.0,
                 start_method: str | None = None, timeout_key: str = "train.step_timeout",
                 restarts_key: str = "train.max_restarts") -> None:
        method = start_method or ("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
        self.ctx = mp.get_context(method)
        self.env_factory = env_factory
        self.max_restarts = max_restarts
        self.timeout = timeout
        self.timeout_key = timeout_key  # the settings that bound this pool, named in its messages
        self.restarts_key = restarts_key
        self.restarts = 0
        self.workers: list[_Worker] = []
        self._files: list[str] = []
        remove_leftovers()
        self._tmp_root = tempfile.mkdtemp(prefix="pool_", dir=run_folder())
        try:
            for w in range(workers):
                self.workers.append(self._start(w))
            # the env factories run in parallel
            self.spec: EnvSpec = agreed_spec([self._recv_spec(w) for w in range(workers)], "rollout workers")
            shape = (workers, len(self.spec.agents), *self.spec.obs_shape)
            self.obs = self._shared(shape)  # (W, N, F, C, H, W)
            self.final = self._shared(shape)
            for w in range(workers):
                try:
                    self._attach(w)
                except WorkerFailure as exc:  # died between its spec and its slots
                    self._replace(w, exc)
        except BaseException:
            self.close()
            raise

    def __len__(self) -> int:
        return len(self.workers)

    def pid(self, w: int) -> int:
        """The process id of worker w."""
        return int(self.workers[w].proc.pid or 0)

    def _start(self, w: int) -> _Worker:
        return _Worker(self.ctx, self.env_factory, f"rollout-{w}", self._tmp_root)

    def _shared(self, shape: tuple[int, ...]) -> np.ndarray:
        folder = SHM if SHM.is_dir() else run_folder()  # RAM-backed where there is one
        fd, path = tempfile.mkstemp(prefix=f"{owner()}_obs_", dir=folder)
        os.close(fd)
        self._files.append(path)
        return _map(path, shape, self.spec.obs_dtype, "w+")

    def _attach(self, w: int) -> None:
        arrays = [(path, a.shape, self.spec.obs_dtype, w) for path, a in zip(self._files, (self.obs, self.final),
                                                                          strict=True)]
        self.workers[w].send("attach", arrays)
        self.workers[w].recv(self.timeout, self.timeout_key)

    def _recv_spec(self, w: int) -> EnvSpec:
        for attempt in range(1, START_ATTEMPTS + 1):
            try:
                return self.workers[w].recv(max(self.timeout, START_TIMEOUT), self.timeout_key)
            except WorkerFailure as exc:
                reason = exc
                if attempt < START_ATTEMPTS:
                    self._replace(w, exc)
        raise SimulationError(f"rollout worker {w} could not start its env {START_ATTEMPTS} times in a row; "
                              f"last failure: {reason}")

    def _replace(self, w: int, reason: Exception) -> None:
        """Kill worker w and start another in its place (attached to the shared slots once they exist)."""
        for _ in range(START_ATTEMPTS):
            self.restarts += 1
            if self.restarts > self.max_restarts:
                raise SimulationError(f"rollout worker {w} failed; {self.restarts} failures in total exceed "
                                      f"{self.restarts_key} = {self.max_restarts}; last failure: {reason}")
            log.warning("rollout worker %d failed (%s); replacing it (restart %d of at most %d)", w,
                        str(reason).splitlines()[0], self.restarts, self.max_restarts)
            self.workers[w].kill()
            self.workers[w] = self._start(w)
            if not self._files:  # starting up: the caller receives the new worker's spec
                return
            try:
                spec = self.workers[w].recv(max(self.timeout, START_TIMEOUT), self.timeout_key)
                if spec != self.spec:
                    raise SimulationError(f"rollout worker {w} was restarted with another env spec: {spec}")
                self._attach(w)
                return
            except WorkerFailure as exc:
                reason = exc
        raise SimulationError(f"rollout worker {w} could not start its env {START_ATTEMPTS} times in a row; "
                              f"last failure: {reason}")

    def _send(self, ws: Sequence[int], cmd: str, args: Sequence[Any]) -> None:
        for w, arg in zip(ws, args, strict=True):
            try:
                self.workers[w].send(cmd, arg)
            except WorkerFailure:
                pass  # found at recv

    def send_call(self, ws: Sequence[int], fn: Callable[[Any, Any], Any], args: Sequence[Any]) -> None:
        """Run `fn(env, arg)` in each worker of `ws` (local processes only: Ray actors take resets and steps)."""
        self._send(ws, "call", [(fn, a) for a in args])

    def recv(self, ws: Sequence[int], lost: Callable[[str], Any] | None = None) -> list[Any]:
        """Results of the last command sent to each worker of `ws`; a failed worker is replaced and its result is
        `lost(why)`, `why` the failure's first line (default: `StepResult.lost_episode`)."""
        got: dict[int, Any] = {}
        failed: dict[int, WorkerFailure] = {}
        # All of them at once, so that each one's beats are heard as they come and its silence is timed alone.
        waits = dict.fromkeys(ws, self.timeout)  # [s] worker -> how long its next message may take
        deadlines = {w: time.monotonic() + self.timeout for w in ws}
        while deadlines:
            conns = {self.workers[w].conn: w for w in deadlines}
            for conn in wait(list(conns), max(0.0, min(deadlines.values()) - time.monotonic())):
                w = conns[conn]
                try:
                    beat, payload = self.workers[w].read()
                except WorkerFailure as exc:
                    failed[w] = exc
                    del deadlines[w]
                    continue
                if beat:
                    waits[w] = max(self.timeout, payload or 0.0)
                    deadlines[w] = time.monotonic() + waits[w]
                else:
                    got[w] = payload
                    del deadlines[w]
            now = time.monotonic()
            for w in [w for w, deadline in deadlines.items() if deadline <= now]:
                failed[w] = self.workers[w].silent(waits[w], self.timeout_key)
                del deadlines[w]
        n = len(self.spec.agents)
        out: list[Any] = []
        for w in ws:  # replaced only now: a replacement's start must not eat into the others' time
            if w in got:
                out.append(got[w])
                continue
            self._replace(w, failed[w])
            self.obs[w] = 0
            why = failure_line(failed[w])
            out.append(StepResult.lost_episode(n, self.spec.n_actions, why) if lost is None else lost(why))
        return out

    def close(self) -> None:
        for worker in self.workers:
            worker.close()
        self.workers = []
        for path in self._files:
            Path(path).unlink(missing_ok=True)
        self._files = []
        shutil.rmtree(self._tmp_root, ignore_errors=True)
