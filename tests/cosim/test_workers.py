"""Rollout workers over the fake env: shared-memory observations, PettingZoo semantics, failures and restarts,
beats within long calls, temporary files named after their owner."""

import functools
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import cosim
import cosim.workers
from agents.fake_env import CueEnv, make_fake_env, play_episode
from agents.train import episode_seed
from cosim.config import EVAL_SEED_START
from cosim.errors import NetError, SimulationError
from cosim.scratch import remove_leftovers, run_folder
from cosim.workers import START_ATTEMPTS, WorkerPool

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)


def test_fake_env_passes_the_pettingzoo_parallel_api_test() -> None:
    parallel_api_test(CueEnv(n_agents=3), num_cycles=20)
    env = CueEnv()
    assert env.observation_space("av_0") is env.observation_space("av_1")


@pytest.mark.parametrize("dtype", ["uint8", "float16", "float32"])
def test_shared_memory_carries_the_envs_observations_exactly(dtype: str, delivers_exactly, delivery_envs) -> None:
    pool = WorkerPool(delivery_envs(dtype), workers=2)
    try:
        results = delivers_exactly(pool, dtype)
        assert all(r.episode is not None and r.episode["length"] == 4 for r in results)  # no auto-reset
    finally:
        pool.close()
    assert not any(Path(f).exists() for f in pool._files)


def test_crashed_agents_leave_and_others_go_on() -> None:
    pool = WorkerPool(make_fake_env(n_agents=2, horizon=5), workers=1)
    try:
        pool.send_reset([0], [0])
        pool.recv([0])
        pool.send_step([0], np.array([[3, 1]]))  # av_0 accelerates: crash
        (r,) = pool.recv([0])
        assert r.terminated.tolist() == [True, False] and r.reward[0] == -1.0
        assert r.alive.tolist() == [False, True] and r.episode is None
        assert r.action_mask.tolist() == [[0] * 5, [1] * 5]  # an env without masks allows every action
        assert not pool.obs[0, 0].any() and pool.obs[0, 1].any()
    finally:
        pool.close()


def test_failing_worker_is_replaced_and_its_episode_lost(tmp_path: Path) -> None:
    flag = tmp_path / "failed"
    pool = WorkerPool(make_fake_env(n_agents=2, fail_once_file=str(flag), fail_at_step=2), workers=2)
    try:
        pool.send_reset([0, 1], [0, 1])
        pool.recv([0, 1])
        idle = np.ones((2, 2), dtype=np.int64)
        pool.send_step([0, 1], idle)
        assert not any(r.lost for r in pool.recv([0, 1]))
        pool.send_step([0, 1], idle)
        second = pool.recv([0, 1])  # one of the two workers fails here (whichever touches the flag first)
        assert sum(r.lost for r in second) == 1 and pool.restarts == 1
        lost = next(w for w, r in enumerate(second) if r.lost)
        assert not second[lost].alive.any()
        pool.send_reset([lost], [5])  # the replacement serves the shared slots like the first
        (r,) = pool.recv([lost])
        assert r.alive.all() and pool.obs[lost].any()
    finally:
        pool.close()


def test_a_stopped_worker_times_out_and_is_replaced() -> None:
    pool = WorkerPool(make_fake_env(n_agents=2), workers=1, timeout=2.0)
    try:
        os.kill(pool.workers[0].proc.pid, signal.SIGSTOP)
        pool.send_reset([0], [0])
        (r,) = pool.recv([0])
        assert r.lost and pool.restarts == 1
        pool.send_reset([0], [0])
        assert not pool.recv([0])[0].lost
    finally:
        pool.close()


def test_too_many_restarts_abort() -> None:
    with pytest.raises(SimulationError, match="max_restarts"):
        WorkerPool(make_fake_env(n_agents=0), workers=1, max_restarts=1)


def test_an_env_that_never_starts_stops_the_run_after_a_few_attempts(caplog: pytest.LogCaptureFixture) -> None:
    # Not max_restarts (100) restarts of a worker that cannot start: that fault is systematic.
    with pytest.raises(SimulationError, match=f"could not start its env {START_ATTEMPTS} times in a row"):
        WorkerPool(make_fake_env(n_agents=0), workers=2, max_restarts=100)
    assert len([r for r in caplog.records if "replacing it" in r.message]) == START_ATTEMPTS - 1


def test_bad_input_in_a_worker_stops_the_run_at_once(tmp_path: Path) -> None:
    # A ConfigError / NetError would fail again in every restart: it reaches the user as it is.
    with pytest.raises(NetError, match="nope.net.xml"):
        WorkerPool(functools.partial(cosim.parallel_env, "configs/default.yaml",
                                     {"net.file": str(tmp_path / "nope.net.xml")}), workers=1)


def test_training_seeds_stay_below_evaluation_seeds() -> None:
    seeds = {episode_seed(s, u, w) for s in (0, 7, 10_000_123) for u in range(5) for w in range(4)}
    assert len(seeds) == 60
    assert all(0 <= s < EVAL_SEED_START for s in seeds)
    # Fixed across processes and versions: a run resumed elsewhere continues with the same episodes.
    assert episode_seed(3, 10, 2) == 1206495


def test_a_long_call_with_quick_steps_does_not_time_out() -> None:
    # 40 steps of 0.1 s: an episode of 4 s, twice the timeout, each step far within it.
    pool = WorkerPool(make_fake_env(horizon=40, step_sleep=0.1), workers=2, timeout=2.0)
    try:
        pool.send_call([0, 1], play_episode, [0, 1])
        assert pool.recv([0, 1], lost=lambda why: None) == [40, 40] and pool.restarts == 0
    finally:
        pool.close()


@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_a_stopped_worker_within_a_call_is_replaced_naming_the_setting(caplog: pytest.LogCaptureFixture) -> None:
    pool = WorkerPool(make_fake_env(horizon=100, step_sleep=0.05), workers=2, timeout=2.0,
                      timeout_key="evaluate.step_timeout")
    try:
        pool.send_call([0, 1], play_episode, [0, 1])
        time.sleep(0.5)
        os.kill(pool.pid(1), signal.SIGSTOP)
        with caplog.at_level(logging.WARNING, logger="cosim.workers"):
            assert pool.recv([0, 1], lost=lambda why: None) == [100, None] and pool.restarts == 1
        assert "(rollout-1: no answer in 2 s (evaluate.step_timeout)); replacing it" in caplog.text
        pool.send_call([1], play_episode, [1])  # the replacement plays the episode again
        assert pool.recv([1], lost=lambda why: None) == [100]
    finally:
        pool.close()


def _owned(pid: int, start: int, rest: str = "") -> str:
    return f"cosim_{pid}-{start}{rest}"


def test_a_pools_files_are_named_after_its_process() -> None:
    start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
    me = _owned(os.getpid(), start)
    pool = WorkerPool(make_fake_env(), workers=1)
    try:
        assert run_folder() == Path(tempfile.gettempdir()) / me
        assert Path(pool._tmp_root).parent == run_folder()
        assert all(Path(f).name.startswith(f"{me}_obs_") for f in pool._files) and len(pool._files) == 2
        remove_leftovers()
        assert Path(pool._tmp_root).is_dir() and all(Path(f).exists() for f in pool._files)  # alive: kept
    finally:
        pool.close()
    assert not Path(pool._tmp_root).exists() and not any(Path(f).exists() for f in pool._files)


@pytest.mark.parametrize("deep", [False, True])
def test_multiprocessing_folder_goes_into_the_run_folder_and_all_goes_at_exit(deep: bool) -> None:
    # A socket path may hold 107 bytes: under a deep TMPDIR multiprocessing's folder stays beside, recorded.
    base = Path(tempfile.mkdtemp(prefix="w", dir="/tmp"))
    tmpdir = base / ("d" * 60 if deep else "")
    tmpdir.mkdir(exist_ok=True)
    script = ("import multiprocessing.util as u, os, sys\n"
              "from agents.fake_env import make_fake_env\n"
              "from cosim.scratch import run_folder\nfrom cosim.workers import WorkerPool\n"
              "for method in ('forkserver', 'spawn'):\n"
              "    pool = WorkerPool(make_fake_env(), 1, start_method=method)\n"
              "    pool.send_reset([0], [0])\n"
              "    assert not pool.recv([0])[0].lost\n"
              "    pool.close()\n"
              "print(run_folder(), u.get_temp_dir(), sorted(os.listdir(run_folder())))\n")
    try:
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                              env={**os.environ, "TMPDIR": str(tmpdir)}, cwd=Path(__file__).parents[2])
        assert proc.returncode == 0 and not proc.stderr, proc.stderr
        folder, pymp, inside = proc.stdout.split(" ", 2)
        assert Path(folder).parent == tmpdir and Path(pymp).name.startswith("pymp-")
        assert Path(pymp).parent == (tmpdir if deep else Path(folder))
        assert ("'pymp'" in inside) == deep  # the record of where it is
        assert list(tmpdir.iterdir()) == []  # both removed at exit
    finally:
        shutil.rmtree(base)
