"""Multi-agent actor-critic training (paper Section 4; A2C or PPO) over W rollout workers: `cosim train`.

Contract: `train(cfg, out_dir, ...)` trains the AVs of `cfg` until `train.episodes` episodes have finished in
total or the `train.budget_min` wall-clock budget is spent (both over the whole run, resumes included),
writing into `out_dir`: `config.yaml` (the resolved config), `checkpoint.pt` (every `train.checkpoint_every`
updates, at the end, and on Ctrl-C or SIGTERM, which stop the run after the update in progress),
`updates.csv`, `episodes.csv` and TensorBoard files under `tb/`. `resume=True` continues the run in `out_dir`
from its checkpoint: same parameters, optimizer and value-normaliser state, RNG states and counters; episode
seeds follow from (seed, update, worker), so a resumed run continues the same sequence as an uninterrupted one.
It returns a `TrainResult`; `cosim train` (cosim/cli.py) calls it.

The run folder has one writer (`cosim.files.FolderLock`, held from the first check of the folder to the end of
the run): a second `train` into it is refused while the first lives. A stop in the middle of an update (a second
Ctrl-C) writes the checkpoint of the last complete update, exact: its parameters, optimizer and RNG states and
counters are kept aside as each update begins, and the logs are cut back to it. A resume refuses a `config.yaml`
that is not a YAML mapping, and warns, naming the file and both counts, when `episodes.csv` or `updates.csv`
lacks rows the checkpoint counts (deleted or cut: the run goes on, its log without them).

One update: every worker plays one whole episode (`agents.collect`), then the network(s) learn from every
sample the scheme allows (`agents.multiagent`). Samples of absent agents and episodes lost to a worker
failure are masked out, never padded into the loss. With `train.segments` an update is a segment of
`train.segment_steps` decisions of every worker's continuing episodes instead (`agents.collect.Segments`: a worker
starts its next episode as one ends; a resumed run starts new ones). Under demand (`demand.enabled`) it always is,
of every worker's continuing run, agents indexed by observation slot, one shared network; an episode is one run
(warm-up and window), and its row in `episodes.csv` holds the run's reward per AV released. The runs in progress
at a stop are not in the checkpoint (SUMO's state is not saved): a resumed run starts new runs, so it continues
with other runs than an uninterrupted one would.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
import math
import random
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm import tqdm

from agents.checkpoint import (
    BEST_NAME,
    CHECKPOINT_NAME,
    NET_RECORD,
    POLICY_NAME,
    CheckpointError,
    check_spec,
    load_policy,
    read_checkpoint,
    rng_state,
    save_checkpoint,
    save_policy,
    set_rng_state,
)
from agents.collect import Collected, Segments, collect
from agents.config import TrainConfig, check_device, train_config
from agents.logs import RunLogger, cut_logs, log_gaps
from agents.multiagent import Batch, MultiAgentPolicy
from agents.rollout import Backend
from agents.validation import (
    MOVING_SHARE,
    better,
    constant_action,
    describe,
    moving_threshold,
    summarize,
    validate,
    validation_seeds,
)
from cosim.config import EVAL_SEED_START, Config, SafetyConfig, read_yaml
from cosim.errors import ConfigError, EpisodeError, NetError
from cosim.files import FolderLock, FolderState, atomic_write_text, stale_temporaries
from cosim.progress import Heartbeat
from cosim.sumo.setting import Setting
from cosim.workers import WORKER_MIB, EnvFactory, check_memory

log = logging.getLogger(__name__)

TORCH_THREADS = torch.get_num_threads()  # torch's default, before any run of this process set its own
# validated: the episodes trained when the last validation ran (train.eval_every)
COUNTERS = ("episodes", "updates", "samples", "restarts", "lost_episodes", "validated", "egoistic_until")
# The env's summary keys an episodes.csv row carries: of an episode, and of a run under demand.
EPISODE_KEYS = ("crashed", "merged", "mean_distance", "merger_distance", "length", "cause_av", "cause_hv_into_av",
                "cause_merger", "merger_alt")
DEMAND_KEYS = ("length", "avs_released", "collisions", "collisions_window", "merge_rate_pct", "crash_rate_pct",
               "throughput_total_vph", "throughput_mainline_vph", "throughput_ramp_vph", "delay_mean_s",
               "delay_ramp_s")


@dataclass(frozen=True)
class TrainResult:
    out_dir: Path
    checkpoint: Path
    episodes: int  # finished episodes counted as data, over the whole run
    updates: int
    samples: int  # valid agent-samples collected, over the whole run
    restarts: int  # rollout worker restarts, over the whole run
    lost_episodes: int  # episodes dropped because their worker failed
    interrupted: bool  # stopped by Ctrl-C or SIGTERM (the checkpoint holds the last complete update)
    recent_return: float  # mean per-agent episode return over the last 100 episodes of this call
    wall_s: float  # [s] of this call
    rollout_s: float  # [s] of this call spent collecting (env steps + acting)
    update_s: float  # [s] of this call spent in gradient updates
    new_samples: int  # agent-samples collected by this call
    train_s: float  # [s] of training over the whole run (what `budget_min` limits)


def episode_seed(seed: int, update: int, worker: int) -> int:
    """The training episode of `worker` in update `update`: reproducible, and below the evaluation seeds."""
    return int(np.random.SeedSequence([seed, update, worker]).generate_state(1)[0]) % EVAL_SEED_START


# Keys a resume may change without --allow-config-change: how long and how a run is run, not what it learns; the
# safety measures only count what happens (a run from before the section existed resumes without it).
RESUMABLE = frozenset({"train.episodes", "train.budget_min", "train.checkpoint_every", "train.log_every",
                       "train.eval_every", "train.eval_episodes", "train.init_from",
                       "train.log_every_s", "train.step_timeout", "train.max_restarts", "train.torch_threads",
                       "train.device", *(f"safety.{key}" for key in SafetyConfig.model_fields)})
# What a run from before a key existed did, for the resume's comparison: it trained without action masks, and
# without a safety layer.
UNRECORDED = {"train.action_mask": False, "av.shield": "none", "train.segment_steps": 64, "train.segments": False,
              "demand.exit": "terminated"}


def _from_config(exc: CheckpointError) -> CheckpointError:
    """A start the config asked for (train.init_from) that cannot be had, with the way out."""
    return CheckpointError(f"train.init_from: {exc}; set train.init_from=null to train from scratch, or pass "
                           "--init-from POLICY")


def run_config(cfg: Config, tc: TrainConfig) -> dict[str, Any]:
    """What a run's config.yaml holds: the resolved config with the train section as trained."""
    return {**cfg.to_dict(), "train": tc.model_dump()}


def flat_keys(data: Any, prefix: str = "") -> dict[str, Any]:
    """A config's nested sections as one mapping of dotted keys ("train.seed") to values."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for k, v in data.items():
            out.update(flat_keys(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: data}


def config_changes(saved: Path, new: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """Dotted key -> (the run's value, the new one) for every key that differs, RESUMABLE keys left out."""
    if not saved.is_file():
        raise CheckpointError(f"--resume: {saved} not found; the run folder is incomplete")
    # The run's config, which a resume compares with the user's: what to do when it is damaged.
    hint = "it is the run's config, which a resume compares with yours: restore it, or train into another --out"
    try:
        loaded = read_yaml(saved)
    except ConfigError as exc:
        raise ConfigError(f"--resume: {exc}; {hint}") from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"--resume: {saved}: not a mapping of config sections; {hint}")
    old = {**UNRECORDED, **flat_keys(loaded)}
    now = flat_keys(yaml.safe_load(yaml.safe_dump(new)))  # the same YAML types on both sides
    return {k: (old.get(k), now.get(k)) for k in sorted(set(old) | set(now))
            if old.get(k) != now.get(k) and k not in RESUMABLE}


def _started_from(saved: Path) -> str | None:
    """The policy a run started from, as its config.yaml (read by `config_changes` already) records it."""
    return flat_keys(read_yaml(saved)).get("train.init_from")


def _record_changes(out_dir: Path, changes: dict[str, tuple[Any, Any]], update: int) -> None:
    path = out_dir / "config_changes.yaml"
    history = yaml.safe_load(path.read_text()) if path.is_file() else []
    history.append({"at_update": update, "time": time.strftime("%Y-%m-%d %H:%M:%S"),
                    "changes": {k: {"from": old, "to": new} for k, (old, new) in changes.items()}})
    atomic_write_text(path, yaml.safe_dump(history, sort_keys=False))


def _resumed_record(record: Path, where: dict[str, Any]) -> None:
    """On resume: warn when the run's net file is not the one it trained on so far (same path, other content), and
    keep in `where` (the record the resume writes) the policy the run started from, a fact of the run that the
    resuming command does not repeat (`--init-from` starts runs only)."""
    try:
        before = json.loads(record.read_text(encoding="utf-8"))
        sha = before["net"]["sha256"]
    except (OSError, ValueError, KeyError, TypeError):
        return  # a run from before nets were recorded, or a damaged record: nothing to compare
    if "init_from" in before:
        where["init_from"] = before["init_from"]
    if sha != where["net"]["sha256"]:
        log.warning("%s: the net %s changed since this run began (sha256 %s, now %s): the run goes on, on the new one",
                    record, where["net"]["file"], sha[:12], where["net"]["sha256"][:12])


def _check_memory(cfg: Config, tc: TrainConfig, backend: Backend, setting: Setting | None) -> None:
    """A run whose batch and (local) worker processes need more memory than this machine has is refused before any
    of it is allocated or started."""
    obs = cfg.observation
    values = math.prod(obs.shape)
    if cfg.demand.enabled:
        assert setting is not None and setting.demand is not None
        steps, agents, who = tc.segment_steps, setting.demand.slots, "AV slots"
    else:
        steps = tc.segment_steps if tc.segments else max(1, round(cfg.sim.horizon / cfg.sim.decision_period))
        agents, who = cfg.scenario.n_avs, "AVs"
    batch = steps * tc.workers * agents * values * np.dtype(obs.dtype).itemsize
    parts = [(f"one update's batch ({steps:,} decision steps x {tc.workers} workers x {agents} {who} x "
              f"{values:,} observation values)", batch)]
    if backend.name == "local":
        parts.append((f"{tc.workers} worker processes", tc.workers * WORKER_MIB << 20))
    check_memory(parts, "lower train.segment_steps (under demand or with segments) or sim.horizon, train.workers "
                        "(--workers), scenario.n_avs or the observation's size")


def _check_demand(setting: Setting, tc: TrainConfig) -> None:
    """What training under demand cannot do, refused before anything starts."""
    assert setting.demand is not None
    decisions = max(1, round(setting.demand.horizon / setting.config.sim.decision_period))
    if tc.segment_steps >= decisions:
        raise ConfigError(f"train.segment_steps: {tc.segment_steps} decisions, not shorter than a run ({decisions} "
                          f"decisions of demand.warmup + demand.window); give fewer")
    if not tc.shared_policy:
        raise ConfigError("train.shared_policy: false: under demand AVs come and go, each a new agent; one network "
                          "per AV has no AV to belong to: set train.shared_policy: true")


def _default_env_factory(cfg: Config) -> EnvFactory:
    from cosim.environment.factory import parallel_env  # the meeting point of agents/ and cosim/, through PettingZoo

    return functools.partial(parallel_env, cfg.to_dict())


def train(cfg: Config, out_dir: Path, *, workers: int | None = None, episodes: int | None = None,
          budget_min: float | None = None, resume: bool = False, device: str | None = None,
          env_factory: EnvFactory | None = None, progress: bool | None = None,
          allow_config_change: bool = False, backend: str = "local", ray_address: str | None = None,
          overrides: Sequence[str] = (), init_from: Path | None = None) -> TrainResult:
    """Train (or, with `resume`, continue training) the AVs of `cfg` into `out_dir` (see module doc); `overrides`:
    the command line's, recorded in the run's net.json; `init_from`: a new run starts from the networks of this
    policy file or run (`agents.checkpoint.load_policy`) with a fresh optimizer, recorded in net.json (else from
    the config's `train.init_from`, which a resume ignores)."""
    run = _Run.open(cfg, Path(out_dir), workers, episodes, budget_min, resume, device, env_factory,
                    allow_config_change, progress, Backend(backend, ray_address), overrides, init_from)
    try:
        with StopRequest() as stop:
            while not run.finished() and not stop.requested:
                run.begin_update()
                got = run.collect()
                stats = run.learn()
                run.log(got, stats)
                run.end_update()
                run.maybe_checkpoint()
                run.maybe_validate()
            if not stop.requested:
                run.maybe_validate(final=True)  # best.pt weighs the final policy too
        run.interrupted = stop.requested
    except KeyboardInterrupt:  # a second Ctrl-C, or one outside the loop
        run.interrupted = True
    except (ConfigError, NetError, EpisodeError):  # the input's fault: the folder as it was, then say why
        run.failed = True
        raise
    finally:
        with StopRequest.held(replay=False):
            run.close()
    return run.result()


class StopRequest:
    """SIGINT / SIGTERM during training ask to stop after the update in progress, so that the final checkpoint
    is an update boundary and a resume continues the same sequence; a second signal stops at once."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():  # only there can Python handle signals
            self.previous = {sig: signal.signal(sig, self._handle) for sig in self.SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)

    @staticmethod
    @contextmanager
    def held(replay: bool = True) -> Iterator[None]:
        """SIGINT / SIGTERM held back while a checkpoint is written (cut by KeyboardInterrupt, torch's zip writer fails
        with a traceback of its own and the write is lost): with `replay`, sent again once it is whole, to whatever
        handles them then; without, said and ignored (the run is stopping already)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        got: list[int] = []

        def hold(signum: int, frame: object) -> None:
            got.append(signum)
            if not replay:
                log.warning("%s: writing the final checkpoint, then stopping", signal.Signals(signum).name)

        previous = {sig: signal.signal(sig, hold) for sig in StopRequest.SIGNALS}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        for sig in got if replay else ():
            signal.raise_signal(sig)

    def _handle(self, signum: int, frame: object) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("%s: stopping after the update in progress (send it again to stop at once)",
                    signal.Signals(signum).name)


class _Run:
    """The state of one training run and its steps, each named for what `train` does with it."""

    @classmethod
    def open(cls, cfg: Config, out_dir: Path, workers: int | None, episodes: int | None, budget_min: float | None,
             resume: bool, device: str | None, env_factory: EnvFactory | None, allow_change: bool = False,
             progress: bool | None = None, backend: Backend | None = None, overrides: Sequence[str] = (),
             init_from: Path | None = None) -> _Run:
        """Every check on the input and the run folder, before anything in the folder changes."""
        backend = backend or Backend()
        backend.check()
        if init_from is not None and resume:
            raise ConfigError(f"--init-from {init_from}: starts a new run; --resume continues one from its own "
                              "checkpoint: give one of the two")
        # The config's start (train.init_from) only where neither the command line nor a resume says otherwise.
        configured = init_from is None and not resume and cfg.train.init_from is not None
        if configured:
            init_from = Path(cfg.train.init_from)
        try:
            start = load_policy(init_from) if init_from is not None else None  # a bad file fails here, at once
        except CheckpointError as exc:
            raise _from_config(exc) if configured else exc from None
        if start is not None:
            start[1]["configured"] = configured
        # The config on its net, resolved once: the demand's checks and the run's record read it.
        setting = Setting.of(cfg) if cfg.demand.enabled or env_factory is None else None
        tc = train_config(cfg)
        if setting is not None and setting.demand is not None:
            _check_demand(setting, tc)
        tc = tc.model_copy(update={"workers": workers or tc.workers, "episodes": episodes or tc.episodes,
                                   "budget_min": tc.budget_min if budget_min is None else budget_min,
                                   "device": device or tc.device})
        check_device(tc.device, "--device")
        _check_memory(cfg, tc, backend, setting)
        if tc.device.startswith("cuda") and not torch.cuda.is_available():
            raise ConfigError(f"--device {tc.device}: CUDA is not available on this machine")
        if out_dir.exists() and not out_dir.is_dir():
            raise ConfigError(f"--out {out_dir}: is a file, not a folder")
        lock = FolderLock(out_dir, "cosim train")
        lock.acquire(create=False)  # a live run's files are its own, even to read: refused before any check
        before = FolderState.capture(out_dir)
        try:
            ckpt_path = out_dir / CHECKPOINT_NAME
            if not resume and ckpt_path.exists():
                raise CheckpointError(f"checkpoint {ckpt_path}: exists already; pass --resume to continue that run "
                                      "or choose another --out")
            payload = read_checkpoint(ckpt_path) if resume else None
            changes = config_changes(out_dir / "config.yaml", run_config(cfg, tc)) if resume else {}
            # The run's config names the policy it started from, whoever asked for it (`--init-from` or the key), and
            # keeps naming it over resumes, whose command lines do not: `--config RUN/config.yaml` then starts the
            # same way, and a reader of the config needs no other record.
            began = start[1]["path"] if start is not None else None
            if resume:
                began = _started_from(out_dir / "config.yaml")
            tc = tc.model_copy(update={"init_from": None if began is None else str(Path(began).resolve())})
            if changes and not allow_change:
                listed = "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changes.items())
                # A run from before a key existed: its config.yaml lacks the key, which reads as today's default.
                older = [f"--set {k}={yaml.safe_dump(old).splitlines()[0]}" for k, (old, _) in changes.items()
                         if k in UNRECORDED and old == UNRECORDED[k]]
                keys = "that key" if len(older) == 1 else "those keys"
                how = f" {' '.join(older)}: the run is from before {keys} existed" if older else ""
                raise ConfigError(f"--resume {out_dir}: the config differs from the run's ({listed}); resume with "
                                  f"the run's config (cosim train --config RUN/config.yaml{how}), or pass "
                                  "--allow-config-change to continue with the new one (recorded in "
                                  "RUN/config_changes.yaml)")
            if payload is not None:
                counters = payload["counters"]
                logged_every = int(payload.get("train", {}).get("log_every", tc.log_every))
                for gap in log_gaps(out_dir, int(counters["updates"]), int(counters["episodes"]), logged_every):
                    log.warning("%s", gap)
            where = setting.record(overrides) if setting is not None and env_factory is None else None
            if where is not None and resume:
                _resumed_record(out_dir / NET_RECORD, where)
            if where is not None and start is not None:
                where["init_from"] = start[1]["path"]
            offered = (setting.demand.mainline_total + setting.demand.ramp_vph
                       if setting is not None and setting.demand is not None else None)
            return cls(cfg, tc, out_dir, payload, env_factory or _default_env_factory(cfg), changes, progress,
                       backend, lock, before, where, start, offered)
        except BaseException:
            lock.release()
            raise

    def __init__(self, cfg: Config, tc: TrainConfig, out_dir: Path, payload: dict[str, Any] | None,
                 env_factory: EnvFactory, changes: dict[str, tuple[Any, Any]] | None = None,
                 progress: bool | None = None, backend: Backend | None = None, lock: FolderLock | None = None,
                 before: FolderState | None = None, where: dict[str, Any] | None = None,
                 start: tuple[dict[str, Any], dict[str, Any]] | None = None,
                 offered_vph: float | None = None) -> None:
        self.cfg, self.tc, self.out_dir = cfg, tc, out_dir
        # Under demand: the flow offered, and the throughput best.pt asks first (agents.validation.better).
        self.offered_vph = offered_vph
        self.moving_vph = None if offered_vph is None else moving_threshold(offered_vph)
        self.before = before or FolderState.capture(out_dir)
        self.failed = False  # a CosimError stopped the run (set by `train`)
        self.checkpointed: dict[str, int] | None = None  # the counters of this command's last checkpoint
        self.lock = lock or FolderLock(out_dir, "cosim train")
        self.ckpt_path = out_dir / CHECKPOINT_NAME
        self.counters = {k: 0 for k in COUNTERS}
        self.train_s = 0.0  # over the whole run
        self.best: dict[str, float] | None = None  # the validation row of best.pt
        if payload is not None:
            self.counters.update({k: int(v) for k, v in payload["counters"].items() if k in COUNTERS})
            self.train_s = float(payload["counters"].get("train_s", 0.0))
            self.best = payload.get("best")
        # While the workers step, the learner's forwards take one thread: a second one would take a core from SUMO
        # and wait at OpenMP's barriers whenever the kernel gives that core to a worker; the update, with the workers
        # idle, takes all cores (scripts/bench_train.py measured both). train.torch_threads fixes both.
        self.threads = {"act": tc.torch_threads or 1, "update": tc.torch_threads or TORCH_THREADS}
        # The initial weights too depend on the thread count (orthogonal init's QR), whatever ran before here.
        torch.set_num_threads(self.threads["update"])
        random.seed(tc.seed)
        np.random.seed(tc.seed)
        torch.manual_seed(tc.seed)
        self.pool = (backend or Backend()).pool(env_factory, tc.workers, tc.max_restarts, tc.step_timeout)
        try:
            spec = self.pool.spec
            self.agents = spec.agents
            self.spec = {"agents": list(spec.agents), "obs_shape": list(spec.obs_shape), "obs_dtype": spec.obs_dtype,
                         "n_actions": spec.n_actions, "shared_policy": tc.shared_policy,
                         "feature_dim": tc.feature_dim, "head_hidden": tc.head_hidden,
                         "shared_encoder": tc.shared_encoder, "obs_norm": tc.obs_norm,
                         "feature_norm": tc.feature_norm, "central_critic": tc.central_critic}
            self.policy = MultiAgentPolicy(len(spec.agents), spec.obs_shape, spec.n_actions, tc, tc.device)
            # Which one `auto` chose decides whether the run is reproducible bit for bit (README).
            log.info("forward passes in %s (train.precision: %s)",
                     "bfloat16" if self.policy.bf16 else "float32", tc.precision)
            if start is not None:
                self._start_from(*start)
            if payload is not None:
                check_spec(payload, self.spec, self.ckpt_path)
                self.policy.load_state_dict(payload["policy"])
                set_rng_state(payload["rng"])
                log.info("resumed %s at update %d, episode %d", self.ckpt_path, self.counters["updates"],
                         self.counters["episodes"])
            # Storage for one update, allocated once: T steps x W workers x N agents (under demand: AV slots).
            self.demand = cfg.demand.enabled
            # train.egoistic_episodes' curriculum: the episodes trained on each AV's own utility (none where every
            # angle is 0, whose reward that is already, nor under demand, where it was not measured). A run that
            # starts from a trained policy skips it (the counter's -1 keeps that over resumes): it learnt to drive.
            self.warmup = tc.egoistic_episodes if any(cfg.phis()) else 0
            if self.warmup and self.demand:
                self.warmup = 0
                log.info("train.egoistic_episodes: no egoistic warm-up under demand (measured on episodes only)")
            elif self.warmup and start is not None:
                self.counters["egoistic_until"] = -1
                log.info("train.egoistic_episodes: no egoistic warm-up for a run that starts from a trained policy")
            elif self.counters["episodes"] < self.warmup and not self.counters["egoistic_until"]:
                log.info("egoistic warm-up: episodes %d-%d train on each AV's own utility (phi = 0), the rest on "
                         "reward.phi's reward (train.egoistic_episodes)", self.counters["episodes"] + 1, self.warmup)
            self.segments = Segments(self.pool, self.demand) if self.demand or tc.segments else None
            self.batch = Batch.allocate(tc.segment_steps if self.segments else spec.max_steps, tc.workers,
                                        len(spec.agents), spec.obs_shape, getattr(torch, spec.obs_dtype),
                                        spec.n_actions)
            # Every check passed: from here on the run folder changes.
            self.lock.acquire()
            for stale in [p for name in (CHECKPOINT_NAME, POLICY_NAME, BEST_NAME)
                          for p in stale_temporaries(out_dir, name)]:
                log.info("removing %s, left by a checkpoint write that was killed", stale)
                stale.unlink()
            if changes:
                log.warning("resuming with a changed config: %s", ", ".join(changes))
                _record_changes(out_dir, changes, self.counters["updates"])
            atomic_write_text(out_dir / "config.yaml", yaml.safe_dump(run_config(cfg, tc), sort_keys=False))
            if where is not None:
                atomic_write_text(out_dir / NET_RECORD, json.dumps(where, indent=2) + "\n")
            self.logger = RunLogger(out_dir, self.counters["updates"], self.counters["episodes"])
        except BaseException:
            self.pool.close()
            raise
        self.restarts_before = self.counters["restarts"]
        self.interrupted = False
        self.boundary: dict[str, Any] | None = None  # the checkpoint payload as the update in progress began
        self.start = time.perf_counter()
        self.start_samples = self.counters["samples"]
        self.timing = {"rollout": 0.0, "update": 0.0}
        self.batch_stats: dict[str, float] = {}
        # A progress bar on a terminal; periodic log lines otherwise (a log file gets no bar frames).
        self.headless = not sys.stderr.isatty() if progress is None else not progress
        self.heartbeat = Heartbeat(tc.log_every_s)
        self.bar = tqdm(total=tc.episodes, initial=min(self.counters["episodes"], tc.episodes), unit="ep",
                        dynamic_ncols=True, disable=self.headless, desc="train")

    def _start_from(self, nets: dict[str, Any], meta: dict[str, Any]) -> None:
        """Every network of this run from `nets` (`load_policy`'s), which must fit the run's spec."""
        path = meta["path"]
        try:
            check_spec({"spec": meta["spec"]}, {k: self.spec[k] for k in ("obs_shape", "n_actions", "feature_dim",
                                                                          "head_hidden", "shared_encoder",
                                                                          "obs_norm", "feature_norm",
                                                                          "central_critic")},
                       Path(path))
        except CheckpointError as exc:
            raise _from_config(exc) if meta.get("configured") else exc from None
        for name, net in zip(self.agents, self.policy.nets, strict=False):  # one per AV, or the shared one
            source = next(iter(nets.values())) if meta["spec"]["shared_policy"] else nets.get(name)
            if source is None:
                raise CheckpointError(f"--init-from {path}: one network per AV, for {sorted(nets)}; none for {name}")
            net.load_state_dict(source.state_dict())
        for k in range(len(self.policy.acting)):  # per AV: the frozen acting copies start alike
            self.policy.disseminate(k)
        log.info("starting from the networks of %s (trained %d episodes there), with a fresh optimizer", path,
                 int(meta["counters"].get("episodes", 0)))

    # -- the steps of `train` -----------------------------------------------------------------------------
    def progress(self) -> float:
        """Fraction of the run done: of its episodes, or of its time budget if that is further along."""
        budget = self.tc.budget_min * 60.0
        return max(self.counters["episodes"] / self.tc.episodes, self.train_s / budget if budget else 0.0)

    def finished(self) -> bool:
        return self.progress() >= 1.0

    def begin_update(self) -> None:
        # Kept aside (a copy: learning changes the tensors in place), so that a stop at any point of the update
        # checkpoints the run exactly as it was at this boundary; a copy of the policy state costs a fraction
        # of the update's episodes, and of the checkpoint write.
        self.boundary = self.payload(copy_policy=True)

    def end_update(self) -> None:
        self.boundary = None

    def next_seeds(self) -> list[int]:
        """One episode seed per worker of this update; fewer workers when fewer episodes remain."""
        n = min(self.tc.workers, self.tc.episodes - self.counters["episodes"])
        return [episode_seed(self.tc.seed, self.counters["updates"], w) for w in range(n)]

    def collect(self) -> Collected:
        torch.set_num_threads(self.threads["act"])
        t0 = time.perf_counter()
        update = self.counters["updates"]
        warming = bool(self.warmup) and not self.counters["egoistic_until"]  # the warm-up neither over nor skipped
        egoistic = warming and self.counters["episodes"] < self.warmup
        if warming and not egoistic:
            self.end_warmup()
        with self.policy.collecting():
            if self.segments is not None:
                starts = [0] * self.tc.workers

                def seed_of(w: int) -> int:  # the k-th episode a worker starts in this update: (update, w + k W)
                    starts[w] += 1
                    return episode_seed(self.tc.seed, update, w + (starts[w] - 1) * self.tc.workers)

                got = self.segments.collect(self.policy, self.batch, update, seed_of, egoistic)
            else:
                got = collect(self.pool, self.policy, self.batch, self.next_seeds(), update, egoistic)
        self.timing["rollout"] += time.perf_counter() - t0
        self._rollout_s = time.perf_counter() - t0
        return got

    def end_warmup(self) -> None:
        """`train.egoistic_episodes` are done: from this update on the AVs train on reward.phi's reward, with a fresh
        optimizer and value normaliser (the returns' scale changes), as a run started from this policy would."""
        self.policy.restart_learning(self.tc)
        self.counters["egoistic_until"] = self.counters["episodes"]
        log.info("egoistic warm-up over at episode %d: training on reward.phi's reward from here, with a fresh "
                 "optimizer and value normaliser", self.counters["episodes"])

    def learn(self) -> dict[str, float]:
        torch.set_num_threads(self.threads["update"])
        t0 = time.perf_counter()
        update = self.counters["updates"]
        stats = self.policy.update(self.batch, self.tc, update, self.progress())
        if self.policy.ends_block(update):
            self.policy.disseminate(self.policy.learner(update))
        dt = time.perf_counter() - t0
        self.timing["update"] += dt
        self.train_s += self._rollout_s + dt
        return stats

    def log(self, got: Collected, stats: dict[str, float]) -> None:
        c = self.counters
        c["updates"] += 1
        c["samples"] += got.samples
        c["lost_episodes"] += got.lost
        c["restarts"] = self.restarts_before + self.pool.restarts
        rows = []
        for ep in got.episodes:
            c["episodes"] += 1
            row: dict[str, Any] = {"episode": c["episodes"], "update": c["updates"], "seed": ep.seed,
                                   "return_mean": float(ep.returns.mean())}
            if not self.demand:  # under demand the agent axis is slots, each held by many AVs in turn
                row.update({f"return_{a}": float(r) for a, r in zip(self.agents, ep.returns, strict=True)})
            for key in DEMAND_KEYS if self.demand else EPISODE_KEYS:
                row[key] = float(ep.info.get(key, float("nan")))
            row.update({f"term_{name}": float(v.mean()) for name, v in sorted(ep.terms.items())})
            rows.append(row)
            self.logger.episode(row)
        self.bar.update(len(got.episodes))
        sps = (c["samples"] - self.start_samples) / max(time.perf_counter() - self.start, 1e-9)
        self.logger.episodes_to_tb(c["updates"], rows)
        if c["updates"] % self.tc.log_every == 0:
            self.logger.update({"update": c["updates"], "episodes": c["episodes"], "samples": c["samples"],
                                "samples_per_s": sps, "train_s": self.train_s, "restarts": c["restarts"], **stats})
        if self.demand:  # an episode is a run of minutes: its collisions, not a crash of the episode
            rates = {"collisions": self.logger.rate("collisions"), "ret": self.logger.rate("return_mean")}
            said = f"runs, recent collisions per run {rates['collisions']:.1f} return per AV {rates['ret']:.2f}"
        else:
            rates = {"crash": self.logger.rate("crashed"), "merge": self.logger.rate("merged"),
                     "ret": self.logger.rate("return_mean")}
            said = (f"episodes, recent crash {rates['crash']:.2f} merge {rates['merge']:.2f} return "
                    f"{rates['ret']:.2f}")
        self.bar.set_postfix(sps=f"{sps:.0f}", **{k: f"{v:.2f}" for k, v in rates.items()}, refresh=False)
        if self.headless and self.heartbeat():
            log.info("update %d, %d/%d %s, %.0f agent-samples/s, loss %.3f entropy %.3f, %.0f s trained",
                     c["updates"], c["episodes"], self.tc.episodes, said, sps, stats.get("loss", float("nan")),
                     stats.get("entropy", float("nan")), self.train_s)

    def maybe_checkpoint(self) -> None:
        if self.counters["updates"] % self.tc.checkpoint_every == 0:
            self.checkpoint()

    def maybe_validate(self, final: bool = False) -> None:
        """Validate (agents.validation) when another `train.eval_every` episodes have passed since the last time,
        or, `final`, when the run's last episodes were not validated yet; keep best.pt, then checkpoint, so that
        the checkpoint knows the best so far."""
        c, every = self.counters, self.tc.eval_every
        if not every or not (c["episodes"] // every > c["validated"] // every
                             or (final and c["episodes"] > c["validated"])):
            return
        torch.set_num_threads(self.threads["act"])
        t0 = time.perf_counter()
        fig = summarize(validate(self.pool, self.policy, validation_seeds(self.tc.eval_episodes), c["updates"]))
        spent = time.perf_counter() - t0
        self.train_s += spent  # the budget is wall-clock time, validation's included
        c["validated"] = c["episodes"]
        best = better(fig, self.best, self.moving_vph)
        row = {"update": c["updates"], "episodes": c["episodes"], "samples": c["samples"], "train_s": self.train_s,
               "validation_s": spent, **fig, "best": int(best)}
        self.logger.validation(row)
        if best:
            self.best = row
            with StopRequest.held():
                save_policy(self.out_dir / BEST_NAME, self.payload(), validation=row)
        what = "runs" if self.demand else "episodes"
        log.info("validation at %s %d (%d greedy %s, %.0f s): %s%s", what[:-1], c["episodes"],
                 fig["episodes_validated"], what, spent, describe(fig),
                 f"; best so far, kept as {BEST_NAME}" if best else "")
        if self.moving_vph is not None and fig["throughput"] < self.moving_vph:
            log.warning("the greedy policy carries %.0f veh/h, under %.0f%% of the flow offered (%.0f veh/h): it does "
                        "not keep traffic moving, and best.pt prefers any validation that does", fig["throughput"],
                        100 * MOVING_SHARE, self.offered_vph)
        constant = constant_action(fig)
        if constant is not None:
            log.warning("the greedy policy took action %d at %.1f%% of its validation decisions: the validation "
                        "measures that one action, not what the sampling policy has learned (the runs of "
                        "episodes.csv); such a policy has not learned when to do otherwise yet", constant,
                        fig[f"greedy_action_{constant}"])
        if self.segments is not None:  # validation reset the workers: the next segment starts new runs
            self.segments.drop()
        self.checkpoint()

    def payload(self, copy_policy: bool = False) -> dict[str, Any]:
        """The checkpoint of the run as it is now."""
        policy = self.policy.state_dict()
        return {"spec": self.spec, "policy": copy.deepcopy(policy) if copy_policy else policy,
                "counters": {**self.counters, "train_s": self.train_s}, "rng": rng_state(),
                "train": self.tc.model_dump(), "config": self.cfg.to_dict(), "phis": list(self.cfg.phis()),
                "best": self.best}

    def checkpoint(self, payload: dict[str, Any] | None = None) -> None:
        payload = payload or self.payload()
        with StopRequest.held():
            save_checkpoint(self.ckpt_path, payload)
        self.checkpointed = {k: int(payload["counters"][k]) for k in ("updates", "episodes")}

    def close(self) -> None:
        """The final checkpoint (of the last complete update when stopped inside one), then the folder is free."""
        try:
            restarts = self.restarts_before + self.pool.restarts  # the update in progress's restarts did happen
            if self.failed:
                self._undo()
            elif self.boundary is None:
                self.counters["restarts"] = restarts
                self.checkpoint()
                if self.interrupted:
                    log.warning("stopped at update %d; wrote a checkpoint to %s", self.counters["updates"],
                                self.ckpt_path)
            else:  # stopped inside an update: its parameters and counters are neither before nor after it
                partial = self.boundary["counters"]["updates"] + 1
                self.boundary["counters"]["restarts"] = restarts
                self.counters = {k: self.boundary["counters"][k] for k in COUNTERS}
                self.train_s = self.boundary["counters"]["train_s"]
                self.checkpoint(self.boundary)
                cut_logs(self.out_dir, self.counters["updates"], self.counters["episodes"])
                log.warning("stopped during update %d: wrote a checkpoint of the last complete update (%d) to %s",
                            partial, self.counters["updates"], self.ckpt_path)
        finally:
            self.bar.close()
            self.pool.close()
            self.logger.close()
            self.lock.release()

    def _undo(self) -> None:
        """After a failure of the input: the folder as the command found it, or, where this command checkpointed
        already, as at that checkpoint (its logs cut back to it; the checkpoint is a complete update)."""
        self.logger.close()
        if self.checkpointed is None:
            self.before.restore()
            log.warning("the run folder %s is as it was before this command", self.out_dir)
        else:
            cut_logs(self.out_dir, self.checkpointed["updates"], self.checkpointed["episodes"])
            log.warning("the run folder %s holds this command's last checkpoint (update %d); resume it once the "
                        "cause is fixed", self.out_dir, self.checkpointed["updates"])

    def result(self) -> TrainResult:
        c = self.counters
        return TrainResult(self.out_dir, self.ckpt_path, c["episodes"], c["updates"], c["samples"], c["restarts"],
                           c["lost_episodes"], self.interrupted, self.logger.rate("return_mean"),
                           time.perf_counter() - self.start, self.timing["rollout"], self.timing["update"],
                           c["samples"] - self.start_samples, self.train_s)
