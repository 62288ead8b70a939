"""Shared pytest fixtures: a small merge net, and the check every env worker pool (local processes, Ray actors)
must pass."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.fake_env import CueEnv, make_fake_env
from cosim.workers import StepResult
from sumo_net.build import build_merge_net, run_netconvert
from sumo_net.shapes import SHAPES, build_shape


@pytest.fixture(scope="session")
def shaped_nets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every net of `sumo_net.shapes.SHAPES`, built once per session without its description; name -> path."""
    out = {}
    for name in SHAPES:
        # Without its description, as a user's own net: the roles are inferred (the builder's kept to compare).
        net = build_shape(name, tmp_path_factory.mktemp(name))
        net.with_name(f"{name}.yaml").rename(net.with_name(f"{name}.described.yaml"))
        out[name] = net
    return out


@pytest.fixture(scope="session")
def two_lane_net(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-lane merge net (80 m acceleration lane) built once per session; returns its .net.xml path."""
    out = tmp_path_factory.mktemp("two_lane_net")
    return build_merge_net(out, lanes=2, accel_length=80, upstream_length=100, downstream_length=500)


@pytest.fixture(scope="session")
def rampless_net(tmp_path_factory: pytest.TempPathFactory, two_lane_net: Path) -> Path:
    """`two_lane_net` rebuilt without its ramp and the ramp's connection, no description beside it: a net that
    holds no on-ramp merge; returns its merge.net.xml path."""
    out = tmp_path_factory.mktemp("rampless_net")
    drop = {"merge.nod.xml": None, "merge.edg.xml": 'id="ramp"', "merge.con.xml": 'from="ramp"'}
    for name, marker in drop.items():
        lines = two_lane_net.with_name(name).read_text().splitlines()
        (out / name).write_text("\n".join(line for line in lines if marker is None or marker not in line))
    return run_netconvert(out, "merge")


MASKED = (3,)  # the actions the pool's envs in `delivers_exactly` mask


def _delivers_exactly(pool: Any, dtype: str) -> list[StepResult]:
    """Drive a 2-worker pool of `delivery_envs(dtype)` through a whole episode beside the same envs in this
    process, seeded alike: every observation, reward and final observation must arrive bit for bit, and each live
    agent's action mask (zeros for the others). Returns the last step's results."""
    local = [CueEnv(n_agents=3, horizon=4, dtype=dtype, masked=MASKED) for _ in range(2)]
    allowed = np.array([0 if a in MASKED else 1 for a in range(5)], dtype=np.int8)
    assert pool.obs.shape == (2, 3, 2, 4, 8, 16) and pool.obs.dtype == np.dtype(dtype)
    assert pool.spec.max_steps == 4
    pool.send_reset([0, 1], [11, 12])
    assert all(r.action_mask.tolist() == [allowed.tolist()] * 3 for r in pool.recv([0, 1]))
    want = [env.reset(seed=s)[0] for env, s in zip(local, (11, 12), strict=True)]
    rng = np.random.default_rng(0)
    for _ in range(4):
        for w in range(2):
            np.testing.assert_array_equal(pool.obs[w], np.stack([want[w][a] for a in local[w].possible_agents]))
        actions = rng.choice([0, 2], size=(2, 3))
        pool.send_step([0, 1], actions)
        results = pool.recv([0, 1])
        for w, res in enumerate(results):
            want[w], rew, _, trunc, _ = local[w].step(dict(zip(local[w].possible_agents, actions[w].tolist(),
                                                               strict=True)))
            assert res.reward.tolist() == [rew[a] for a in local[w].possible_agents]
            np.testing.assert_array_equal(res.action_mask, res.alive[:, None] * allowed)
            assert res.action_mask.dtype == np.int8
            for i, a in enumerate(local[w].possible_agents):
                if trunc[a]:  # truncated: the final observation is in the final slot
                    np.testing.assert_array_equal(pool.final[w, i], want[w][a])
    return results


@pytest.fixture
def delivers_exactly() -> Callable[[Any, str], list[StepResult]]:
    return _delivers_exactly


@pytest.fixture
def delivery_envs() -> Callable[[str], Callable[[], CueEnv]]:
    """dtype -> the env factory of the pool that `delivers_exactly` checks."""
    return lambda dtype: make_fake_env(n_agents=3, horizon=4, dtype=dtype, masked=MASKED)
