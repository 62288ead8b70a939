"""Rollout workers over the fake env: PettingZoo semantics, copies of views, auto-reset, restarts."""

import functools
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import cosim
from agents.fake_env import CueEnv, make_fake_env
from agents.rollout import WorkerPool, _seed
from cosim.config import EVAL_SEED_START
from cosim.errors import NetError, SimulationError


def test_fake_env_passes_the_pettingzoo_parallel_api_test() -> None:
    parallel_api_test(CueEnv(n_agents=3), num_cycles=20)
    env = CueEnv()
    assert env.observation_space("av_0") is env.observation_space("av_1")


def test_pool_steps_resets_and_reports_episodes() -> None:
    pool = WorkerPool(make_fake_env(n_agents=2, horizon=3), workers=2, seed=1)
    try:
        assert pool.spec.agents == ("av_0", "av_1") and pool.spec.obs_shape == (2, 4, 8, 16)
        obs, alive = pool.reset()
        assert obs.shape == (2, 2, 2, 4, 8, 16) and alive.all()
        assert obs.flags.writeable
        idle = np.ones((2, 2), dtype=np.int64)
        pool.step(idle)
        results = pool.step(idle)
        assert all(r.episode is None for r in results)
        before = results[0].next_obs.copy()
        results = pool.step(idle)  # step 3 = horizon: both agents truncated, episode over, auto-reset
        for r in results:
            assert r.truncated.all() and not r.terminated.any()
            assert set(r.final_obs) == {0, 1} and r.final_obs[0].shape == (2, 4, 8, 16)
            assert r.episode is not None and r.episode["length"] == 3
            assert r.alive.all()  # the next episode's first observation
            assert set(r.reward_terms) == {"speed", "collision"}
        np.testing.assert_array_equal(before, before.copy())  # earlier results are copies, not views
    finally:
        pool.close()


def test_crashed_agents_leave_and_others_go_on() -> None:
    pool = WorkerPool(make_fake_env(n_agents=2, horizon=5), workers=1)
    try:
        pool.reset()
        (r,) = pool.step(np.array([[3, 1]]))  # av_0 accelerates: crash
        assert r.terminated.tolist() == [True, False] and r.reward[0] == -1.0
        assert r.alive.tolist() == [False, True] and r.episode is None
        assert not r.next_obs[0].any()
    finally:
        pool.close()


def test_failing_worker_is_restarted_and_its_episode_lost(tmp_path: Path) -> None:
    flag = tmp_path / "failed"
    pool = WorkerPool(make_fake_env(n_agents=2, fail_once_file=str(flag), fail_at_step=2), workers=2)
    try:
        pool.reset()
        idle = np.ones((2, 2), dtype=np.int64)
        first = pool.step(idle)
        assert not any(r.lost for r in first)
        second = pool.step(idle)  # one of the two workers fails here (whichever touches the flag first)
        assert sum(r.lost for r in second) == 1 and pool.restarts == 1
        lost = next(r for r in second if r.lost)
        assert lost.alive.all() and lost.next_obs.any()  # a fresh episode in a fresh process
        assert flag.exists()
        third = pool.step(idle)
        assert not any(r.lost for r in third)
    finally:
        pool.close()


def test_too_many_restarts_abort(tmp_path: Path) -> None:
    with pytest.raises(SimulationError, match="max_restarts"):
        WorkerPool(make_fake_env(n_agents=0), workers=1, max_restarts=1)


def test_bad_input_in_a_worker_stops_the_run_at_once(tmp_path: Path) -> None:
    # A ConfigError / NetError would fail again in every restart: it reaches the user as it is.
    with pytest.raises(NetError, match="nope.net.xml"):
        WorkerPool(functools.partial(cosim.parallel_env, "configs/default.yaml",
                                     {"net.file": str(tmp_path / "nope.net.xml")}), workers=1)


def test_training_seeds_stay_below_evaluation_seeds() -> None:
    seeds = {_seed(s, w, g) for s in (0, 7, 10_000_123) for w in range(4) for g in range(3)}
    assert len(seeds) == 36
    assert all(0 <= s < EVAL_SEED_START - 1_000_000 for s in seeds)
