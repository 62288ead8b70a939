"""Shared pytest fixtures: a small merge net, and the check every env worker pool (local processes, Ray actors)
must pass."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.fake_env import CueEnv
from cosim.workers import StepResult
from sumo_net.build import build_merge_net

# Nets of the usual shapes, built with netconvert from the node, edge and connection files the builder writes
# (sumo_net.build), their description YAML removed so that the roles are inferred as for a user's own net.
SHAPES: dict[str, dict[str, Any]] = {
    # the approach in 3 edges, a ramp of 2 edges, 2 edges after the merge; 120 / 80 km/h
    "multi_edge": dict(lanes=2, upstream_length=500, upstream_edges=3, ramp_length=240, ramp_edges=2,
                       downstream_edges=2, downstream_length=600),
    # a 3-lane highway bending left on a 600 m radius, names of one's own; 100 / 60 km/h
    "curved": dict(lanes=3, upstream_length=400, curve_radius=600, highway_speed=27.78, ramp_speed=16.67,
                   ids={"ramp": "slip_road", "hw_in": "main_a", "hw_merge": "main_b", "hw_out": "main_c"}),
    # a 2-lane ramp into two acceleration lanes; 130 / 80 km/h
    "two_lane_ramp": dict(lanes=2, upstream_length=450, ramp_lanes=2, highway_speed=36.11, ramp_speed=22.22),
    # 3 lanes, the left one ending after the merge; 60 / 40 km/h
    "lane_drop": dict(lanes=3, upstream_length=300, downstream_edges=2, lane_drop=True, highway_speed=16.67,
                      ramp_speed=11.11),
    # OSM's ids (way -4711 in pieces, way 88 for the ramp), a 1-lane highway; 80 / 50 km/h
    "osm_ids": dict(lanes=1, upstream_length=350, upstream_edges=2, highway_speed=22.22, ramp_speed=13.89,
                    ids={"hw_in_0": "-4711#0", "hw_in_1": "-4711#1", "hw_merge": "-4711#2", "hw_out": "-4711#3",
                         "ramp": "88#1"}),
    # what `cosim build-net --lanes 1` builds: a 1-lane highway with a 120 m approach
    "one_lane": dict(lanes=1),
}


@pytest.fixture(scope="session")
def shaped_nets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every net of SHAPES, built once per session without its description; name -> .net.xml path."""
    out = {}
    for name, shape in SHAPES.items():
        net = build_merge_net(tmp_path_factory.mktemp(name), name=name, **shape)
        net.with_name(f"{name}.yaml").rename(net.with_name(f"{name}.described.yaml"))  # the builder's, to compare
        out[name] = net
    return out


@pytest.fixture(scope="session")
def two_lane_net(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-lane merge net (80 m acceleration lane) built once per session; returns its .net.xml path."""
    out = tmp_path_factory.mktemp("two_lane_net")
    return build_merge_net(out, lanes=2, accel_length=80, upstream_length=100, downstream_length=500)


def _delivers_exactly(pool: Any, dtype: str) -> list[StepResult]:
    """Drive a 2-worker pool of `make_fake_env(n_agents=3, horizon=4, dtype=dtype)` through a whole episode
    beside the same envs in this process, seeded alike: every observation, reward and final observation must
    arrive bit for bit. Returns the last step's results."""
    local = [CueEnv(n_agents=3, horizon=4, dtype=dtype) for _ in range(2)]
    assert pool.obs.shape == (2, 3, 2, 4, 8, 16) and pool.obs.dtype == np.dtype(dtype)
    assert pool.spec.max_steps == 4
    pool.send_reset([0, 1], [11, 12])
    pool.recv([0, 1])
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
            for i, a in enumerate(local[w].possible_agents):
                if trunc[a]:  # truncated: the final observation is in the final slot
                    np.testing.assert_array_equal(pool.final[w, i], want[w][a])
    return results


@pytest.fixture
def delivers_exactly() -> Callable[[Any, str], list[StepResult]]:
    return _delivers_exactly
