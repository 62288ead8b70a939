"""How the AVs' networks learn from one batch: the shared network uses every live AV's sample; the paper's
per-AV scheme trains the learner only, freezes the others and disseminates exactly; masking; bootstrapping."""

import dataclasses

import pytest
import torch

from agents.config import TrainConfig
from agents.multiagent import Batch, MultiAgentPolicy

OBS = (2, 4, 8, 16)


def small_tc(**kw: object) -> TrainConfig:
    return TrainConfig(**{"feature_dim": 32, "head_hidden": 16, "lr": 0.01, "optimizer": "adam", **kw})


def random_batch(T: int = 3, W: int = 2, N: int = 3, seed: int = 0) -> Batch:
    g = torch.Generator().manual_seed(seed)
    b = Batch.allocate(T, W, N, OBS, torch.float32)
    b.obs[:] = torch.rand(b.obs.shape, generator=g)
    b.valid[:] = True
    b.actions[:] = torch.randint(0, 5, b.actions.shape, generator=g)
    b.logp[:] = -1.6
    b.rewards[:] = torch.randn(b.rewards.shape, generator=g)
    b.truncated[-1] = True  # every episode cut at the last step
    b.final_values[-1] = torch.randn(b.final_values[-1].shape, generator=g)
    return b


def copy_batch(b: Batch) -> Batch:
    return Batch(**{f.name: getattr(b, f.name).clone() for f in dataclasses.fields(b)})


def snapshot(nets: list[torch.nn.Module]) -> list[dict[str, torch.Tensor]]:
    return [{k: v.clone() for k, v in n.state_dict().items()} for n in nets]


def same(net: torch.nn.Module, state: dict[str, torch.Tensor]) -> bool:
    return all(torch.equal(v, state[k]) for k, v in net.state_dict().items())


def trained(tc: TrainConfig, batch: Batch, n_agents: int = 3) -> tuple[dict, list[dict[str, torch.Tensor]]]:
    torch.manual_seed(0)
    policy = MultiAgentPolicy(n_agents, OBS, 5, tc)
    stats = policy.update(batch, tc, update=0, progress=0.0)
    return stats, snapshot(policy.nets)


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_shared_network_learns_from_every_live_agents_sample(algo: str) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=1, ppo_epochs=1)
    b = random_batch()
    b.valid[2:, 1, 2] = False  # agent 2 of worker 1 crashed at step 1
    b.terminated[1, 1, 2] = True
    stats, base = trained(tc, b)
    assert stats["batch"] == 3 * 2 * 3 - 1  # every valid sample of every agent, none dropped
    # A change in any one live agent's reward changes the update: each of them is in the batch.
    for w, i in ((0, 0), (0, 1), (1, 2), (1, 0)):
        other = copy_batch(b)
        other.rewards[0, w, i] += 10.0
        _, nets = trained(tc, other)
        assert not all(torch.equal(nets[0][k], base[0][k]) for k in base[0]), (w, i)


def test_masked_samples_do_not_enter_the_loss() -> None:
    """Garbage in invalid samples (a crashed agent, a lost episode) must not change the update."""
    tc = small_tc()
    a = random_batch()
    a.valid[1:, 0, 0] = False  # agent 0 of worker 0 gone after step 0 (it crashed there)
    a.terminated[0, 0, 0] = True
    a.valid[:, 1] = False  # worker 1's episode was lost
    b = copy_batch(a)
    for garbage in (b.rewards, b.values, b.final_values):
        garbage[1:, 0, 0] = -1e3
        garbage[:, 1] = 1e3
    b.obs[1:, 0, 0] = 7.0
    b.actions[:, 1] = 4
    (sa, na), (sb, nb) = trained(tc, a), trained(tc, b)
    assert sa["batch"] == 1 + 3 + 3 and sa["loss"] == sb["loss"]
    assert all(torch.equal(na[0][k], nb[0][k]) for k in na[0])


def test_truncated_samples_bootstrap_from_their_final_value() -> None:
    tc = small_tc(gamma=0.9, value_norm=False, normalize_advantage=False)
    b = random_batch(T=1, W=1, N=1)
    b.values[0, 0, 0], b.final_values[0, 0, 0], b.rewards[0, 0, 0] = 0.5, 2.0, 1.0
    stats, _ = trained(tc, b, n_agents=1)
    assert stats["advantage"] == pytest.approx(1.0 + 0.9 * 2.0 - 0.5)
    b.truncated[0, 0, 0], b.terminated[0, 0, 0] = False, True  # a crash: no bootstrap
    stats, _ = trained(tc, b, n_agents=1)
    assert stats["advantage"] == pytest.approx(1.0 - 0.5)


def test_per_av_learner_cycles_in_blocks_and_acts_with_its_live_network() -> None:
    policy = MultiAgentPolicy(3, OBS, 5, small_tc(shared_policy=False, disseminate_every=2))
    assert [policy.learner(u) for u in range(7)] == [0, 0, 1, 1, 2, 2, 0]
    assert [policy.ends_block(u) for u in range(4)] == [False, True, False, True]
    assert policy.acting_net(0, 0) is policy.nets[0] and policy.acting_net(1, 0) is policy.acting[1]
    assert all(not p.requires_grad for net in policy.acting for p in net.parameters())
    shared = MultiAgentPolicy(3, OBS, 5, small_tc())
    assert len(shared.nets) == 1 and shared.acting == [] and shared.learner(5) is None
    assert all(shared.acting_net(i, 5) is shared.nets[0] and shared.trains(i, 5) for i in range(3))


def test_per_av_update_trains_the_learner_on_all_its_samples_and_disseminates_exactly() -> None:
    torch.manual_seed(0)
    tc = small_tc(shared_policy=False, disseminate_every=2)
    policy = MultiAgentPolicy(3, OBS, 5, tc)
    nets0, acting0 = snapshot(policy.nets), snapshot(policy.acting)
    b = random_batch()
    stats = policy.update(b, tc, update=2, progress=0.0)  # update 2: AV 1's block
    learner = policy.learner(2)
    assert learner == 1 and stats["batch"] == 3 * 2  # all of AV 1's samples: every step of every worker
    assert not same(policy.nets[learner], nets0[learner])
    for k in range(3):  # frozen copies and the other AVs' networks do not move
        assert same(policy.acting[k], acting0[k])
        if k != learner:
            assert same(policy.nets[k], nets0[k])
    policy.disseminate(learner)
    assert same(policy.acting[learner], snapshot(policy.nets)[learner])
    assert all(same(policy.acting[k], acting0[k]) for k in range(3) if k != learner)


def test_act_batches_by_network_and_reports_logp_and_values() -> None:
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, OBS, 5, small_tc(shared_policy=False))
    obs, agents = torch.rand(5, *OBS), torch.tensor([0, 2, 1, 0, 2])
    actions, logp, values = policy.act(obs, agents, update=0)
    assert actions.shape == (5,) and actions.dtype == torch.int64 and (logp <= 0).all()
    for k in range(5):  # each agent's sample went through its own acting network
        net = policy.acting_net(int(agents[k]), 0)
        with torch.no_grad():
            logits, v = net(obs[k:k + 1])
        assert values[k].item() == pytest.approx(v.item(), abs=1e-5)
        assert logp[k].item() == pytest.approx(torch.log_softmax(logits, -1)[0, actions[k]].item(), abs=1e-5)
    torch.testing.assert_close(policy.value(obs, agents, update=0), values)


def test_schedules_set_the_learning_rate_and_entropy_weight() -> None:
    tc = small_tc(lr=0.01, lr_final=0.001, entropy_coef=0.02, entropy_final=0.0)
    policy = MultiAgentPolicy(1, OBS, 5, tc)
    stats = policy.update(random_batch(N=1), tc, update=0, progress=0.5)
    assert stats["lr"] == pytest.approx(0.0055) and stats["entropy_coef"] == pytest.approx(0.01)
    assert policy.optimizers[0].param_groups[0]["lr"] == pytest.approx(0.0055)
