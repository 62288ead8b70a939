"""`cosim sweep`: train every (SVO angle, seed) within a time budget, evaluate all on the same seeds, report.

Contract: `sweep(cfg, out, phis, seeds, budget_min, ...)` writes into `out`:
- `baselines/NAME/`: `cosim evaluate` of each baseline policy (idle, scripted, courteous, sumo by default);
- `runs/phi_P_seed_S/`: a training run (`cosim train` with `reward.phi = P`, `train.seed = S` and the wall-clock
  budget) and its evaluation in `eval/`, every run and baseline on the same evaluation seeds;
- `report.md` with `sweep.json` and figures (rewritten after every run, over the runs evaluated so far):
  crash % (total and by cause) and merge success % per angle with
  95% intervals (Wilson, episodes pooled over seeds) beside the baselines; the merging vehicle's distance
  egoistic vs altruistic (the paper's histogram); throughput and time loss over the angles (the
  safety/flow trade-off); the training curves; and the checks of the paper's claims, each with its figures.
Runs go egoistic and altruistic angles first, seed by seed, then the other angles (`run_order`). Every step is
resumable: an interrupted sweep run again with the same arguments continues each training run
from its checkpoint, each evaluation from its last finished episode, and skips what is complete. The exact
command and each step's wall time go into the report. With `backend=Backend("ray")` each run is a Ray task
(its rollout workers Ray actors), as many at once as the cluster has CPUs for; they finish in any order,
and `out` must be on a file system that every machine of the cluster sees. One sweep at a time per `out`
(`cosim.files.FolderLock`, as each of its runs and evaluations holds its own folder): a second is refused.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from agents.config import train_config
from agents.rollout import Backend
from cosim.config import EVAL_SEED_START, Config, check_seed, load_config
from cosim.errors import ConfigError, SimulationError
from cosim.evaluation.report import ALTRUISTIC, EGOISTIC
from cosim.evaluation.runner import Baseline, evaluate
from cosim.evaluation.store import run_name
from cosim.files import FolderLock, atomic_write_text

log = logging.getLogger(__name__)

BASELINES = ("idle", "scripted", "courteous", "sumo")


def sweep(cfg: Config, out: Path, phis: Sequence[float], seeds: Sequence[int], budget_min: float,
          eval_episodes: int = 100, eval_workers: int = 2, baselines: Sequence[str] = BASELINES,
          command: str = "", backend: Backend | None = None, demand: Config | None = None) -> dict[str, Any]:
    """Run (or continue) the sweep into `out`; returns the report's data (module doc). `demand`: a demand config
    (`demand.enabled`) every run and baseline is evaluated on too, `demand.seeds` runs of its window each."""
    if demand is not None and not demand.demand.enabled:
        raise ConfigError("--demand: that config's demand.enabled is false; give a demand config "
                          "(e.g. configs/demand.yaml)")
    if not phis or not seeds:
        raise ConfigError("cosim sweep: give at least one --phi and one --seed")
    if budget_min <= 0:
        raise ConfigError(f"--budget-min: must be > 0, got {budget_min}")
    if eval_episodes < 1 or eval_workers < 1:
        raise ConfigError("--eval-episodes and --eval-workers: must be >= 1")
    for phi in phis:
        if not -math.pi <= phi <= math.pi:
            raise ConfigError(f"--phi: expected angles in radians within [-pi, pi], got {phi}")
    for seed in seeds:  # train.seed: checked here, before the baselines run, not run by run
        check_seed("--seeds", seed)
    backend = backend or Backend()
    backend.check()
    out = Path(out).resolve()  # Ray tasks on other machines find it there (a shared file system)
    # One sweep per folder (its runs and evaluations lock their own): a live one's is refused before the cluster
    # is joined, and a new folder is made only once the cluster can take the runs.
    lock = FolderLock(out, "cosim sweep")
    lock.acquire(create=False)
    cluster = None
    try:
        # Joined first: a cluster that cannot take the runs fails before any work is done.
        cluster = _RayRuns(backend, cfg, eval_workers) if backend.name == "ray" else None
        lock.acquire()
        return _sweep(cfg, out, phis, seeds, budget_min, eval_episodes, eval_workers, baselines, command, cluster,
                      demand)
    finally:
        if cluster is not None:
            cluster.close()
        lock.release()


def _sweep(cfg: Config, out: Path, phis: Sequence[float], seeds: Sequence[int], budget_min: float,
           eval_episodes: int, eval_workers: int, baselines: Sequence[str], command: str,
           cluster: _RayRuns | None, demand: Config | None = None) -> dict[str, Any]:
    walls: dict[str, float] = _load_walls(out)
    for name in baselines:
        t0 = time.perf_counter()
        evaluate(cfg, Baseline(name), out / "baselines" / name, episodes=eval_episodes, seed=EVAL_SEED_START,
                 workers=eval_workers, trajectories=0, plots=False)
        _add_wall(walls, f"evaluate {name}", t0)
        if demand is not None:
            t0 = time.perf_counter()
            evaluate(demand, Baseline(name), out / "baselines_demand" / name, episodes=demand.demand.seeds,
                     seed=EVAL_SEED_START, workers=eval_workers, plots=False)
            _add_wall(walls, f"evaluate {name} in demand", t0)
    atomic_write_text(out / "walls.json", json.dumps(walls, indent=2) + "\n")
    from cosim.evaluation.report import write_report  # matplotlib only once there is something to plot

    result: dict[str, Any] = {}
    args = (cfg, out, budget_min, eval_episodes, eval_workers, demand)
    runs = run_order(phis, seeds)
    finished = cluster.run(runs, args) if cluster is not None else (
        _train_and_evaluate(*args, phi, seed) for phi, seed in runs)
    for run_walls in finished:
        for key, seconds in run_walls.items():
            walls[key] = walls.get(key, 0.0) + seconds
        atomic_write_text(out / "walls.json", json.dumps(walls, indent=2) + "\n")
        # The report so far after every run: an interrupted sweep still shows what it has.
        result = write_report(out, phis, seeds, baselines, eval_episodes, command, walls,
                              demand.demand.seeds if demand is not None else 0)
    return result


class _RayRuns:
    """The sweep's runs as Ray tasks over the cluster, as many at once as it has CPUs for: a run's task takes
    one for its learner (or its evaluation's workers, if more), and its rollout actors one each."""

    def __init__(self, backend: Backend, cfg: Config, eval_workers: int) -> None:
        from agents.ray_pool import connect

        workers = train_config(cfg).workers
        self.task_cpus = max(1, eval_workers)
        per_run = workers + self.task_cpus
        self.ray, self.started = connect(backend.ray_address, per_run)
        cpus = self.ray.cluster_resources().get("CPU", 0)
        self.parallel = int(cpus) // per_run
        if self.parallel < 1:
            self.close()
            raise ConfigError(f"train.workers = {workers}, --eval-workers {eval_workers}: a run needs {per_run} CPUs "
                              f"of the Ray cluster (its learner or evaluation, and its rollout actors), the cluster "
                              f"has {cpus:g}")

    def run(self, runs: Sequence[tuple[float, int]], args: tuple) -> Iterator[dict[str, float]]:
        """Yields each run's wall times as it finishes, in the order they finish."""
        ray = self.ray
        log.info("%d runs on Ray, %d at a time", len(runs), self.parallel)
        task = ray.remote(num_cpus=self.task_cpus, max_retries=0)(_train_and_evaluate)
        queue, pending = list(runs), {}
        try:
            while queue or pending:
                while queue and len(pending) < self.parallel:
                    phi, seed = queue.pop(0)
                    pending[task.remote(*args, phi, seed, "ray")] = run_name(phi, seed)
                (done,), _ = ray.wait(list(pending), num_returns=1)
                name = pending.pop(done)
                try:
                    yield ray.get(done)
                except ray.exceptions.RayTaskError as exc:  # the run's own error, as the local sweep raises it
                    cause = exc.cause if isinstance(exc.cause, Exception) else SimulationError(f"{name}: {exc}")
                    raise cause from None
                log.info("finished %s", name)
        finally:  # stopped or failed: the other runs stop too (each resumes from its last checkpoint)
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self.started:
            self.ray.shutdown()
            self.started = False


def run_order(phis: Sequence[float], seeds: Sequence[int]) -> list[tuple[float, int]]:
    """The egoistic and altruistic angles first, seed by seed (the paper's comparison), then the other angles
    seed by seed (the first seed of each gives the whole grid early)."""
    key = [p for p in phis if any(math.isclose(p, k, abs_tol=1e-3) for k in (EGOISTIC, ALTRUISTIC))]
    rest = [p for p in phis if p not in key]
    return [(p, s) for group in (key, rest) for s in seeds for p in group]


def _load_walls(out: Path) -> dict[str, float]:
    path = out / "walls.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _train_and_evaluate(cfg: Config, out: Path, budget_min: float, eval_episodes: int, eval_workers: int,
                        demand: Config | None, phi: float, seed: int, backend: str = "local") -> dict[str, float]:
    """Train (or finish training) and evaluate one run; returns the wall times [s] of what it did."""
    from agents.checkpoint import CHECKPOINT_NAME, TrainedPolicy, read_checkpoint
    from agents.train import train

    walls: dict[str, float] = {}
    name = run_name(phi, seed)
    run_dir = out / "runs" / name
    run_cfg = load_config(cfg, {"reward.phi": phi, "train.seed": seed, "train.budget_min": budget_min})
    ckpt = run_dir / CHECKPOINT_NAME
    done = False
    if ckpt.is_file():  # finished: its budget spent, or all of its episodes trained
        saved = read_checkpoint(ckpt)
        trained_s = float(saved["counters"].get("train_s", 0.0))
        done = trained_s >= budget_min * 60.0 or saved["counters"]["episodes"] >= saved["train"]["episodes"]
    if not done:
        log.info("training %s (budget %.1f min)", name, budget_min)
        t0 = time.perf_counter()
        result = train(run_cfg, run_dir, resume=ckpt.is_file(), backend=backend)
        _add_wall(walls, f"train {name}", t0)
        if result.interrupted:
            raise KeyboardInterrupt
        for old in ("eval", "eval_demand"):  # evaluations of an earlier state of the run
            shutil.rmtree(run_dir / old, ignore_errors=True)
    t0 = time.perf_counter()
    evaluate(run_cfg, TrainedPolicy(str(ckpt.resolve())), run_dir / "eval", episodes=eval_episodes,
             seed=EVAL_SEED_START, workers=eval_workers, trajectories=3, run_dir=run_dir, plots=False)
    _add_wall(walls, f"evaluate {name}", t0)
    if demand is not None:
        t0 = time.perf_counter()
        evaluate(load_config(demand, {"reward.phi": phi}), TrainedPolicy(str(ckpt.resolve())),
                 run_dir / "eval_demand", episodes=demand.demand.seeds, seed=EVAL_SEED_START, workers=eval_workers,
                 run_dir=run_dir, plots=False)
        _add_wall(walls, f"evaluate {name} in demand", t0)
    return walls


def _add_wall(walls: dict[str, float], key: str, t0: float) -> None:
    """Wall time [s] of a step, summed over the invocations that worked on it (an interrupted sweep resumes)."""
    walls[key] = walls.get(key, 0.0) + time.perf_counter() - t0
