"""What a collected step trains on, and how the learner acts on it, on the real env."""

import functools

import numpy as np
import pytest
import torch

import cosim
from agents.collect import collect, training_reward
from agents.config import train_config
from agents.model import VelocityMapEncoder
from agents.multiagent import Batch, MultiAgentPolicy
from cosim.config import load_config
from cosim.environment.factory import parallel_env
from cosim.workers import WorkerPool, _EnvRunner

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


@pytest.mark.parametrize("central_critic", [False, True])
def test_acting_on_the_real_env_runs_the_first_layers_on_new_frames_only_and_values_as_a_whole_forward(
        monkeypatch, central_critic: bool) -> None:
    # The env's stacks shift by one frame per decision, so after an agent's first decision only its newest frame
    # goes through the first two layers; what the learner recorded is what the network gives the whole observations,
    # a central critic's values those of each worker's AVs at each decision together.
    cfg = load_config("configs/smoke.yaml", {"train.feature_dim": 16, "train.head_hidden": 16,
                                             "train.precision": "float32", "train.obs_norm": True,
                                             "train.central_critic": central_critic})
    pool = WorkerPool(functools.partial(parallel_env, cfg.to_dict()), 2, 0, 60.0)
    try:
        spec = pool.spec
        torch.manual_seed(0)
        policy = MultiAgentPolicy(len(spec.agents), spec.obs_shape, spec.n_actions, train_config(cfg))
        batch = Batch.allocate(spec.max_steps, 2, len(spec.agents), spec.obs_shape, getattr(torch, spec.obs_dtype),
                               spec.n_actions)
        seen: list[int] = []
        frame_features = VelocityMapEncoder.frame_features
        monkeypatch.setattr(VelocityMapEncoder, "frame_features",
                            lambda self, x: seen.append(len(x)) or frame_features(self, x))
        with policy.collecting():
            got = collect(pool, policy, batch, [21, 22], update=0)
    finally:
        pool.close()
    assert len(got.episodes) == 2
    rows = batch.valid.flatten().nonzero().squeeze(1)
    continuing = batch.continues(rows)
    f = spec.obs_shape[0]
    assert continuing.float().mean() > 0.7
    assert sum(seen) == len(rows) + (f - 1) * int((~continuing).sum())  # truncated agents' finals go whole
    t_, w_, i_ = batch.valid.nonzero(as_tuple=True)
    with torch.no_grad():
        _, values = policy.nets[0](batch.observations(rows), teams=t_ * 2 + w_)
        if central_critic:  # not each AV alone
            assert (policy.nets[0](batch.observations(rows))[1] - values).abs().max() > 1e-4
    torch.testing.assert_close(batch.values[t_, w_, i_], values, atol=1e-5, rtol=1e-5)
