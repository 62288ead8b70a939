"""GAE / n-step advantages against hand-computed values, terminated vs truncated, the A2C and PPO losses (with
action masks too), value normalisation."""

import math

import pytest
import torch

from agents.losses import OPTIMIZERS, ValueNorm, actor_critic_loss, gae, masked_logits, normalize


def col(*values: float) -> torch.Tensor:
    """A (T, 1) float column: T steps of one agent."""
    return torch.tensor(values, dtype=torch.float32)[:, None]


def flags(*values: bool) -> torch.Tensor:
    return torch.tensor(values)[:, None]


def test_one_step_lambda_one_is_the_papers_advantage() -> None:
    # A = r + gamma V(s') - V(s) for every sample, whatever the batch.
    r, v, v_next = torch.tensor([[1.0, -2.0, 0.5]]), torch.tensor([[0.3, 0.1, -1.0]]), torch.tensor([[2.0, 0.0, 4.0]])
    no = torch.zeros(1, 3, dtype=torch.bool)
    adv, ret = gae(r, v, v_next, no, no, gamma=0.9, gae_lambda=1.0)
    torch.testing.assert_close(adv, r + 0.9 * v_next - v)
    torch.testing.assert_close(ret, r + 0.9 * v_next)


def test_n_step_return_with_lambda_one() -> None:
    # Three steps, no end: A_0 = r0 + g r1 + g^2 r2 + g^3 V(s3) - V(s0).
    g = 0.5
    r, v = col(1.0, 2.0, 3.0), col(0.5, 1.0, 1.5)
    v_next = col(1.0, 1.5, 4.0)  # V(s1), V(s2), V(s3) (bootstrap)
    no = flags(False, False, False)
    adv, ret = gae(r, v, v_next, no, no, gamma=g, gae_lambda=1.0)
    expected_ret = [1 + g * 2 + g**2 * 3 + g**3 * 4, 2 + g * 3 + g**2 * 4, 3 + g * 4]
    torch.testing.assert_close(ret, col(*expected_ret))
    torch.testing.assert_close(adv, col(*expected_ret) - v)


def test_gae_lambda_hand_computed() -> None:
    g, lam = 0.9, 0.5
    r, v, v_next = col(1.0, 0.0), col(0.2, 0.4), col(0.4, 1.0)
    no = flags(False, False)
    adv, _ = gae(r, v, v_next, no, no, gamma=g, gae_lambda=lam)
    d1 = 0.0 + g * 1.0 - 0.4
    d0 = 1.0 + g * 0.4 - 0.2
    torch.testing.assert_close(adv, col(d0 + g * lam * d1, d1))


def test_termination_does_not_bootstrap_and_cuts_the_trace() -> None:
    # Step 1 crashes; step 2 is the first step of the next episode of the same slot.
    g = 0.9
    r, v = col(1.0, -5.0, 2.0), col(0.5, 0.7, 0.1)
    v_next = col(0.7, 99.0, 0.3)  # 99 is whatever follows the crash: must be ignored
    term, trunc = flags(False, True, False), flags(False, False, False)
    adv, ret = gae(r, v, v_next, term, trunc, gamma=g, gae_lambda=1.0)
    torch.testing.assert_close(ret, col(1.0 + g * -5.0, -5.0, 2.0 + g * 0.3))
    torch.testing.assert_close(adv, ret - v)


def test_truncation_bootstraps_from_the_final_observation_and_cuts_the_trace() -> None:
    g = 0.9
    r, v = col(1.0, 1.0, 2.0), col(0.5, 0.7, 0.1)
    v_next = col(0.7, 3.0, 0.3)  # 3.0 = V(final observation) of the truncated step 1
    term, trunc = flags(False, False, False), flags(False, True, False)
    adv, ret = gae(r, v, v_next, term, trunc, gamma=g, gae_lambda=1.0)
    torch.testing.assert_close(ret, col(1.0 + g * (1.0 + g * 3.0), 1.0 + g * 3.0, 2.0 + g * 0.3))
    torch.testing.assert_close(adv, ret - v)


def test_invalid_samples_are_zero_and_cut_the_trace() -> None:
    r, v, v_next = col(1.0, 7.0, 2.0), col(0.0, 7.0, 0.0), col(0.0, 7.0, 0.0)
    no = flags(False, False, False)
    valid = flags(True, False, True)
    adv, ret = gae(r, v, v_next, no, no, gamma=1.0, gae_lambda=1.0, valid=valid)
    torch.testing.assert_close(adv, col(1.0, 0.0, 2.0))
    torch.testing.assert_close(ret, col(1.0, 0.0, 2.0))


def test_a2c_loss_hand_computed() -> None:
    logits = torch.zeros(2, 5, requires_grad=True)  # uniform policy: log pi = -log 5, entropy = log 5
    values = torch.tensor([1.0, 2.0], requires_grad=True)
    actions = torch.tensor([0, 3])
    adv, ret = torch.tensor([1.0, -3.0]), torch.tensor([2.0, 2.0])
    terms = actor_critic_loss(logits, values, actions, adv, ret, entropy_coef=0.1, value_coef=0.5)
    policy = -(-math.log(5) * 1.0 + -math.log(5) * -3.0) / 2
    value = (1.0**2 + 0.0**2) / 2
    assert terms.policy.item() == pytest.approx(policy)
    assert terms.value.item() == pytest.approx(value)
    assert terms.entropy.item() == pytest.approx(math.log(5))
    assert terms.loss.item() == pytest.approx(policy + 0.5 * value - 0.1 * math.log(5))
    terms.loss.backward()
    assert logits.grad is not None and values.grad is not None


def test_masked_actions_leave_the_loss_and_its_gradient() -> None:
    """Uniform logits over 5 actions, 2 of them masked in sample 0 and 4 in sample 1: log pi and the entropy are
    those of the uniform policy over the allowed actions, and the masked logits get no gradient."""
    logits = torch.zeros(2, 5, requires_grad=True)
    mask = torch.tensor([[1, 1, 1, 0, 0], [0, 1, 0, 0, 0]], dtype=torch.int8)
    actions, adv, ret = torch.tensor([0, 1]), torch.tensor([1.0, -3.0]), torch.zeros(2)
    terms = actor_critic_loss(logits, torch.zeros(2), actions, adv, ret, entropy_coef=0.1, value_coef=0.5, mask=mask)
    assert terms.policy.item() == pytest.approx(-(-math.log(3) * 1.0 + 0.0 * -3.0) / 2)
    assert terms.entropy.item() == pytest.approx((math.log(3) + 0.0) / 2)
    terms.loss.backward()
    assert torch.isfinite(logits.grad).all() and (logits.grad[mask == 0] == 0).all()
    assert (logits.grad[0, :3] != 0).all()
    unmasked = actor_critic_loss(logits, torch.zeros(2), actions, adv, ret, entropy_coef=0.1, value_coef=0.5)
    assert unmasked.policy.item() == pytest.approx(-(-math.log(5) * 1.0 + -math.log(5) * -3.0) / 2)
    assert masked_logits(logits, None) is logits


def test_ppo_clipped_loss_hand_computed() -> None:
    # Two actions, log pi(a0) = log 0.8 and log pi(a1) = log 0.2 now; before the update they were 0.5 and 0.5.
    logits = torch.log(torch.tensor([[0.8, 0.2], [0.8, 0.2], [0.8, 0.2]]))
    actions = torch.tensor([0, 0, 1])
    old_logp = torch.log(torch.tensor([0.5, 0.5, 0.5]))
    adv = torch.tensor([1.0, -1.0, 1.0])
    values, ret = torch.zeros(3), torch.zeros(3)
    terms = actor_critic_loss(logits, values, actions, adv, ret, entropy_coef=0.0, value_coef=0.0,
                              old_logp=old_logp, clip_range=0.2)
    # ratios 1.6, 1.6, 0.4; clipped to 1.2, 1.2, 0.8:
    # min(1.6 * 1, 1.2 * 1) = 1.2; min(1.6 * -1, 1.2 * -1) = -1.6; min(0.4 * 1, 0.8 * 1) = 0.4
    assert terms.policy.item() == pytest.approx(-(1.2 - 1.6 + 0.4) / 3)
    assert terms.clip_fraction.item() == pytest.approx(1.0)
    # k3 KL estimate: mean of (rho - 1) - log rho
    rho = torch.tensor([1.6, 1.6, 0.4])
    assert terms.approx_kl.item() == pytest.approx(((rho - 1) - rho.log()).mean().item(), rel=1e-5)
    # Inside the clip range PPO's surrogate has A2C's gradient.
    logits = torch.zeros(1, 2, requires_grad=True)
    ppo = actor_critic_loss(logits, torch.zeros(1), torch.tensor([0]), torch.tensor([2.0]), torch.zeros(1), 0.0,
                            0.0, old_logp=torch.log(torch.tensor([0.5])), clip_range=0.2)
    (g_ppo,) = torch.autograd.grad(ppo.policy, logits)
    a2c = actor_critic_loss(logits, torch.zeros(1), torch.tensor([0]), torch.tensor([2.0]), torch.zeros(1), 0.0, 0.0)
    (g_a2c,) = torch.autograd.grad(a2c.policy, logits)
    torch.testing.assert_close(g_ppo, g_a2c)
    with pytest.raises(ValueError, match="old_logp"):
        actor_critic_loss(logits, torch.zeros(1), torch.tensor([0]), torch.ones(1), torch.zeros(1), 0.0, 0.0,
                          clip_range=0.2)


def test_value_norm_tracks_the_targets_scale() -> None:
    vn = ValueNorm(beta=0.5)
    x = torch.tensor([100.0, 110.0, 90.0, 100.0])
    assert torch.equal(vn.normalize(x), x)  # nothing seen yet: identity
    for _ in range(30):
        vn.update(x)
    mean, std = vn.stats()
    assert mean.item() == pytest.approx(100.0) and std.item() == pytest.approx(x.std(unbiased=False).item(), rel=1e-3)
    torch.testing.assert_close(vn.denormalize(vn.normalize(x)), x)
    assert normalize(torch.tensor([1.0, 3.0])).tolist() == pytest.approx([-0.7071, 0.7071], abs=1e-4)


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_optimizer_factory(name: str) -> None:
    from agents.config import TrainConfig

    p = torch.nn.Parameter(torch.ones(3))
    opt = OPTIMIZERS[name]([p], TrainConfig(lr=0.1))
    p.sum().backward()
    opt.step()
    assert not torch.equal(p.detach(), torch.ones(3))
