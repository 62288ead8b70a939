"""`cosim evaluate`: a policy's episodes on evaluation seeds, written as CSV, JSON and plots.

Contract:
- `evaluate(cfg, policy, out_dir, ...)` runs `episodes` episodes with seeds `seed, seed + 1, ...`; the
  default first seed, `cosim.config.EVAL_SEED_START` = 10,000,000, keeps evaluation disjoint from training,
  whose episode seeds are drawn below it (`agents.train.episode_seed`). A policy follows the `Policy`
  protocol: `Baseline(name)` for `sumo` (SUMO's own models drive the AVs: an all-human road), `idle`,
  `random`, `scripted`, `courteous` (`cosim.environment.policies`); trained ones come from `agents`
  (`agents.checkpoint.TrainedPolicy`, `agents.sb3.Sb3Policy`) without this package importing them.
- Into `out_dir` go: `evaluation.json` (what was evaluated: the policy's identity, `config_sha256`, the hash
  of the resolved config, and `scenario_sha256`), `config.yaml` (the resolved config), `episodes.csv` (one
  row per episode, appended and flushed as each finishes: the env's episode summary (crash and crash by class
  and cause, merge and time to merge, distance and mean speed by class, the merging vehicle's distance, the
  guide AV and its actions), SUMO's throughput [veh/h], time loss [s] and mean speed [m/s] over the flow
  window, and `distance_check`, the largest |our odometer - SUMO's tripinfo routeLength| [m] over the
  episode's vehicles), `summary.json` (each metric's mean and interval over the requested seeds,
  `cosim.evaluation.store.summarize_evaluation`, written atomically), `trajectories/seed_S.npz` for the first
  `trajectories` episodes, `sumo/episode_S/` (SUMO's tripinfo and induction-loop files), `plots/` (with
  `video_seed_S.mp4` or `.gif` for the first `videos` episodes, `cosim.evaluation.video`) and `report.md` (the
  table, the figures and links to the videos), where the evaluation is called `evaluation_label` (the trained
  run's name, else the policy's), as in `cosim evaluate`'s table.
- Resume: a second call with the same `out_dir` skips the seeds already in `episodes.csv`; a folder
  holding an evaluation of another policy / checkpoint / net / config is refused, each known by its content
  where it was recorded (`model_sha256`, `net_sha256`, `config_sha256` without the folder's and the net's paths),
  so a folder moved or cloned with its net and policy resumes; `summary.json` stands in for a missing
  `evaluation.json`, and episodes that neither accounts for are refused. One writer per folder
  (`cosim.files.FolderLock`, held from the first look at the folder to the summary): a second evaluation into it
  is refused while the first lives. An evaluation that fails before its first episode leaves the folder as it
  found it, and a folder that holds no finished episode is anyone's: nothing blocks the corrected rerun.
- `workers > 1` runs episodes on `cosim.workers.WorkerPool` (libsumo runs one simulation per process); a
  worker that gives no step for `evaluate.step_timeout` seconds is replaced (logged), and an episode whose
  worker failed is played again by its replacement.
- Bad input raises a `CosimError`: episodes or workers < 1 or trajectories or videos < 0 (a `ConfigError`), a
  checkpoint whose observation shape or agents do not fit the net/preset, a net without a merge.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml
from tqdm import tqdm

from cosim.config import EVAL_SEED_START, VALIDATION_SEED_START, Config, load_config
from cosim.environment.control import Action
from cosim.environment.factory import parallel_env
from cosim.environment.flow_metrics import demand_setting, demand_summary
from cosim.environment.merge_env import MergeEnv
from cosim.environment.policies import POLICIES
from cosim.errors import ConfigError, CosimError, EpisodeError, check_at_least
from cosim.evaluation.store import config_hash, save_trajectory, scenario_hash, summarize_evaluation
from cosim.files import AppendCsv, FolderLock, FolderState, atomic_write_text, read_csv, write_json
from cosim.progress import Heartbeat
from cosim.workers import START_TIMEOUT, WORKER_MIB, WorkerPool, check_memory, keep_alive

log = logging.getLogger(__name__)

BASELINES = ("sumo", "idle", "random", "scripted", "courteous")


def check_counts(episodes: int, workers: int, trajectories: int, prefix: str = "", videos: int = 0) -> None:
    """`ConfigError` unless episodes >= 1, workers >= 1, trajectories >= 0 and videos >= 0 (`prefix`: e.g. "--"
    for flags)."""
    for name, value, least in (("episodes", episodes, 1), ("workers", workers, 1), ("trajectories", trajectories, 0),
                               ("videos", videos, 0)):
        check_at_least(prefix + name, value, least)


def _warn_unless_held_out(seeds: Sequence[int]) -> None:
    """A trained policy's figures on seeds it trained on or was chosen on (best.pt, by validation) test nothing:
    said, not refused (a user may want them)."""
    trained = sum(s < EVAL_SEED_START for s in seeds)
    validated = sum(s >= VALIDATION_SEED_START for s in seeds)
    where = [text for n, text in ((trained, f"{trained} below {EVAL_SEED_START:,}, where training draws its episodes"),
                                  (validated, f"{validated} from {VALIDATION_SEED_START:,}, the validation seeds "
                                              "best.pt is chosen on")) if n]
    if where:
        log.warning("evaluation seeds %d..%d: %s; a trained policy's figures there are not held out (the evaluation "
                    "seeds: %s to %s)", seeds[0], seeds[-1], " and ".join(where), f"{EVAL_SEED_START:,}",
                    f"{VALIDATION_SEED_START - 1:,}")


# -- policies ------------------------------------------------------------------------------------------
Observations = dict[str, np.ndarray]
ActPolicy = Callable[[Observations], dict[str, int]]  # live agents' observations -> their actions


class Policy(Protocol):
    """What `evaluate` runs. Picklable: each worker process loads it for its own env. Trained policies
    (`agents.checkpoint.TrainedPolicy`, `agents.sb3.Sb3Policy`) follow it without this package importing them."""

    name: str  # recorded as evaluation.json's "policy"
    overrides: Mapping[str, Any]  # config overrides the policy needs

    def identity(self) -> dict[str, Any]:
        """What tells this policy's state from another's ({checkpoint, greedy, trained_updates, model_sha256}):
        recorded in evaluation.json; an evaluation folder holding another one is not resumed."""
        ...

    def load(self, env: MergeEnv, worker: bool) -> Callable[[int], ActPolicy]:
        """A factory: episode seed -> the policy for that episode (seeded, so results do not depend on workers);
        `worker`: in an evaluation worker process (one of several on the machine's cores)."""
        ...


@dataclass(frozen=True)
class Baseline:
    """A hand-written policy of `cosim.environment.policies`, or `sumo`: SUMO's own models drive the AVs."""

    name: str  # one of BASELINES

    def __post_init__(self) -> None:
        if self.name not in BASELINES:
            raise ConfigError(f"--policy {self.name}: unknown; expected one of {['checkpoint', 'sb3', *BASELINES]}")

    @property
    def overrides(self) -> Mapping[str, Any]:
        return {"sim.av_driver": "sumo"} if self.name == "sumo" else {}

    def identity(self) -> dict[str, Any]:
        return {"checkpoint": None, "greedy": True, "trained_updates": None, "model_sha256": None}

    def load(self, env: MergeEnv, worker: bool) -> Callable[[int], ActPolicy]:
        if self.name == "sumo":  # actions are ignored when SUMO drives; send idle
            return lambda seed: lambda obs: dict.fromkeys(obs, int(Action.IDLE))
        builder = POLICIES[self.name]

        def for_episode(seed: int) -> ActPolicy:
            policy = builder(seed)
            return lambda obs: policy(env)

        return for_episode


# -- episodes ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """Everything a worker needs, picklable."""

    config: dict[str, Any]  # Config.to_dict() with the evaluation's overrides
    policy: Policy
    out_dir: str
    record: frozenset[int]  # seeds whose trajectories are saved
    videos: frozenset[int] = frozenset()  # seeds whose videos are written ...
    video_dir: str = ""  # ... into this folder (`cosim.evaluation.video`)


class Runner:
    """One env and one policy in this process; `run(seed)` plays an episode and returns its row."""

    def __init__(self, job: Job, env: MergeEnv, worker: bool = False) -> None:
        self.job = job
        self.env = env
        self.video: Path | None = None  # the last video written
        try:
            self.policy = job.policy.load(self.env, worker)
        except BaseException:  # e.g. a checkpoint that does not fit: free the process's SUMO slot
            self.env.close()
            raise

    def run(self, seed: int) -> dict[str, Any]:
        """The episode's row; with its seed in `job.videos` (or with sumo-gui) what a person sees of it too
        (`cosim.evaluation.video.EpisodeView`): its video in `job.video_dir` (`self.video`: the file)."""
        env = self.env
        act = self.policy(seed)
        view = None
        if seed in self.job.videos or env.session.gui is not None:
            from cosim.evaluation.video import EpisodeView  # matplotlib only for videos

            view = EpisodeView(env, video=seed in self.job.videos)
        obs, _ = env.reset(seed=seed)
        if view is not None:
            view.start()
        keep_alive()  # in a worker: each step restarts its timeout (evaluate.step_timeout)
        # The env's own tracker gives the row; a second one records the trajectories of the plotted episodes.
        recorder = env.new_tracker(record=True) if seed in self.job.record else None
        if recorder is not None:
            recorder.observe(env.snapshot)
        returns: dict[str, float] = {}  # of every agent that acted (in demand mode, AVs come and go)
        while env.agents:
            actions = act(obs)
            if view is not None:
                view.decide(actions)
            obs, rewards, _, _, _ = env.step(actions)
            for a, r in rewards.items():
                returns[a] = returns.get(a, 0.0) + r
            if recorder is not None:
                recorder.observe(env.snapshot, actions if env.session.drive_avs else None)
            keep_alive()
        if view is not None:
            view.stop()
        env.flush_outputs()
        row = {"seed": seed, "policy": self.job.policy.name, **env.last_summary,
               "av_return": float(np.mean(list(returns.values()))) if returns else math.nan}
        if view is not None and view.video:
            title = f"{self.job.policy.name}, episode seed {seed}"
            self.video = view.write(Path(self.job.video_dir) / f"video_seed_{seed}", title)
        sumo = env.sumo_outputs.pop(seed, None)
        if sumo is not None:
            row.update(sumo.as_row())
            ours = env.window_distance
            row["distance_check"] = max((abs(ours[v] - sumo.distance[v]) for v in ours if v in sumo.distance),
                                        default=math.nan)
        if recorder is not None:
            save_trajectory(Path(self.job.out_dir) / "trajectories" / f"seed_{seed}.npz", recorder.trajectory())
        return row

    def close(self) -> None:
        self.env.close()


_RUNNER: Runner | None = None  # a worker process's runner, built at its first episode


@dataclass(frozen=True)
class _Lost:
    why: str  # the failure's first line


def _play(env: MergeEnv, job_seed: tuple[Job, int]) -> dict[str, Any]:
    """A worker's episode (`WorkerPool.send_call`): the policy is loaded once per process."""
    global _RUNNER
    job, seed = job_seed
    if _RUNNER is None or _RUNNER.job != job:
        keep_alive(START_TIMEOUT)  # loading a trained policy takes longer than a step
        _RUNNER = Runner(job, env, worker=True)
    return _RUNNER.run(seed)


def run_episodes(job: Job, seeds: Sequence[int], workers: int = 1,
                 max_restarts: int = 3) -> Iterator[dict[str, Any]]:
    """Rows of the given episodes as they finish (in seed order with one worker, else round by round).

    Several workers run on `cosim.workers.WorkerPool`; a worker silent for `evaluate.step_timeout` within an
    episode is replaced, and an episode whose worker failed is played again by the replacement, up to
    `max_restarts` failures over the evaluation; one that fails again on its fresh worker stops the evaluation
    (`EpisodeError`): the same seed failing twice is the episode's own fault."""
    if workers <= 1 or len(seeds) <= 1:
        runner = Runner(job, parallel_env(job.config))
        try:
            for seed in seeds:
                yield runner.run(seed)
        finally:
            runner.close()
        return
    pool = WorkerPool(functools.partial(parallel_env, job.config), min(workers, len(seeds)), max_restarts,
                      timeout=load_config(job.config).evaluate.step_timeout, timeout_key="evaluate.step_timeout",
                      restarts_key="an evaluation's max_restarts")
    try:
        todo = list(seeds)
        failed: dict[int, str] = {}  # seed -> why its first worker failed
        while todo:
            batch, todo = todo[:len(pool)], todo[len(pool):]
            ws = list(range(len(batch)))
            pool.send_call(ws, _play, [(job, s) for s in batch])
            for seed, row in zip(batch, pool.recv(ws, lost=_Lost), strict=True):
                if not isinstance(row, _Lost):
                    yield row
                elif seed in failed:  # a fresh worker failed on it too: the episode's own fault, not bad luck
                    raise EpisodeError(f"evaluation episode (seed {seed}) fails the same way on a fresh worker: "
                                          f"{row.why}")
                else:
                    failed[seed] = row.why
                    todo.append(seed)  # its worker failed and was replaced: play the episode again
    finally:
        pool.close()


# -- the evaluation ------------------------------------------------------------------------------------
def evaluate(cfg: Config, policy: Policy, out_dir: Path, episodes: int, seed: int = EVAL_SEED_START,
             workers: int = 1, trajectories: int = 3, confidence: float = 0.95, run_dir: Path | None = None,
             plots: bool = True, overrides: Sequence[str] = (), videos: int = 0) -> dict[str, Any]:
    """Evaluate `policy` on episodes `seed .. seed + episodes - 1` into `out_dir`; returns the summary dict
    (also written to `out_dir/summary.json`, with what it ran on: `cosim.sumo.setting.Setting.record`, the
    command line's `overrides` included; `report.md` words it). Resumes an interrupted evaluation in the same
    folder."""
    check_counts(episodes, workers, trajectories, videos=videos)
    started = min(workers, episodes) if workers > 1 else 0
    check_memory([(f"{started} worker processes", started * WORKER_MIB << 20)], "lower --workers")
    out_dir = Path(out_dir).resolve()
    cfg = load_config(cfg, {**policy.overrides, "sim.outputs": True, "sim.output_dir": str(out_dir / "sumo")})
    if cfg.demand.enabled:  # a run of minutes: its figures are the flow's, not per-episode trajectories or videos
        if videos:
            log.warning("--videos %d: a demand run has no episode videos; its flow figures (speed heatmap, "
                        "time-space diagram of the merge area) show it", videos)
        trajectories = videos = 0
    identity = policy.identity()
    seeds = [seed + k for k in range(episodes)]
    job = Job(cfg.to_dict(), policy, str(out_dir), frozenset(seeds[:trajectories]), frozenset(seeds[:videos]),
              str(out_dir / "plots"))
    lock = FolderLock(out_dir, "cosim evaluate")
    lock.acquire(create=False)  # an evaluation under way there is refused before its files are read
    before = FolderState.capture(out_dir)
    csv_path = out_dir / "episodes.csv"
    try:
        # Bad nets and checkpoints fail here, before the folder is claimed; the env's setting is the run's.
        probe = Runner(job, parallel_env(job.config))
        on_net = probe.env.setting
        probe.close()
        where = on_net.record(overrides, seeds)
        meta = {"policy": policy.name, "checkpoint": identity["checkpoint"], "greedy": identity["greedy"],
                "net": cfg.net.file, "net_sha256": where["net"]["sha256"], "config": cfg.source,
                "run": None if run_dir is None else str(Path(run_dir).resolve()),
                "config_sha256": config_hash(cfg.to_dict()), "scenario_sha256": scenario_hash(cfg.to_dict()),
                "trained_updates": identity["trained_updates"], "model_sha256": identity["model_sha256"]}
        if identity["trained_updates"] is not None:
            _warn_unless_held_out(seeds)
        lock.acquire()
        _claim(out_dir, meta, cfg)
        writer = AppendCsv(csv_path)  # first: it drops a half-written last row
        done = {int(r["seed"]) for r in read_csv(csv_path, ints=("seed",))}
        todo = [s for s in seeds if s not in done]
        if done & set(seeds):
            log.info("resuming %s: %d of %d episodes already done", out_dir, len(done & set(seeds)), episodes)
        headless, heartbeat = not sys.stderr.isatty(), Heartbeat(30.0)
        for k, row in enumerate(tqdm(run_episodes(job, todo, workers), total=len(todo),
                                     desc=f"evaluate {policy.name}", unit="ep", leave=False, disable=headless),
                                start=1):
            writer.write(row)
            if headless and heartbeat():
                log.info("evaluate %s: %d of %d episodes", policy.name, k, len(todo))
        rows, metrics = summarize_evaluation(out_dir, seed, episodes, confidence)
        checks = [float(r["distance_check"]) for r in rows if r.get("distance_check") not in (None, "", "nan")]
        summary = {**meta, "episodes": len(rows), "first_seed": seed, "requested_episodes": episodes,
                   "confidence": confidence, "metrics": metrics,
                   "distance_check_max_m": max(checks) if checks else math.nan, "setting": where}
        if on_net.demand is not None:
            summary["demand"] = {**demand_setting(on_net), **demand_summary(rows, metrics)}
        write_json(out_dir / "summary.json", summary)
        if checks and max(checks) > 0.5:
            log.warning("our distances and SUMO's tripinfo differ by up to %.2f m", max(checks))
        figures: list[Path] = []
        label = evaluation_label(policy, run_dir)
        if plots:
            from cosim.evaluation.plots import plot_evaluation  # matplotlib only when plotting

            if cfg.demand.enabled:
                from cosim.evaluation.flow_plots import plot_demand

                figures = plot_demand(out_dir, out_dir / "plots", label, [int(r["seed"]) for r in rows])
            else:
                figures = plot_evaluation(out_dir, out_dir / "plots", label=label, rows=rows)
        from cosim.evaluation.compare import evaluation_report  # the comparison's report, of one evaluation

        evaluation_report(out_dir, label, figures)
        return summary
    except CosimError:
        if not _has_episodes(csv_path):  # nothing to keep: nothing may block the corrected rerun into this folder
            before.restore()
        raise
    finally:
        lock.release()


def evaluation_label(policy: Policy, run_dir: Path | None) -> str:
    """What an evaluation is called in its report, its figures and the terminal's table: the trained run's folder
    name, else the policy's (a baseline, or a policy file without its run)."""
    return Path(run_dir).name if run_dir is not None else policy.name


def _has_episodes(csv_path: Path) -> bool:
    """Whether an evaluation's episodes.csv holds a finished episode (a damaged one counts: it is not ours)."""
    try:
        return bool(read_csv(csv_path))
    except CosimError:
        return True


def _same_with_todays_defaults(saved: Path, meta: dict[str, Any]) -> bool:
    """Whether a folder's config.yaml, written before keys were added to the config (each added with the default
    that keeps the old behaviour), is the config evaluated now once those keys take their defaults."""
    try:
        return config_hash(load_config(saved).to_dict()) == meta["config_sha256"]
    except CosimError:  # a config today's schema refuses is not today's
        return False


def _claim(out_dir: Path, meta: dict[str, Any], cfg: Config) -> None:
    """Write evaluation.json and config.yaml, or check that an existing evaluation is the same one (its
    evaluation.json, or the summary.json that records the same, which results kept in a repository hold alone)."""
    path = out_dir / "evaluation.json"
    record = path if path.is_file() else out_dir / "summary.json"
    held = _has_episodes(out_dir / "episodes.csv")  # a folder without an episode is anyone's
    if held and not record.is_file():
        raise CosimError(f"{out_dir}: holds episodes (episodes.csv) but no evaluation.json or summary.json saying "
                         "what they evaluated; resuming could mix two evaluations: move the folder away and evaluate "
                         "into a new --out")
    if held:
        try:
            old = json.loads(record.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            old = exc
        if not isinstance(old, dict):  # what the folder evaluated is unknown: resuming could mix two evaluations
            raise CosimError(f"{record}: not a JSON object ({old}); it records what this folder evaluated: move the "
                             "folder away and evaluate into a new --out")
        # trained_updates, model_sha256, net_sha256: only where recorded (folders from before they were); the net's
        # and the checkpoint's paths only where their content was not (a folder cloned with its net and policy
        # elsewhere is the same evaluation).
        later = ("trained_updates", "model_sha256", "net_sha256")
        paths = (*(() if old.get("net_sha256") else ("net",)), *(() if old.get("model_sha256") else ("checkpoint",)))
        differs = [k for k in ("policy", "greedy", *paths, *later)
                   if old.get(k) != meta[k] and (old.get(k) is not None or k not in later)]
        if differs:
            raise CosimError(f"{out_dir}: holds an evaluation with other {', '.join(differs)} "
                             f"({', '.join(f'{k}={old.get(k)!r}' for k in differs)}); choose another --out")
        # Folders from before the hash was stored: hash their config.yaml.
        old_hash = old.get("config_sha256") or config_hash(yaml.safe_load((out_dir / "config.yaml").read_text()))
        if old_hash != meta["config_sha256"] and not _same_with_todays_defaults(out_dir / "config.yaml", meta):
            raise ConfigError(f"{out_dir}: holds an evaluation with another config (see its config.yaml; a "
                              f"different --set, --config or net?); resuming would mix episodes of both in one "
                              f"summary: choose another --out")
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    atomic_write_text(path, json.dumps(meta, indent=2) + "\n")
