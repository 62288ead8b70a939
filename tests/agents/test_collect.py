"""What a collected step trains on, on the real env."""

import numpy as np
import pytest

import cosim
from agents.collect import training_reward
from cosim.workers import _EnvRunner

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)


def test_the_egoistic_training_reward_is_each_avs_own_utility_on_the_real_env() -> None:
    env = cosim.parallel_env("configs/smoke.yaml", ["reward.phi=0.7854"])
    infos: list[dict] = []
    step = env.step

    def spied(actions: dict) -> tuple:
        out = step(actions)
        infos.append(out[4])
        return out

    env.step = spied
    runner = _EnvRunner(env)
    shape = (len(runner.agents), *runner.spec.obs_shape)
    runner.obs, runner.final = np.zeros(shape, runner.spec.obs_dtype), np.zeros(shape, runner.spec.obs_dtype)
    runner.reset(seed=11)
    social = 0.0
    rng = np.random.default_rng(0)
    try:
        for _ in range(env.max_steps):
            res = runner.step(rng.integers(0, 5, len(runner.agents)))
            for agent, info in infos[-1].items():
                i = runner.agents.index(agent)
                assert training_reward(res, egoistic=True)[i] == pytest.approx(info["ego_utility"], abs=1e-5)
                social += abs(info["social_utility"])
            np.testing.assert_array_equal(training_reward(res, egoistic=False), res.reward)
            if res.episode is not None:
                break
    finally:
        env.close()
    assert social > 0  # the env's reward had a part for the others, which the egoistic one leaves out
