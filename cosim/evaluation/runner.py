"""`cosim evaluate`: run trained AVs (a checkpoint) or a baseline on evaluation seeds; write CSV, JSON, plots.

Contract:
- `evaluate(cfg, policy, out_dir, ...)` runs `episodes` episodes with seeds `seed, seed + 1, ...`; the
  default first seed, `cosim.config.EVAL_SEED_START` = 10,000,000, keeps evaluation disjoint from training,
  whose episode seeds are drawn below it (`agents.train.episode_seed`). Policies: `checkpoint` (a trained
  run; greedy argmax actions, or sampled), `sumo` (SUMO's own models drive the AVs: an all-human road),
  `idle`, `random`, `scripted` (`cosim.environment.policies`).
- Into `out_dir` go: `evaluation.json` (what was evaluated, with `config_sha256`, the hash of the resolved
  config), `config.yaml` (the resolved config), `episodes.csv` (one row per episode, appended and flushed
  as each finishes: the env's episode summary (`MergeEnv.episode_summary`: crash and crash by class, merge
  and time to merge, distance and mean speed by class, the merging vehicle's distance, the guide AV and its
  actions), SUMO's throughput [veh/h], time loss [s] and mean speed [m/s] over the flow window, and
  `distance_check`, the largest |our odometer - SUMO's tripinfo routeLength| [m] over the episode's
  vehicles), `summary.json` (each
  metric's mean and interval, `cosim.evaluation.stats.summarize`, written atomically), `trajectories/seed_S.npz` for
  the first `trajectories` episodes, `sumo/episode_S/` (SUMO's tripinfo and induction-loop files) and
  `plots/`.
- `summarize_evaluation(eval_dir, first_seed, episodes, confidence)` picks the rows of the requested seeds
  from `episodes.csv` and summarises them: `evaluate` and `cosim compare` both report through it.
- Resume: a second call with the same `out_dir` skips the seeds already in `episodes.csv`; a folder
  holding an evaluation of another policy / checkpoint / net / config (`config_sha256`; the folder's
  location, `sim.output_dir`, is not part of it) is refused.
- `workers > 1` runs episodes in spawned worker processes (libsumo runs one simulation per process).
- Bad input raises a `CosimError`: episodes or workers < 1 or trajectories < 0 (a `ConfigError`), no
  checkpoint in the run folder, a checkpoint whose observation shape or agents do not fit the net/preset,
  a net without a merge (from the net description).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import logging
import math
import multiprocessing as mp
import multiprocessing.util
import shutil
import signal
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from cosim.cli import Heartbeat, add_config_arguments
from cosim.config import EVAL_SEED_START, Config, load_config, parse_section
from cosim.environment.control import Action
from cosim.environment.merge_env import MergeEnv
from cosim.environment.policies import POLICIES
from cosim.errors import ConfigError, CosimError
from cosim.evaluation.stats import format_table, summarize
from cosim.files import AppendCsv, atomic_path, atomic_write_text

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint"  # the policy name of a trained run
SB3 = "sb3"  # a Stable-Baselines3 PPO model (scripts/train_sb3.py), from --checkpoint
TRAINED = (CHECKPOINT, SB3)
BASELINES = ("sumo", "idle", "random", "scripted", "courteous")
# Config overrides a policy needs: the all-human baseline hands the AVs to SUMO.
POLICY_OVERRIDES: dict[str, dict[str, Any]] = {"sumo": {"sim.av_driver": "sumo"}}


@dataclass(frozen=True)
class EvaluateConfig:
    """The config's `evaluate:` section (all optional; command-line flags override)."""

    episodes: int = 100  # evaluation episodes
    seed: int = EVAL_SEED_START  # first evaluation seed; training seeds stay below it
    greedy: bool = True  # argmax actions; false: sampled from the policy
    trajectories: int = 3  # first episodes whose per-step trajectories are kept for plots
    workers: int = 1  # worker processes
    confidence: float = 0.95  # of the intervals in the summary


def evaluate_config(section: Mapping[str, Any]) -> EvaluateConfig:
    """Validate the `evaluate:` section; unknown keys and wrong types raise `ConfigError`."""
    ec = parse_section(EvaluateConfig, section, "evaluate")
    if ec.episodes < 1 or ec.workers < 1 or ec.trajectories < 0 or not 0 < ec.confidence < 1:
        raise ConfigError("evaluate: need episodes >= 1, workers >= 1, trajectories >= 0, 0 < confidence < 1")
    return ec


def check_counts(episodes: int, workers: int, trajectories: int, prefix: str = "") -> None:
    """`ConfigError` unless episodes >= 1, workers >= 1 and trajectories >= 0 (`prefix`: e.g. "--" for flags)."""
    for name, value, least in (("episodes", episodes, 1), ("workers", workers, 1), ("trajectories", trajectories, 0)):
        if value < least:
            raise ConfigError(f"{prefix}{name}: must be >= {least}, got {value}")


# -- policies ------------------------------------------------------------------------------------------
Observations = dict[str, np.ndarray]
ActPolicy = Callable[[Observations], dict[str, int]]  # live agents' observations -> their actions


@dataclass(frozen=True)
class PolicySpec:
    name: str  # one of TRAINED or BASELINES
    checkpoint: str | None = None  # the checkpoint (CHECKPOINT) or model file (SB3)
    greedy: bool = True


def make_policy(spec: PolicySpec, env: MergeEnv) -> Callable[[int], ActPolicy]:
    """A factory: episode seed -> the policy for that episode (seeded, so results do not depend on workers)."""
    if spec.name == CHECKPOINT:
        return _checkpoint_policy(Path(spec.checkpoint or ""), env, spec.greedy)
    if spec.name == SB3:
        return _sb3_policy(Path(spec.checkpoint or ""), env, spec.greedy)
    if spec.name == "sumo":  # actions are ignored when SUMO drives; send idle
        return lambda seed: lambda obs: dict.fromkeys(obs, int(Action.IDLE))
    if spec.name not in POLICIES:
        raise ConfigError(f"--policy {spec.name}: unknown; expected one of {[*TRAINED, *BASELINES]}")
    builder = POLICIES[spec.name]

    def for_episode(seed: int) -> ActPolicy:
        policy = builder(seed)
        return lambda obs: policy(env)

    return for_episode


def _checkpoint_policy(path: Path, env: MergeEnv, greedy: bool) -> Callable[[int], ActPolicy]:
    import torch  # only a trained policy needs torch

    from agents.checkpoint import CheckpointError, act_agents, load_policy

    nets, meta = load_policy(path)
    spec = meta["spec"]
    agents = env.possible_agents
    shape = tuple(env.observation_space(agents[0]).shape)
    if tuple(spec["obs_shape"]) != shape:
        raise CheckpointError(
            f"checkpoint {path}: observations of shape {tuple(spec['obs_shape'])}, but this net/preset gives "
            f"{shape} (observation preset {env.cfg.observation.preset!r}); evaluate with the run's config")
    missing = [a for a in agents if a not in nets]
    if missing or spec["n_actions"] != env.action_space(agents[0]).n:
        raise CheckpointError(f"checkpoint {path}: trained for agents {sorted(nets)} with {spec['n_actions']} "
                              f"actions; this scenario has {agents} with {env.action_space(agents[0]).n}")

    def for_episode(seed: int) -> ActPolicy:
        torch.manual_seed(seed)  # sampled actions are reproducible per episode
        return lambda obs: act_agents(nets, obs, greedy)

    return for_episode


def _sb3_policy(path: Path, env: MergeEnv, greedy: bool) -> Callable[[int], ActPolicy]:
    import torch

    from agents.checkpoint import act_agents

    try:
        from agents.sb3 import load_actor
    except ImportError as exc:
        raise ConfigError(f"--policy sb3: {exc.name} is missing; pip install -e \".[sb3]\" installs it") from None
    space = env.observation_space(env.possible_agents[0])
    actor = load_actor(path, tuple(space.shape), int(env.action_space(env.possible_agents[0]).n))
    actors = dict.fromkeys(env.possible_agents, actor)  # one network for all AVs

    def for_episode(seed: int) -> ActPolicy:
        torch.manual_seed(seed)  # sampled actions are reproducible per episode
        return lambda obs: act_agents(actors, obs, greedy)

    return for_episode


# -- episodes ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """Everything a worker needs, picklable."""

    config: dict[str, Any]  # Config.to_dict() with the evaluation's overrides
    policy: PolicySpec
    out_dir: str
    record: frozenset[int]  # seeds whose trajectories are saved


class Runner:
    """One env and one policy in this process; `run(seed)` plays an episode and returns its row."""

    def __init__(self, job: Job) -> None:
        self.job = job
        self.env = MergeEnv(load_config(job.config))
        try:
            self.policy = make_policy(job.policy, self.env)
        except BaseException:  # e.g. a checkpoint that does not fit: free the process's SUMO slot
            self.env.close()
            raise

    def run(self, seed: int) -> dict[str, Any]:
        env = self.env
        act = self.policy(seed)
        obs, _ = env.reset(seed=seed)
        # The env's own tracker gives the row; a second one records the trajectories of the plotted episodes.
        recorder = env.new_tracker(record=True) if seed in self.job.record else None
        if recorder is not None:
            recorder.observe(env.snapshot)
        returns = dict.fromkeys(env.possible_agents, 0.0)
        infos: dict[str, Any] = {}
        while env.agents:
            actions = act(obs)
            obs, rewards, _, _, infos = env.step(actions)
            for a, r in rewards.items():
                returns[a] += r
            if recorder is not None:
                recorder.observe(env.snapshot, actions if env.session.drive_avs else None)
        env.flush_outputs()
        summary = next(iter(infos.values()))["episode"]  # every agent's last info carries it
        row = {"seed": seed, "policy": self.job.policy.name, **summary,
               "av_return": float(np.mean(list(returns.values())))}
        sumo = env.sumo_outputs.pop(seed, None)
        if sumo is not None:
            row.update(sumo.as_row())
            ours = env.window_distance
            row["distance_check"] = max((abs(ours[v] - sumo.distance[v]) for v in ours if v in sumo.distance),
                                        default=math.nan)
        if recorder is not None:
            _save_npz(Path(self.job.out_dir) / "trajectories" / f"seed_{seed}.npz", recorder.trajectory())
        return row

    def close(self) -> None:
        self.env.close()


_RUNNER: Runner | None = None  # the worker process's runner


def _worker_init(job: Job, tmp_root: str) -> None:
    global _RUNNER
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    tempfile.tempdir = tmp_root  # the parent removes it, also after a worker was killed
    if job.policy.name in TRAINED:
        import torch

        torch.set_num_threads(1)  # W workers on W cores
    _RUNNER = Runner(job)
    mp.util.Finalize(_RUNNER, _RUNNER.close, exitpriority=10)  # closes the env when the pool ends


def _worker_run(seed: int) -> dict[str, Any]:
    assert _RUNNER is not None
    return _RUNNER.run(seed)


def run_episodes(job: Job, seeds: Sequence[int], workers: int = 1) -> Iterator[dict[str, Any]]:
    """Rows of the given episodes as they finish (in seed order with one worker, else as they come)."""
    if workers <= 1 or len(seeds) <= 1:
        runner = Runner(job)
        try:
            for seed in seeds:
                yield runner.run(seed)
        finally:
            runner.close()
        return
    ctx = mp.get_context("spawn")
    tmp_root = tempfile.mkdtemp(prefix="cosim_eval_")
    pool = ctx.Pool(min(workers, len(seeds)), initializer=_worker_init, initargs=(job, tmp_root))
    try:
        yield from pool.imap_unordered(_worker_run, seeds)
        pool.close()  # the workers exit on their own, closing their envs
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
        shutil.rmtree(tmp_root, ignore_errors=True)


# -- files ---------------------------------------------------------------------------------------------
def _save_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def read_rows(path: Path) -> list[dict[str, str]]:
    """Rows of an episodes.csv (a half-written last line from an interrupted run is dropped)."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return [r for r in rows if r.get("seed") and None not in r.values()]


def summarize_evaluation(eval_dir: Path, first_seed: int, episodes: int,
                         confidence: float = 0.95) -> tuple[list[dict[str, str]], dict[str, dict[str, float | int]]]:
    """(rows, metrics): the episodes.csv rows of seeds `first_seed .. first_seed + episodes - 1` in seed order
    (one per seed), and their `summarize`d metrics. Rows of other seeds in the file are left out."""
    wanted = range(first_seed, first_seed + episodes)
    by_seed = {int(r["seed"]): r for r in read_rows(Path(eval_dir) / "episodes.csv") if int(r["seed"]) in wanted}
    rows = [by_seed[s] for s in sorted(by_seed)]
    return rows, summarize(rows, confidence)


def scenario_hash(config: Mapping[str, Any]) -> str:
    """sha256 of what makes the episodes themselves (net, simulation, scenario, drivers, observation), leaving out
    what policies may differ in when compared: the reward (the SVO angle) and who drives the AVs."""
    kept = {k: v for k, v in config.items() if k not in ("train", "evaluate", "reward")}
    kept["sim"] = {k: v for k, v in config.get("sim", {}).items() if k not in ("output_dir", "av_driver")}
    return hashlib.sha256(json.dumps(kept, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def config_hash(config: Mapping[str, Any]) -> str:
    """sha256 of a resolved config (`Config.to_dict()`) as canonical JSON, over what shapes the episodes: not
    `sim.output_dir` (where the folder is: a moved or copied evaluation still resumes), nor the `train` and
    `evaluate` sections (how many episodes and workers; the policy is compared on its own)."""
    kept = {k: v for k, v in config.items() if k not in ("train", "evaluate")}
    kept["sim"] = {k: v for k, v in config.get("sim", {}).items() if k != "output_dir"}
    text = json.dumps(kept, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def trajectory_files(out_dir: Path) -> list[Path]:
    return sorted((out_dir / "trajectories").glob("seed_*.npz"), key=lambda p: int(p.stem.split("_")[1]))


def load_trajectory(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


# -- the evaluation ------------------------------------------------------------------------------------
def evaluate(cfg: Config, policy: PolicySpec, out_dir: Path, episodes: int, seed: int = EVAL_SEED_START,
             workers: int = 1, trajectories: int = 3, confidence: float = 0.95, run_dir: Path | None = None,
             plots: bool = True) -> dict[str, Any]:
    """Evaluate `policy` on episodes `seed .. seed + episodes - 1` into `out_dir`; returns the summary dict
    (also written to `out_dir/summary.json`). Resumes an interrupted evaluation in the same folder."""
    check_counts(episodes, workers, trajectories)
    out_dir = Path(out_dir).resolve()
    overrides = {**POLICY_OVERRIDES.get(policy.name, {}), "sim.outputs": True,
                 "sim.output_dir": str(out_dir / "sumo")}
    cfg = load_config(cfg, overrides)
    meta = {"policy": policy.name, "checkpoint": policy.checkpoint, "greedy": policy.greedy,
            "net": cfg.net.file, "run": None if run_dir is None else str(Path(run_dir).resolve()),
            "config_sha256": config_hash(cfg.to_dict()), "scenario_sha256": scenario_hash(cfg.to_dict()),
            "trained_updates": _trained_updates(policy),
            # An SB3 model has no update counter: its content tells a retrained model from the evaluated one.
            "model_sha256": (hashlib.sha256(Path(policy.checkpoint).read_bytes()).hexdigest()
                             if policy.name == SB3 and policy.checkpoint else None)}
    seeds = [seed + k for k in range(episodes)]
    job = Job(cfg.to_dict(), policy, str(out_dir), frozenset(seeds[:trajectories]))
    Runner(job).close()  # bad nets and checkpoints fail here, before the folder is claimed
    _claim(out_dir, meta, cfg)
    csv_path = out_dir / "episodes.csv"
    writer = AppendCsv(csv_path)  # first: it drops a half-written last row
    done = {int(r["seed"]) for r in read_rows(csv_path)}
    todo = [s for s in seeds if s not in done]
    if done & set(seeds):
        log.info("resuming %s: %d of %d episodes already done", out_dir, len(done & set(seeds)), episodes)
    headless, heartbeat = not sys.stderr.isatty(), Heartbeat(30.0)
    for k, row in enumerate(tqdm(run_episodes(job, todo, workers), total=len(todo), desc=f"evaluate {policy.name}",
                                 unit="ep", leave=False, disable=headless), start=1):
        writer.write(row)
        if headless and heartbeat():
            log.info("evaluate %s: %d of %d episodes", policy.name, k, len(todo))
    rows, metrics = summarize_evaluation(out_dir, seed, episodes, confidence)
    checks = [float(r["distance_check"]) for r in rows if r.get("distance_check") not in (None, "", "nan")]
    summary = {**meta, "episodes": len(rows), "first_seed": seed, "requested_episodes": episodes,
               "confidence": confidence, "metrics": metrics,
               "distance_check_max_m": max(checks) if checks else math.nan}
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2, allow_nan=True) + "\n")
    if checks and max(checks) > 0.5:
        log.warning("our distances and SUMO's tripinfo differ by up to %.2f m", max(checks))
    if plots:
        from cosim.evaluation.compare import plot_run  # matplotlib only when plotting

        plot_run(out_dir, out_dir / "plots", label=policy.name, rows=rows)
    return summary


def _trained_updates(policy: PolicySpec) -> int | None:
    """Which state of a checkpoint is evaluated: a run trained further must not resume its old evaluation."""
    if policy.name != CHECKPOINT or policy.checkpoint is None:
        return None
    from agents.checkpoint import load_policy

    updates = load_policy(policy.checkpoint)[1]["counters"].get("updates")
    return None if updates is None else int(updates)


def _claim(out_dir: Path, meta: dict[str, Any], cfg: Config) -> None:
    """Write evaluation.json and config.yaml, or check that an existing evaluation is the same one."""
    path = out_dir / "evaluation.json"
    if path.is_file():
        old = json.loads(path.read_text())
        # trained_updates, model_sha256: only where recorded (folders from before they were).
        later = ("trained_updates", "model_sha256")
        differs = [k for k in ("policy", "checkpoint", "greedy", "net", *later)
                   if old.get(k) != meta[k] and (k in old or k not in later)]
        if differs:
            raise CosimError(f"{out_dir}: holds an evaluation with other {', '.join(differs)} "
                             f"({', '.join(f'{k}={old.get(k)!r}' for k in differs)}); choose another --out")
        # Folders from before the hash was stored: hash their config.yaml.
        old_hash = old.get("config_sha256") or config_hash(yaml.safe_load((out_dir / "config.yaml").read_text()))
        if old_hash != meta["config_sha256"]:
            raise ConfigError(f"{out_dir}: holds an evaluation with another config (see its config.yaml; a "
                              f"different --set, --config or net?); resuming would mix episodes of both in one "
                              f"summary: choose another --out")
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    atomic_write_text(path, json.dumps(meta, indent=2) + "\n")


def print_summary(summary: Mapping[str, Any], label: str) -> None:
    """The one print of the command: the summary table."""
    print(format_table({label: summary["metrics"]}, {label: summary["episodes"]},
                       confidence=summary.get("confidence", 0.95)))


# -- command line --------------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, default=None)
    parser.add_argument("--run", type=Path, help="training run folder (its config.yaml and checkpoint.pt)")
    parser.add_argument("--checkpoint", type=Path, help="checkpoint file (default: RUN/checkpoint.pt)")
    parser.add_argument("--policy", choices=[*TRAINED, *BASELINES], default=None,
                        help="a baseline instead of a checkpoint: sumo (SUMO drives the AVs), idle, random, "
                             "scripted (egoistic), courteous (lets the merging vehicle in); or sb3, a "
                             "Stable-Baselines3 model given by --checkpoint (scripts/train_sb3.py) "
                             "(default: checkpoint)")
    parser.add_argument("--episodes", type=int, help="evaluation episodes (default: evaluate.episodes, 100)")
    parser.add_argument("--net", type=Path, help="evaluate on another .net.xml (its description is found "
                                                 "beside it or inferred)")
    parser.add_argument("--seed", type=int, help=f"first evaluation seed (default: {EVAL_SEED_START:,}, disjoint "
                                                 "from training seeds)")
    parser.add_argument("--workers", type=int, help="worker processes (default: 1)")
    parser.add_argument("--sample", action="store_true", help="sample actions instead of the greedy argmax")
    parser.add_argument("--trajectories", type=int, help="episodes whose trajectories are plotted (default: 3)")
    parser.add_argument("--out", type=Path, help="output folder (default: RUN/eval)")
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")


def run(args: argparse.Namespace) -> int:
    name = args.policy or CHECKPOINT
    if args.run is not None and not (args.run / "config.yaml").is_file():
        raise CosimError(f"--run {args.run}: not a training run folder (no config.yaml; `cosim train` writes one)")
    config = args.config or (args.run / "config.yaml" if args.run else "configs/default.yaml")
    overrides = list(args.overrides)
    if args.net is not None:
        if not args.net.is_file():
            raise ConfigError(f"--net {args.net}: not found")
        overrides += [f"net.file={args.net.resolve()}", "net.description=null"]
    cfg = load_config(config, overrides)
    ec = evaluate_config(cfg.evaluate)
    episodes = ec.episodes if args.episodes is None else args.episodes
    workers = ec.workers if args.workers is None else args.workers
    trajectories = ec.trajectories if args.trajectories is None else args.trajectories
    check_counts(episodes, workers, trajectories, prefix="--")
    checkpoint = None
    if name == SB3:
        if args.checkpoint is None or not args.checkpoint.is_file():
            raise CosimError(f"--policy sb3: give the model file with --checkpoint FILE (got {args.checkpoint})")
        checkpoint = str(args.checkpoint.resolve())
    if name == CHECKPOINT:
        if args.run is None and args.checkpoint is None:
            raise CosimError("cosim evaluate: give --run RUN (or --checkpoint FILE) for a trained policy, "
                             f"or --policy {{{','.join(BASELINES)}}} for a baseline")
        from agents.checkpoint import CHECKPOINT_NAME, POLICY_NAME  # torch: a trained policy needs it anyway

        # The small policy file where the run has one (the networks alone), else the resumable checkpoint.
        checkpoint = args.checkpoint or next((args.run / n for n in (POLICY_NAME, CHECKPOINT_NAME)
                                              if (args.run / n).is_file()), args.run / CHECKPOINT_NAME)
        if not checkpoint.is_file():
            raise CosimError(f"checkpoint {checkpoint}: not found; train the run first (cosim train), pass "
                             f"--checkpoint FILE, or evaluate a baseline with --policy")
        checkpoint = str(checkpoint.resolve())
    out = args.out or (args.run / "eval" if args.run else None)
    if out is None:
        raise CosimError("cosim evaluate: give --out DIR for a baseline without --run")
    policy = PolicySpec(name, checkpoint, greedy=ec.greedy and not args.sample)
    summary = evaluate(cfg, policy, out, episodes=episodes, seed=ec.seed if args.seed is None else args.seed,
                       workers=workers, trajectories=trajectories,
                       confidence=ec.confidence, run_dir=args.run, plots=not args.no_plots)
    log.info("wrote %s", Path(out) / "summary.json")
    print_summary(summary, out.name if args.run is None else args.run.name)
    return 0
