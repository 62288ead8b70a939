"""The Ray backend on a local Ray with 2 CPUs: the rollout contract, failures, and training like the local backend."""

import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import read_checkpoint
from agents.fake_env import make_fake_env
from agents.rollout import Backend
from agents.sweep import sweep
from agents.train import train
from cosim.config import load_config
from cosim.errors import ConfigError, SimulationError
from cosim.files import read_csv

ray = pytest.importorskip("ray")
from agents.ray_pool import RayWorkerPool, keep_signal_handlers  # noqa: E402 - only where Ray is installed

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)


@pytest.fixture(scope="module", autouse=True)
def local_ray() -> Iterator[None]:
    # One local Ray for the module (starting one takes seconds); the pools and runs below join it. Ray's own
    # SIGTERM handler (sys.exit) must not stay for the tests after this module, nor stop the ones in it.
    with keep_signal_handlers():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_a_pool_that_starts_ray_leaves_the_signal_handlers_as_they_were() -> None:
    # ray.init installs a SIGTERM handler that exits with 15; cosim's own handlers (stop after the update with a
    # checkpoint, exit 130) must stay in force while the pool lives and after. This module's Ray is running,
    # so a pool that starts Ray itself (as `cosim train --backend ray` does) is watched in a fresh process.
    script = """
import signal
from agents.fake_env import make_fake_env
from agents.ray_pool import RayWorkerPool

def handlers():
    return [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]

signal.signal(signal.SIGTERM, lambda signum, frame: None)
before = handlers()
pool = RayWorkerPool(make_fake_env(n_agents=1), workers=1)
during = handlers()
pool.close()
print(during == before, handlers() == before)
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[2])
    assert proc.stdout.split() == ["True", "True"], proc.stdout + proc.stderr


def test_actors_deliver_the_envs_observations_exactly(delivers_exactly, delivery_envs) -> None:
    pool = RayWorkerPool(delivery_envs("uint8"), workers=2)
    try:
        results = delivers_exactly(pool, "uint8")
        assert all(r.episode is not None and r.episode["length"] == 4 for r in results)  # no auto-reset
        results[0].reward[0] = 0  # the caller owns what it receives (Ray's object store is read-only)
    finally:
        pool.close()


@pytest.mark.parametrize("sig", [signal.SIGKILL, pytest.param(signal.SIGSTOP, marks=pytest.mark.slow)],
                         ids=["killed", "stopped"])
def test_a_dead_or_silent_actor_is_restarted_and_its_episode_lost(sig: signal.Signals) -> None:
    pool = RayWorkerPool(make_fake_env(n_agents=2), workers=2, timeout=3.0)
    try:
        pool.send_reset([0, 1], [0, 1])
        pool.recv([0, 1])
        before = pool.pid(0)
        os.kill(before, sig)
        pool.send_step([0, 1], np.ones((2, 2), dtype=np.int64))
        lost = [r.lost for r in pool.recv([0, 1])]
        assert lost == [True, False] and pool.restarts == 1 and pool.pid(0) != before
        pool.send_reset([0], [5])  # the new actor serves like the first
        (r,) = pool.recv([0])
        assert not r.lost and r.alive.all() and pool.obs[0].any()
    finally:
        pool.close()
    # The dead actor's temporary folder went too (the env writes SUMO's files there).
    assert not list(Path(tempfile.gettempdir()).glob(f"cosim_{before}-*"))


def test_bad_input_and_hopeless_envs_stop_the_run() -> None:
    with pytest.raises(SimulationError, match="could not start its env"):
        RayWorkerPool(make_fake_env(n_agents=0), workers=1)
    with pytest.raises(ConfigError, match="the Ray cluster has 2 CPUs"):
        RayWorkerPool(make_fake_env(n_agents=2), workers=3)


@pytest.mark.parametrize("by_exit", [False, True], ids=["env-raises", "actor-dies"])
def test_a_failing_actor_in_training_is_restarted_and_its_episode_goes_on(tmp_path: Path, by_exit: bool) -> None:
    flag = tmp_path / "failed"
    cfg = load_config({"train": {"feature_dim": 32, "head_hidden": 32, "precision": "float32"}})
    result = train(cfg, tmp_path / "run", workers=2, episodes=8, backend="ray", progress=False,
                   env_factory=make_fake_env(n_agents=2, fail_once_file=str(flag), fail_at_step=3,
                                             fail_by_exit=by_exit))
    # The restarted actor played the episode again up to the failed step (agents.collect) and went on.
    assert flag.exists() and result.restarts == 1 and result.lost_episodes == 0
    assert len(read_csv(tmp_path / "run" / "episodes.csv")) == result.episodes == 8


@pytest.mark.slow  # 12 s; the pool's own checks on Ray stay in the default tier
def test_ray_trains_the_smoke_config_like_the_local_backend_and_resumes(tmp_path: Path) -> None:
    # SUMO is deterministic per seed and the learner samples the actions, so the same config and seeds give the
    # same run on either backend: the same episodes and, bit for bit, the same weights.
    # float32: bfloat16 kernels (precision auto on CPUs with AVX512-BF16 / AMX) are not reproducible run to run.
    cfg = load_config("configs/smoke.yaml", ["train.precision=float32"])
    local = train(cfg, tmp_path / "local", workers=2, episodes=8, progress=False)
    train(cfg, tmp_path / "ray", workers=2, episodes=4, backend="ray", progress=False)
    resumed = train(cfg, tmp_path / "ray", workers=2, episodes=8, resume=True, backend="ray", progress=False)
    assert (resumed.episodes, resumed.updates, resumed.samples) == (local.episodes, local.updates, local.samples)
    assert read_csv(tmp_path / "ray" / "episodes.csv") == read_csv(tmp_path / "local" / "episodes.csv")
    a, b = (read_checkpoint(r.checkpoint)["policy"]["nets"][0] for r in (local, resumed))
    assert all(torch.equal(v, b[k]) for k, v in a.items())


def test_ray_address_needs_the_ray_backend(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="only with --backend ray"):
        train(load_config("configs/smoke.yaml"), tmp_path / "run", ray_address="auto", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # 21 s
def test_sweep_runs_its_runs_as_ray_tasks(tmp_path: Path) -> None:
    # A run takes a CPU for its learner and one per rollout actor: 2 here, so the 2-CPU Ray runs one at a time.
    cfg = load_config("configs/smoke.yaml", ["train.workers=1"])
    out = tmp_path / "sweep"
    result = sweep(cfg, out, [0.0, 0.7854], [0], budget_min=0.05, eval_episodes=2, eval_workers=1,
                   baselines=("idle",), backend=Backend("ray"))
    assert result["episodes"] == {"idle": 2, "phi=0.000 (egoistic)": 2, "phi=0.785 (altruistic)": 2}
    walls = json.loads((out / "walls.json").read_text())
    assert {"train phi_0.0000_seed_0", "train phi_0.7854_seed_0", "evaluate phi_0.7854_seed_0"} <= set(walls)
    assert (out / "report.md").is_file() and read_checkpoint(out / "runs" / "phi_0.0000_seed_0" / "checkpoint.pt")
    with pytest.raises(ConfigError, match="a run needs 4 CPUs"):  # 2 rollout actors, 2 evaluation workers
        sweep(load_config("configs/smoke.yaml"), tmp_path / "big", [0.0], [0], budget_min=0.05, eval_episodes=2,
              eval_workers=2, baselines=("idle",), backend=Backend("ray"))
    assert not (tmp_path / "big").exists()  # refused before any work
