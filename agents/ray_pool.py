"""Rollout workers as Ray actors (`cosim train --backend ray`): the contract of `cosim.workers.WorkerPool`.

Contract: `RayWorkerPool(env_factory, workers, max_restarts, timeout, address)` connects to Ray (`connect`:
`address` "auto" or HOST:PORT, a running cluster; None, a local Ray started for this process) and starts
W actors, one env (one SUMO) and one CPU each, anywhere in the cluster. It offers what the trainer uses of
`WorkerPool`: `spec`, the (W, N, F, C, H, W) arrays `obs` and `final` (here plain arrays of the driver that
each result is copied into, since actors may live on other machines), `send_reset`, `send_step`, `recv`,
`restarts`, `close` and `pid(w)`. Failures follow `WorkerPool`'s rules: an actor whose env raises, whose
process dies (SUMO crash, node lost) or that stays silent for `timeout` seconds is restarted by Ray
(`ray.kill(..., no_restart=False)` where it is still there), logged, and its result is `lost`; more than
`max_restarts` failures, or an env that fails to start `START_ATTEMPTS` times in a row, raise
`SimulationError`; `ConfigError` / `NetError` reach the caller as they are. Ray is imported here only, and
this module only where `--backend ray` is asked for: the local backend needs no Ray. `connect` (the pool's
and the sweep's way into Ray) leaves the process's SIGINT and SIGTERM handlers as it found them.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import os
import shutil
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from cosim.errors import ConfigError, NetError, SimulationError
from cosim.scratch import remove_leftovers, run_folder
from cosim.workers import (
    START_ATTEMPTS,
    START_TIMEOUT,
    EnvFactory,
    EnvSpec,
    PoolCommands,
    StepResult,
    WorkerFailure,
    _EnvRunner,
    agreed_spec,
    failure_line,
)

log = logging.getLogger(__name__)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ConfigError("--backend ray: Ray is not installed; install it with pip install -e \".[ray]\"") from None
    return ray


@contextlib.contextmanager
def keep_signal_handlers() -> Iterator[None]:
    """The SIGINT and SIGTERM handlers of before, restored on leaving. `ray.init` installs a SIGTERM handler of
    its own (`sys.exit(15)`) that outlives `ray.shutdown`: in its place, a SIGTERM would end `cosim train`
    without its stop after the update in progress, its checkpoint and exit 130."""
    if threading.current_thread() is not threading.main_thread():  # no handlers there, Ray's neither
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            if handler is not None:  # None: a handler set outside Python, which Python cannot put back
                signal.signal(sig, handler)


def connect(address: str | None, cpus: int) -> tuple[Any, bool]:
    """Ray, joined to the cluster at `address` or (None) to a local Ray started here with this machine's CPUs,
    or `cpus` logical ones where that is more (more rollout workers than cores wait on SUMO, as local worker
    processes do); an initialised Ray (inside a Ray task) is used as it is. Returns (ray, whether this call
    started it)."""
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    if address is None:
        with keep_signal_handlers():
            ray.init(num_cpus=max(os.cpu_count() or 1, cpus), include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
        return ray, True
    host, _, port = address.rpartition(":")
    host = host.strip("[]")  # an IPv6 address
    if "://" not in address and host and port.isdigit():  # Ray itself retries an unreachable address for minutes
        try:
            socket.create_connection((host, int(port)), timeout=10).close()
        except OSError as exc:
            raise ConfigError(f"--ray-address {address}: cannot reach it ({exc}); start a cluster there with `ray "
                              "start --head`, or leave out --ray-address for a local Ray") from None
    try:
        with keep_signal_handlers():
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    except ConnectionError as exc:
        raise ConfigError(f"--ray-address {address}: no Ray cluster there ({exc}); start one with `ray start "
                          "--head`, or leave out --ray-address for a local Ray") from None
    return ray, True


class _EnvActor:
    """One env in an actor process. A failure to build the env is kept and returned by `start`, so that the
    driver sees the env's own exception (Ray would otherwise report only that the actor died)."""

    def __init__(self, env_factory: EnvFactory) -> None:
        # The env's temporary files go into this actor process's folder, removed by `close`; an actor that died
        # (killed, SUMO crash) never got there: the folder names its process, and the next actor or pool
        # started on that machine removes it (`run_folder` does, as it makes this one).
        self.tmp = str(run_folder())
        tempfile.tempdir = self.tmp
        self.error: Exception | None = None
        self.runner: _EnvRunner | None = None
        try:
            self.runner = _EnvRunner(env_factory())
            n = len(self.runner.agents)
            shape, dtype = self.runner.spec.obs_shape, self.runner.spec.obs_dtype
            self.runner.obs, self.runner.final = np.zeros((n, *shape), dtype), np.zeros((n, *shape), dtype)
        except (ConfigError, NetError) as exc:  # bad input: the driver stops the run
            self.error = exc
        except BaseException as exc:  # noqa: BLE001 - returned to the driver by start()
            self.error = WorkerFailure(f"env raised {type(exc).__name__}: {exc}")

    def start(self) -> tuple[EnvSpec | BaseException, int]:
        """The env's spec, or why it could not be built; and this process's id, which tells restarts apart."""
        if self.runner is None:
            return self.error or SimulationError("no env"), os.getpid()
        return self.runner.spec, os.getpid()

    def reset(self, arg: tuple[int | None, bool]) -> tuple[StepResult, np.ndarray, None]:
        assert self.runner is not None and self.runner.obs is not None
        return self.runner.reset(*arg), self.runner.obs, None

    def step(self, actions: np.ndarray) -> tuple[StepResult, np.ndarray, np.ndarray | None]:
        assert self.runner is not None and self.runner.obs is not None
        result = self.runner.step(actions)
        # Final observations travel only in the step that truncates someone.
        return result, self.runner.obs, self.runner.final if result.truncated.any() else None

    def close(self) -> None:
        if self.runner is not None:
            try:
                self.runner.env.close()
            except Exception:  # noqa: BLE001 - the env may be broken already
                pass
        shutil.rmtree(self.tmp, ignore_errors=True)


class RayWorkerPool(PoolCommands):
    """W env actors on Ray behind the interface of `cosim.workers.WorkerPool` (module doc)."""

    def __init__(self, env_factory: EnvFactory, workers: int, max_restarts: int = 100, timeout: float = 60.0,
                 address: str | None = None) -> None:
        self.max_restarts = max_restarts
        self.timeout = timeout
        self.restarts = 0
        self.actors: list[Any] = []
        self.pids: list[int] = []
        self._pending: dict[int, Any] = {}
        remove_leftovers()  # what killed runs left on this machine; each actor does the same on its own
        self.ray, self._started_ray = connect(address, workers)
        ray = self.ray
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus < workers:
            self.close()
            raise ConfigError(f"--workers {workers}: the Ray cluster has {cpus:g} CPUs and each rollout actor takes "
                              "one; use fewer workers or add machines")
        # Ray restarts a dead actor by itself; this pool counts the failures against max_restarts.
        self._actor_cls = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=0)(_EnvActor)
        try:
            self.actors = [self._actor_cls.remote(env_factory) for _ in range(workers)]
            starts = [actor.start.remote() for actor in self.actors]
            self.pids = [0] * workers
            self.spec: EnvSpec = agreed_spec([self._ready(w, starts[w]) for w in range(workers)], "rollout actors")
            shape = (workers, len(self.spec.agents), *self.spec.obs_shape)
            self.obs = np.zeros(shape, self.spec.obs_dtype)
            self.final = np.zeros(shape, self.spec.obs_dtype)
        except BaseException:
            self.close()
            raise

    def __len__(self) -> int:
        return len(self.actors)

    def pid(self, w: int) -> int:
        """The process id of worker w's actor (on its node)."""
        return self.pids[w]

    def _get(self, ref: Any, timeout: float) -> Any:
        ray = self.ray
        try:
            return ray.get(ref, timeout=timeout)
        except ray.exceptions.GetTimeoutError:
            raise TimeoutError(f"no answer in {timeout:g} s (train.step_timeout)") from None
        except ray.exceptions.RayTaskError as exc:  # the env raised: its own exception says what went wrong
            cause = getattr(exc, "cause", None)
            if isinstance(cause, ConfigError | NetError):
                raise cause from None
            raise WorkerFailure(f"env raised {cause!r}" if cause is not None else str(exc)) from None

    def _ready(self, w: int, ref: Any = None, dead_pid: int | None = None) -> EnvSpec:
        """Wait until actor w (not the process `dead_pid`, which Ray is replacing) has built its env and return
        its spec; a failure restarts the actor, `START_ATTEMPTS` failures in a row stop the run."""
        ray, wait = self.ray, max(self.timeout, START_TIMEOUT)
        failures, deadline = 0, time.monotonic() + wait
        while True:
            got: EnvSpec | BaseException
            pid: int | None = None
            try:
                got, pid = self._get(ref if ref is not None else self.actors[w].start.remote(), wait)
                waiting = pid == dead_pid  # the old process answered: the kill has not reached it yet
            except ray.exceptions.RayActorError as exc:
                # Being restarted, by Ray or after a kill of ours that a call may still meet as the old process
                # dying: wait. An actor that dies at its very first start is a failure.
                got, waiting = exc, isinstance(exc, ray.exceptions.ActorUnavailableError) or dead_pid is not None
            except (TimeoutError, WorkerFailure, ray.exceptions.RayError) as exc:
                got, waiting = exc, False
            ref = None
            if waiting:
                if time.monotonic() < deadline:
                    time.sleep(0.2)
                    continue
                got = TimeoutError(f"no new actor in {wait:g} s")
            elif pid is not None:
                self.pids[w] = pid
            if isinstance(got, ConfigError | NetError):  # bad input fails alike in every restart
                raise got
            if not isinstance(got, BaseException):
                return got
            failures += 1
            if failures >= START_ATTEMPTS:
                raise SimulationError(f"rollout actor {w} could not start its env {START_ATTEMPTS} times in a row; "
                                      f"last failure: {got}")
            dead_pid = self.pids[w]
            self._restart(w, got)
            deadline = time.monotonic() + wait

    def _restart(self, w: int, reason: BaseException) -> None:
        self.restarts += 1
        if self.restarts > self.max_restarts:
            raise SimulationError(f"rollout actor {w} failed; {self.restarts} failures in total exceed "
                                  f"train.max_restarts = {self.max_restarts}; last failure: {reason}")
        log.warning("rollout actor %d failed (%s); Ray restarts it (restart %d of at most %d)", w,
                    str(reason).splitlines()[0], self.restarts, self.max_restarts)
        exceptions = self.ray.exceptions
        if isinstance(reason, exceptions.RayActorError):
            return  # its process is gone: Ray restarts it by itself (a kill now would end the new one too)
        # A live actor whose env is broken or that hangs (SIGSTOP): killing it with restart makes Ray build it
        # anew from its constructor, on any node with a free CPU.
        try:
            self.ray.kill(self.actors[w], no_restart=False)
        except exceptions.RayError:
            pass

    def _send(self, ws: Sequence[int], cmd: str, args: Sequence[Any]) -> None:
        for w, arg in zip(ws, args, strict=True):
            self._pending[w] = getattr(self.actors[w], cmd).remote(arg)

    def recv(self, ws: Sequence[int]) -> list[StepResult]:
        """Results of the last command sent to each worker of `ws`; a failed actor is restarted and `lost`."""
        n = len(self.spec.agents)
        out = []
        for w in ws:
            try:
                result, obs, final = self._get(self._pending.pop(w), self.timeout)
                result = copy.deepcopy(result)  # Ray hands out read-only views of its object store
                self.obs[w] = obs
                if final is not None:
                    self.final[w] = final
                out.append(result)
            except (TimeoutError, WorkerFailure, self.ray.exceptions.RayError) as exc:
                dead_pid = self.pids[w]
                self._restart(w, exc)
                if self._ready(w, dead_pid=dead_pid) != self.spec:
                    raise SimulationError(f"rollout actor {w} was restarted with another env spec") from None
                self.obs[w] = 0
                out.append(StepResult.lost_episode(n, self.spec.n_actions, failure_line(exc)))
        return out

    def close(self) -> None:
        ray = self.ray
        if self.actors:
            try:
                ray.get([a.close.remote() for a in self.actors], timeout=10.0)
            except (ray.exceptions.RayError, TimeoutError):
                pass
            for actor in self.actors:
                try:
                    ray.kill(actor, no_restart=True)
                except ray.exceptions.RayError:
                    pass
        self.actors = []
        remove_leftovers()  # on this machine, those of actors that died before their close
        if self._started_ray:
            ray.shutdown()
            self._started_ray = False
