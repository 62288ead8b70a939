"""How the AVs' networks learn from one batch: the shared network uses every live AV's sample; the paper's
per-AV scheme trains the learner only, freezes the others and disseminates exactly; masking; bootstrapping;
the same in bfloat16, within its rounding; minibatches padded to few sizes, and split into chunks (whole teams for a
central critic), without a change to the update; the batch's gather of observations; the weights' moving average
that greedy acting plays."""

import dataclasses

import pytest
import torch

from agents.checkpoint import played_nets
from agents.config import TrainConfig
from agents.model import BF16_GRADIENT_TOL, VelocityMapEncoder, bf16_gradient_error
from agents.multiagent import Batch, MultiAgentPolicy, _chunks, bucket
from cosim.errors import ConfigError

OBS = (2, 4, 8, 16)
# The bfloat16 tests' observations: with 2 frames, or 3 on a map this small, torch 2.13's oneDNN gives wrong
# Conv3D weight gradients on CPUs with AVX512-BF16 (`bf16_gradient_error`; the policy refuses bfloat16 there).
BF16_OBS = (3, 4, 16, 32)


def small_tc(**kw: object) -> TrainConfig:
    # float32, not auto: bfloat16 kernels (auto's choice on CPUs with AVX512-BF16 / AMX) are not reproducible
    # run to run, and these tests compare updates bit for bit.
    return TrainConfig(**{"feature_dim": 32, "head_hidden": 16, "lr": 0.01, "optimizer": "adam",
                          "precision": "float32", **kw})


# bfloat16 forced, so that it runs (emulated, slowly) on any CPU. Adam's first step is lr * g / (|g| + eps): with
# the default eps that is lr * sign(g), and a gradient within bfloat16's rounding of zero moves its parameter by
# lr the other way; with eps far above every |g| (below 0.1 here) it is the gradient step lr / eps * g, so the
# parameter change measures the gradient itself.
BF16 = {"precision": "bfloat16", "optimizer_eps": 100.0, "lr": 1.0}
# bfloat16 keeps 8 significant bits (2^-9 relative) of every layer's input, forward and backward: the gradient
# of one update is 4.7% (in norm) off float32's here, and runs of it on bfloat16 hardware differ from each
# other by that kind of rounding. 15% bounds it; a sample that enters or leaves the loss moves it by over 70%.
BF16_TOL = 0.15
LIVE = ((0, 0), (0, 1), (1, 2), (1, 0))  # (worker, agent) of live samples


def random_batch(T: int = 3, W: int = 2, N: int = 3, seed: int = 0, obs: tuple[int, ...] = OBS) -> Batch:
    g = torch.Generator().manual_seed(seed)
    b = Batch.allocate(T, W, N, obs, torch.float32, 5)
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
    policy = MultiAgentPolicy(n_agents, tuple(batch.obs.shape[3:]), 5, tc)
    stats = policy.update(batch, tc, update=0, progress=0.0)
    return stats, snapshot(policy.nets)


def change(tc: TrainConfig, batch: Batch) -> tuple[dict, torch.Tensor]:
    """The statistics of `trained` and how far it moved the shared network's parameters (flat)."""
    torch.manual_seed(0)
    (start,) = snapshot(MultiAgentPolicy(3, tuple(batch.obs.shape[3:]), 5, tc).nets)  # `trained`'s, before it learns
    stats, (end,) = trained(tc, batch)
    return stats, torch.cat([(end[k] - start[k]).flatten() for k in start])


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def crashed_batch(obs: tuple[int, ...] = OBS) -> Batch:
    b = random_batch(obs=obs)
    b.valid[2:, 1, 2] = False  # agent 2 of worker 1 crashed at step 1
    b.terminated[1, 1, 2] = True
    return b


def with_reward_changed(b: Batch, w: int, i: int) -> Batch:
    other = copy_batch(b)
    other.rewards[0, w, i] += 10.0
    return other


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_shared_network_learns_from_every_live_agents_sample(algo: str) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=1, ppo_epochs=1)
    b = crashed_batch()
    stats, base = trained(tc, b)
    assert stats["batch"] == 3 * 2 * 3 - 1  # every valid sample of every agent, none dropped
    # A change in any one live agent's reward changes the update: each of them is in the batch.
    for w, i in LIVE:
        _, nets = trained(tc, with_reward_changed(b, w, i))
        assert not all(torch.equal(nets[0][k], base[0][k]) for k in base[0]), (w, i)


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_in_bfloat16_every_live_agents_sample_moves_the_update(algo: str) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=1, ppo_epochs=1, **BF16)
    b = crashed_batch(BF16_OBS)
    stats, base = change(tc, b)
    assert stats["batch"] == 3 * 2 * 3 - 1
    for w, i in LIVE:
        _, moved = change(tc, with_reward_changed(b, w, i))
        assert relative(moved, base) > 3 * BF16_TOL, (w, i)  # far beyond bfloat16's rounding


def garbage_batches(obs: tuple[int, ...] = OBS) -> tuple[Batch, Batch]:
    """A batch with invalid samples (a crashed agent, a lost episode), and the same with garbage in them."""
    a = random_batch(obs=obs)
    a.valid[1:, 0, 0] = False  # agent 0 of worker 0 gone after step 0 (it crashed there)
    a.terminated[0, 0, 0] = True
    a.valid[:, 1] = False  # worker 1's episode was lost
    b = copy_batch(a)
    for garbage in (b.rewards, b.values, b.final_values):
        garbage[1:, 0, 0] = -1e3
        garbage[:, 1] = 1e3
    b.obs[1:, 0, 0] = 7.0
    b.actions[:, 1] = 4
    return a, b


def test_masked_samples_do_not_enter_the_loss() -> None:
    """Garbage in invalid samples must not change the update."""
    tc = small_tc()
    (sa, na), (sb, nb) = (trained(tc, b) for b in garbage_batches())
    assert sa["batch"] == 1 + 3 + 3 and sa["loss"] == sb["loss"]
    assert all(torch.equal(na[0][k], nb[0][k]) for k in na[0])


def test_masked_samples_do_not_enter_a_bfloat16_update() -> None:
    tc = small_tc(**BF16)
    (sa, clean), (sb, dirty) = (change(tc, b) for b in garbage_batches(BF16_OBS))
    assert sa["batch"] == sb["batch"] == 1 + 3 + 3
    assert sb["loss"] == pytest.approx(sa["loss"], rel=1e-3) and relative(dirty, clean) < BF16_TOL


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_a_bfloat16_update_is_close_to_the_float32_one_and_keeps_float32_weights(algo: str) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=1, ppo_epochs=1, **BF16)
    b = crashed_batch(BF16_OBS)
    s16, d16 = change(tc, b)
    s32, d32 = change(tc.model_copy(update={"precision": "float32"}), b)
    # The loss is of the initial network, whose outputs are tiny: bfloat16 leaves it within 1e-5 (measured).
    assert s16["loss"] == pytest.approx(s32["loss"], rel=1e-3) and relative(d16, d32) < BF16_TOL
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, BF16_OBS, 5, tc)
    policy.update(b, tc, update=0, progress=0.0)
    states = [v for s in policy.optimizers[0].state.values() for v in s.values() if v.dim() > 0]
    assert policy.nets[0].bf16 and states
    assert all(t.dtype == torch.float32 for t in [*policy.nets[0].state_dict().values(), *states])
    _, logp, values = policy.act(b.obs[0, 0], torch.arange(3), update=1)
    assert logp.dtype == values.dtype == torch.float32


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


def test_a_batch_gives_back_the_observations_written_into_it_and_the_network_reads_them_as_written() -> None:
    # The batch stores observations channels last (its doc): what goes in as the env's (F, C, H, W) must come out
    # the same, and the network's outputs on it must be those on the env's layout.
    g = torch.Generator().manual_seed(3)
    b = Batch.allocate(2, 2, 3, OBS, torch.uint8, 5)
    written = torch.randint(0, 256, (3, *OBS), dtype=torch.uint8, generator=g)
    b.obs[1, 0] = torch.from_numpy(written.numpy())
    t_, w_, i_ = torch.tensor([1, 1]), torch.tensor([0, 0]), torch.tensor([2, 0])
    read = b.obs[t_, w_, i_]
    assert torch.equal(read, written[[2, 0]])
    torch.manual_seed(0)
    net = MultiAgentPolicy(3, OBS, 5, small_tc()).nets[0]
    with torch.no_grad():
        for got, want in zip(net(read), net(read.contiguous()), strict=True):
            torch.testing.assert_close(got, want)


def test_schedules_set_the_learning_rate_and_entropy_weight() -> None:
    tc = small_tc(lr=0.01, lr_final=0.001, entropy_coef=0.02, entropy_final=0.0)
    policy = MultiAgentPolicy(1, OBS, 5, tc)
    stats = policy.update(random_batch(N=1), tc, update=0, progress=0.5)
    assert stats["lr"] == pytest.approx(0.0055) and stats["entropy_coef"] == pytest.approx(0.01)
    assert policy.optimizers[0].param_groups[0]["lr"] == pytest.approx(0.0055)


class _DropGradient(torch.autograd.Function):
    """Identity forward, zero gradient backward: a Conv3D kernel that gets bfloat16 weight gradients wrong."""

    @staticmethod
    def forward(ctx: object, x: torch.Tensor) -> torch.Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx: object, grad: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(grad)


@pytest.fixture
def faulty_bf16_conv(monkeypatch: pytest.MonkeyPatch) -> None:
    """Conv3D layers whose output passes no gradient back under bfloat16 autocast (float32 stays right)."""
    conv_forward = torch.nn.Conv3d._conv_forward

    def faulty(self: torch.nn.Conv3d, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        out = conv_forward(self, x, weight, bias)
        return _DropGradient.apply(out) if torch.is_autocast_enabled("cpu") else out

    monkeypatch.setattr(torch.nn.Conv3d, "_conv_forward", faulty)


def test_bfloat16_gradients_are_checked_against_float32_for_the_networks_shape(faulty_bf16_conv: None,
                                                                             monkeypatch: pytest.MonkeyPatch,
                                                                             caplog: pytest.LogCaptureFixture) -> None:
    # Explicit bfloat16 on kernels that get it wrong: refused, naming the key and the layer.
    with pytest.raises(ConfigError, match=r"train.precision: bfloat16: .*features\.conv\.\d\.(weight|bias)"):
        MultiAgentPolicy(3, BF16_OBS, 5, small_tc(**BF16))
    # auto, on a machine where it would pick bfloat16: float32 instead, with a warning.
    monkeypatch.setattr("agents.multiagent.use_bf16", lambda precision, device: True)
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, BF16_OBS, 5, small_tc(precision="auto"))
    assert not policy.bf16 and not policy.nets[0].bf16
    assert "training in float32 instead" in caplog.text
    # The check draws from a forked RNG: the network starts as a float32 run's, so a run stays reproducible.
    torch.manual_seed(0)
    assert same(MultiAgentPolicy(3, BF16_OBS, 5, small_tc()).nets[0], snapshot(policy.nets)[0])
    monkeypatch.undo()
    # Sound kernels (this shape, float32 reference): bfloat16 is kept.
    assert bf16_gradient_error(BF16_OBS, 5, 32, 16)[1] <= BF16_GRADIENT_TOL
    assert MultiAgentPolicy(3, BF16_OBS, 5, small_tc(**BF16)).bf16


def random_masks(m: int, seed: int = 0) -> torch.Tensor:
    """(m, 5) int8 masks with about half the actions masked; idle (1) always allowed, as the env's."""
    g = torch.Generator().manual_seed(seed)
    masks = (torch.rand(m, 5, generator=g) < 0.5).to(torch.int8)
    masks[:, 1] = 1
    return masks


def test_masked_actions_are_never_sampled_and_their_logp_is_the_masked_one() -> None:
    torch.manual_seed(0)
    obs, agents, masks = torch.rand(300, *OBS), torch.zeros(300, dtype=torch.int64), random_masks(300)
    policy = MultiAgentPolicy(1, OBS, 5, small_tc())
    actions, logp, _ = policy.act(obs, agents, update=0, masks=masks)
    assert masks[torch.arange(300), actions].all()  # never a masked action
    with torch.no_grad():
        logits, _ = policy.nets[0](obs)
    want = torch.log_softmax(logits.masked_fill(masks == 0, float("-inf")), -1)[torch.arange(300), actions]
    torch.testing.assert_close(logp, want)
    # Without train.action_mask the masks are ignored: the same untrained policy then samples masked actions.
    free = MultiAgentPolicy(1, OBS, 5, small_tc(action_mask=False))
    free.nets[0].load_state_dict(policy.nets[0].state_dict())
    sampled, _, _ = free.act(obs, agents, update=0, masks=masks)
    assert not masks[torch.arange(300), sampled].all()


@pytest.mark.parametrize("action_mask", [True, False])
def test_the_update_takes_the_log_probabilities_of_the_distribution_that_acted(action_mask: bool) -> None:
    """PPO's first minibatch of its first epoch sees the network that acted: the ratio is 1 (approx_kl 0) exactly
    when the update masks as acting did; an update that ignores the masks sees other log-probabilities."""
    tc = small_tc(algo="ppo", ppo_epochs=1, ppo_minibatches=1, action_mask=action_mask)
    b = random_batch()
    torch.manual_seed(0)
    acting = MultiAgentPolicy(3, OBS, 5, small_tc(algo="ppo"))  # acts with the masks
    t, w, n = b.valid.shape
    b.masks[:] = random_masks(t * w * n).reshape(t, w, n, 5)
    flat_obs, flat_masks = b.obs.reshape(-1, *OBS), b.masks.reshape(-1, 5)
    actions, logp, values = acting.act(flat_obs, torch.arange(n).repeat(t * w), update=0, masks=flat_masks)
    b.actions[:], b.logp[:], b.values[:] = (x.reshape(t, w, n) for x in (actions, logp, values))
    torch.manual_seed(0)
    learner = MultiAgentPolicy(3, OBS, 5, tc)  # the same initial network as `acting`
    stats = learner.update(b, tc, update=0, progress=0.0)
    if action_mask:
        assert stats["approx_kl"] == pytest.approx(0.0, abs=1e-7) and stats["clip_fraction"] == 0.0
    else:
        assert stats["approx_kl"] > 1e-3


def test_bucket_rounds_up_by_at_most_an_eighth_to_few_sizes() -> None:
    sizes = [bucket(n) for n in range(1, 2049)]
    assert all(n <= b <= n + n // 8 for n, b in zip(range(1, 2049), sizes, strict=True))
    assert len(set(sizes)) <= 8 * 11 + 8  # eight per octave (and 1-8 as they are)


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_padding_a_minibatch_to_its_bucket_leaves_the_update_as_it_was(algo: str, monkeypatch) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=2, ppo_epochs=2)
    b = random_batch(T=11)  # 66 samples: PPO's minibatches of 33 padded to 36, A2C's whole batch to 72
    assert bucket(33) == 36 and bucket(66) == 72
    _, padded = trained(tc, copy_batch(b))
    monkeypatch.setattr("agents.multiagent.bucket", lambda n: n)
    _, unpadded = trained(tc, copy_batch(b))
    # Within float32's rounding of sums taken in another order (about 1e-6 here).
    for k, v in unpadded[0].items():
        torch.testing.assert_close(padded[0][k], v, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_a_minibatch_split_into_chunks_makes_the_update_and_statistics_of_one_pass(algo: str, monkeypatch) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=2, ppo_epochs=2, obs_norm=True)
    b = random_batch(T=11)  # 66 samples: A2C's one pass in 7 chunks of at most 10, PPO's minibatches of 33 in 4
    monkeypatch.setattr("agents.multiagent.UPDATE_CHUNK", 10)
    chunked_stats, chunked = trained(tc, copy_batch(b))
    monkeypatch.setattr("agents.multiagent.UPDATE_CHUNK", 1000)
    whole_stats, whole = trained(tc, copy_batch(b))
    for k, v in whole[0].items():
        torch.testing.assert_close(chunked[0][k], v, rtol=1e-5, atol=1e-6)
    assert chunked_stats.keys() == whole_stats.keys()
    for k, v in whole_stats.items():
        assert chunked_stats[k] == pytest.approx(v, rel=1e-5, abs=1e-6), k


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_a_central_critics_update_in_chunks_and_padded_is_its_update_in_one_pass(algo: str, monkeypatch) -> None:
    # The critic pools the features of each sample's team (its worker's AVs at its step): a chunk that cut a team,
    # or a padding row that joined one, would change the values and so the update (cut teams move a parameter by up
    # to 0.003 with PPO and 0.02 with A2C here, against the 1e-5 of float32's rounding allowed).
    tc = small_tc(algo=algo, ppo_minibatches=2, ppo_epochs=2, central_critic=True)
    b = random_batch(T=20)  # 40 teams of 3 (one of 2 from step 5 on): equal chunks of at most 20 would cut teams,
    b.valid[5:, 1, 2] = False  # and whole ones of 21 are padded to 22
    monkeypatch.setattr("agents.multiagent.UPDATE_CHUNK", 20)
    chunked_stats, chunked = trained(tc, copy_batch(b))
    monkeypatch.setattr("agents.multiagent.UPDATE_CHUNK", 1000)
    monkeypatch.setattr("agents.multiagent.bucket", lambda n: n)
    whole_stats, whole = trained(tc, copy_batch(b))
    for k, v in whole[0].items():
        torch.testing.assert_close(chunked[0][k], v, rtol=1e-5, atol=1e-5)
    for k, v in whole_stats.items():
        assert chunked_stats[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k


def test_chunks_of_a_minibatch_are_equal_or_hold_whole_teams(monkeypatch) -> None:
    monkeypatch.setattr("agents.multiagent.UPDATE_CHUNK", 5)
    teams = torch.tensor([0, 0, 0, 1, 1, 2, 2, 2, 2, 3, 4, 4])
    assert [(s.start, s.stop) for s in _chunks(12)] == [(0, 4), (4, 8), (8, 12)]
    assert [(s.start, s.stop) for s in _chunks(12, teams)] == [(0, 5), (5, 9), (9, 12)]
    assert _chunks(3, torch.zeros(3)) == [slice(0, 3)]


def stacked_batch(T: int = 6, W: int = 2, N: int = 3, obs: tuple[int, ...] = (3, 4, 8, 16)) -> Batch:
    """A batch whose agents' stacks shift by one frame per step, as the env's do: agent (w, i)'s observation at t
    is frames t .. t + F - 1 of its own sequence; agent (1, 2) starts anew at step 3 (a reset: older frames zero)
    and agent (0, 1) is gone after step 3."""
    b = random_batch(T=T, W=W, N=N, obs=obs)
    f = obs[0]
    g = torch.Generator().manual_seed(1)
    for w in range(W):
        for i in range(N):
            frames = torch.rand((T + f, *obs[1:]), generator=g)
            for t in range(T):
                b.obs[t, w, i] = frames[t:t + f]
    for t in range(3, T):
        b.obs[t, 1, 2, :max(0, f - 1 - (t - 3))] = 0.0
    b.valid[4:, 0, 1] = False
    return b


def test_a_sample_continues_the_one_before_it_where_its_stack_is_that_one_shifted_by_a_frame() -> None:
    b = stacked_batch()
    T, W, N = b.valid.shape
    rows = torch.arange(T * W * N)
    got = b.continues(rows).view(T, W, N)
    expected = torch.ones(T, W, N, dtype=torch.bool)
    expected[0] = False  # no step before
    expected[3, 1, 2] = False  # began anew
    expected[5, 0, 1] = False  # the one before it is not valid
    assert torch.equal(got, expected)
    # Where each frame is stored first holds that frame, and each frame is stored once but for the reset's zeros.
    valid = b.valid.flatten().nonzero().squeeze(1)
    sources = b.frame_sources(valid)
    assert torch.equal(b.frames(sources.flatten()).view(len(valid), *b.obs.shape[3:]), b.observations(valid))
    f = b.obs.shape[3]
    assert len(sources.unique()) == len(valid) + (f - 1) * W * N + (f - 1)  # newest frames, first stacks, the reset


@pytest.mark.parametrize("algo", ["a2c", "ppo"])
def test_frames_shared_by_samples_go_through_the_first_two_layers_once_without_a_change_to_the_update(
        algo: str, monkeypatch) -> None:
    tc = small_tc(algo=algo, ppo_minibatches=2, ppo_epochs=2, obs_norm=True)
    b = stacked_batch()
    seen: list[int] = []  # frames through the first two layers
    monkeypatch.setattr("agents.model.VelocityMapEncoder.frame_features",
                        lambda self, x, original=VelocityMapEncoder.frame_features: seen.append(len(x))
                        or original(self, x))
    shared_stats, shared = trained(tc, copy_batch(b))
    through_shared, seen[:] = sum(seen), []
    monkeypatch.setattr(Batch, "continues", lambda self, rows: torch.zeros(len(rows), dtype=torch.bool))
    own_stats, own = trained(tc, copy_batch(b))
    # A2C's one pass reads its agents' runs whole, about one frame per sample (34 samples of 3 frames here); PPO's
    # minibatches, drawn at random, hold fewer of a sample's neighbours.
    assert through_shared < (0.6 if algo == "a2c" else 0.9) * sum(seen)
    for k, v in own[0].items():
        torch.testing.assert_close(shared[0][k], v, rtol=1e-5, atol=1e-5)
    for k, v in own_stats.items():
        assert shared_stats[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k


@pytest.mark.parametrize("networks", [{"shared_policy": False}, {"central_critic": True}])
def test_acting_with_the_frame_memory_is_acting_without_it(networks: dict) -> None:
    tc = small_tc(obs_norm=True, **networks)
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, (3, 4, 8, 16), 5, tc)
    policy.update(stacked_batch(), tc, update=0, progress=0.0)  # input statistics taken in
    b = stacked_batch()
    T, W, N = b.valid.shape
    with policy.collecting():
        for t in range(T):
            w_, i_ = (x.flatten() for x in torch.meshgrid(torch.arange(W), torch.arange(N), indexing="ij"))
            keep = b.valid[t, w_, i_]
            w_, i_ = w_[keep], i_[keep]
            flat = (t * W + w_) * N + i_
            obs = b.observations(flat)
            torch.manual_seed(t)
            got = policy.act(obs, i_, update=1, slots=w_ * N + i_, continues=b.continues(flat), teams=w_)
            torch.manual_seed(t)
            expected = policy.act(obs, i_, update=1, teams=w_)
            assert torch.equal(got[0], expected[0])
            for a, e in zip(got[1:], expected[1:], strict=True):
                torch.testing.assert_close(a, e, atol=1e-6, rtol=1e-5)


def test_observations_gathers_the_samples_of_flat_indices() -> None:
    b = random_batch(T=4, W=3, N=2)
    t, w, i = torch.tensor([3, 0, 2, 2]), torch.tensor([1, 2, 0, 0]), torch.tensor([0, 1, 1, 0])
    got = b.observations((t * 3 + w) * 2 + i)
    assert torch.equal(got, b.obs[t, w, i])
    assert got.stride() == b.obs[t, w, i].stride()  # the batch's channels-last layout, which the network reads


def test_the_averaged_copy_follows_the_trained_weights_and_is_what_greedy_acting_plays() -> None:
    tc = small_tc(policy_ema=0.9, obs_norm=True)
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, OBS, 5, tc)
    obs, agents = torch.rand(6, *OBS), torch.tensor([0, 1, 2, 0, 1, 2])
    # Before any update greedy acting plays the trained network: there is no average yet.
    assert policy.played_net(0, 0) is policy.nets[0]
    expected = None
    for u in range(3):
        policy.update(random_batch(seed=u), tc, update=u, progress=0.0)
        now = snapshot(policy.nets)[0]
        if expected is None:  # the first average is a copy
            expected = now
        else:  # then a step toward the trained weights, the decay warmed up as TensorFlow's EMA does
            decay = min(0.9, (1 + u) / (10 + u))
            expected = {k: v if k.startswith("obs_norm.") else decay * expected[k] + (1 - decay) * v
                        for k, v in now.items()}
        for k, v in policy.averaged[0].state_dict().items():
            torch.testing.assert_close(v, expected[k])
    assert not same(policy.averaged[0], snapshot(policy.nets)[0])
    played = policy.played_net(0, 3)
    assert played is policy.averaged[0]
    with torch.no_grad():
        logits, _ = played(obs, float32=True)
        _, trained_values = policy.nets[0](obs)
    greedy, _, _ = policy.act(obs, agents, update=3, greedy=True)
    assert torch.equal(greedy, logits.argmax(-1))
    _, _, values = policy.act(obs, agents, update=3)  # sampling acts with the trained network
    torch.testing.assert_close(values, trained_values)
    # A policy file holds the averages; a resume gets them back, with their count.
    state = policy.state_dict()
    assert played_nets(state)[0] is state["averaged"][0]
    torch.manual_seed(1)
    resumed = MultiAgentPolicy(3, OBS, 5, tc)
    resumed.load_state_dict(state)
    assert resumed.averaged_counts == [3] and same(resumed.averaged[0], policy.averaged[0].state_dict())
    # Without train.policy_ema there are none, and the policy file holds the trained network.
    plain = MultiAgentPolicy(3, OBS, 5, small_tc()).state_dict()
    assert "averaged" not in plain and played_nets(plain) is plain["nets"]


def test_acting_in_a_collecting_region_is_acting_outside_it_and_the_next_region_sees_new_weights() -> None:
    # In bfloat16 the region reuses each weight's cast (autocast's cache) until it closes.
    tc = small_tc(precision="bfloat16")
    torch.manual_seed(0)
    policy = MultiAgentPolicy(3, BF16_OBS, 5, tc)
    assert policy.bf16
    obs, agents = torch.rand(6, *BF16_OBS), torch.tensor([0, 1, 2, 0, 1, 2])
    torch.manual_seed(5)
    outside = policy.act(obs, agents, update=0)
    with policy.collecting():
        torch.manual_seed(5)
        inside = policy.act(obs, agents, update=0)
        values_before = policy.value(obs, agents, update=0)
    for a, b in zip(outside, inside, strict=True):
        assert torch.equal(a, b)
    with torch.no_grad():  # what an update does between two regions
        for p in policy.nets[0].parameters():
            p.mul_(1.5)
    with policy.collecting():
        values_after = policy.value(obs, agents, update=0)
    assert torch.equal(values_after, policy.value(obs, agents, update=0))
    assert not torch.equal(values_after, values_before)
