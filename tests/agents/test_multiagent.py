"""Semi-sequential multi-agent training: learner schedule, frozen copies, exact dissemination, masking."""

import torch

from agents.config import TrainConfig
from agents.multiagent import MultiAgentPolicy, parameters_equal
from agents.train import Rollout, learner_update

OBS = (2, 4, 8, 16)


def small_tc(**kw: object) -> TrainConfig:
    return TrainConfig(feature_dim=32, head_hidden=16, lr=0.01, optimizer="adam", **kw)


def random_rollout(T: int = 3, W: int = 2, N: int = 3, seed: int = 0) -> Rollout:
    g = torch.Generator().manual_seed(seed)
    ro = Rollout.allocate(T, W, N, OBS, torch.float32)
    ro.obs[:] = torch.rand(ro.obs.shape, generator=g)
    ro.alive[:] = True
    ro.valid[:] = True
    ro.actions[:] = torch.randint(0, 5, ro.actions.shape, generator=g)
    ro.rewards[:] = torch.randn(ro.rewards.shape, generator=g)
    return ro


def snapshot(nets: list[torch.nn.Module]) -> list[dict[str, torch.Tensor]]:
    return [{k: v.clone() for k, v in n.state_dict().items()} for n in nets]


def same(net: torch.nn.Module, state: dict[str, torch.Tensor]) -> bool:
    return all(torch.equal(v, state[k]) for k, v in net.state_dict().items())


def test_learner_cycles_over_agents_in_blocks_of_k() -> None:
    policy = MultiAgentPolicy(3, OBS, 5, small_tc(disseminate_every=2))
    assert [policy.learner(u) for u in range(7)] == [0, 0, 1, 1, 2, 2, 0]
    assert [policy.ends_block(u) for u in range(4)] == [False, True, False, True]
    # the learner acts with its live network, the others with frozen copies
    assert policy.acting_net(0, 0) is policy.nets[0]
    assert policy.acting_net(1, 0) is policy.acting[1]
    assert all(not p.requires_grad for net in policy.acting for p in net.parameters())


def test_update_changes_only_the_learner_and_dissemination_copies_exactly() -> None:
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, OBS, 5, small_tc(disseminate_every=2))
    nets0, acting0 = snapshot(policy.nets), snapshot(policy.acting)
    ro = random_rollout()
    learner = policy.learner(0)
    stats = learner_update(policy, learner, ro, small_tc())
    assert stats["batch"] == 6  # T * W samples of the learner only
    assert not same(policy.nets[learner], nets0[learner])
    for k in range(3):  # frozen copies and other AVs' networks do not move
        assert same(policy.acting[k], acting0[k])
        if k != learner:
            assert same(policy.nets[k], nets0[k])
    policy.disseminate(learner)
    assert parameters_equal(policy.acting[learner], policy.nets[learner])
    for k in range(3):
        if k != learner:
            assert same(policy.acting[k], acting0[k])


def test_shared_policy_has_one_network_and_disseminates_to_all() -> None:
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, OBS, 5, small_tc(shared_policy=True, disseminate_every=1))
    assert len(policy.nets) == 1 and len(policy.acting) == 1
    assert {policy.owner(i) for i in range(3)} == {0}
    acting0 = snapshot(policy.acting)[0]
    learner_update(policy, 1, random_rollout(), small_tc())
    assert same(policy.acting[0], acting0)  # AVs 0 and 2 still act with the frozen copy
    assert policy.acting_net(2, 1) is policy.acting[0] and policy.acting_net(1, 1) is policy.nets[0]
    policy.disseminate(1)
    assert all(parameters_equal(policy.acting_net(i, 0), policy.nets[0]) for i in (1, 2))


def test_masked_samples_do_not_enter_the_loss() -> None:
    """Garbage in invalid samples (dead agent, lost episode) must not change the update."""
    tc = small_tc()
    ro_a = random_rollout()
    ro_a.valid[1:, 0, 0] = False  # agent 0 of worker 0 gone after step 0 (it crashed there)
    ro_a.terminated[0, 0, 0] = True
    ro_a.alive[1:, 0, 0] = False
    ro_b = Rollout(ro_a.obs.clone(), ro_a.alive.clone(), ro_a.actions.clone(), ro_a.rewards.clone(),
                   ro_a.terminated.clone(), ro_a.truncated.clone(), ro_a.valid.clone(), {})
    ro_b.obs[1:, 0, 0] = 1e3
    ro_b.rewards[1:, 0, 0] = -1e3
    ro_b.actions[1:, 0, 0] = 4
    results = []
    for ro in (ro_a, ro_b):
        torch.manual_seed(0)
        policy = MultiAgentPolicy(3, OBS, 5, tc)
        stats = learner_update(policy, 0, ro, tc)
        results.append((stats, snapshot(policy.nets)[0]))
    assert results[0][0]["batch"] == 4
    assert results[0][0]["loss"] == results[1][0]["loss"]
    assert all(torch.equal(results[0][1][k], results[1][1][k]) for k in results[0][1])


def test_truncated_samples_bootstrap_from_their_final_observation() -> None:
    tc = small_tc(gamma=0.9)
    ro = random_rollout(T=1, W=1, N=1)
    ro.truncated[0, 0, 0] = True
    ro.final_obs[(0, 0, 0)] = torch.rand(OBS)
    torch.manual_seed(0)
    policy = MultiAgentPolicy(1, OBS, 5, tc)
    net = policy.nets[0]
    with torch.no_grad():
        expected = ro.rewards[0, 0, 0] + 0.9 * net.value(ro.final_obs[(0, 0, 0)][None])[0] - net.value(ro.obs[0, 0])[0]
    stats = learner_update(policy, 0, ro, tc)
    assert abs(stats["advantage"] - expected.item()) < 1e-5


def test_act_batches_alive_agents_and_idles_the_absent() -> None:
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, OBS, 5, small_tc())
    alive = torch.tensor([[True, False, True], [False, False, True]])
    actions = policy.act(torch.rand(2, 3, *OBS), alive, update=0)
    assert actions.shape == (2, 3) and actions.dtype == torch.int64
    assert (actions[~alive] == 1).all()
