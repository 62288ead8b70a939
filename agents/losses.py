"""The learner's pure parts: GAE(lambda) advantages with terminated/truncated kept apart, the A2C and
PPO-clip losses, value normalisation, optimizers.

Contract:
- `gae(...)` maps per-sample rewards, values, next-state values and end flags, all shaped (T, B) with time
  first, to advantages and returns (T, B). A terminated sample does not bootstrap (its next value counts
  as 0); a truncated one bootstraps from `next_values` (the value of its final observation) but, like a
  terminated one, cuts the lambda-trace. Invalid samples (agent absent, lost episode) get 0 and also cut
  the trace. With lambda = 1 the advantage is the n-step return minus V(s); with T = 1 it is the paper's
  r + gamma V(s') - V(s).
- `actor_critic_loss(...)` is the policy, value and entropy loss over a flat batch of valid samples: A2C's
  policy gradient -E[log pi(a|s) A], or with `clip_range` PPO's clipped surrogate
  -E[min(rho A, clip(rho, 1 - eps, 1 + eps) A)], rho = pi(a|s) / pi_old(a|s).
- `normalize(x)` standardises advantages over a batch.
- `masked_logits(logits, mask)` sets the logits of masked actions (mask 0) to -inf: they get probability 0 in
  sampling, log-probabilities and entropy alike. `actor_critic_loss(..., mask=...)` applies it, so the update's
  log-probabilities and entropy are those of the distribution the actions were sampled from.
- `ValueNorm` keeps running (debiased exponential) mean and variance of the critic's targets, so that the
  critic learns returns of any scale at unit scale (MAPPO's value normalisation).
- `OPTIMIZERS` maps `train.optimizer` names to builders.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from torch import nn

from agents.config import TrainConfig


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    terminated: torch.Tensor,
    truncated: torch.Tensor,
    gamma: float,
    gae_lambda: float,
    valid: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and returns (T, B) from float rewards/values/next_values and bool flags, all (T, B).

    `next_values[t]` is V of the observation that follows sample t for the same agent: the next sample's
    observation when the agent goes on, the final observation when it was truncated (ignored if it
    terminated). Sample t + 1 continues sample t unless t ended (terminated, truncated) or is invalid.
    """
    if valid is None:
        valid = torch.ones_like(terminated, dtype=torch.bool)
    not_terminated = (~terminated).to(values.dtype)
    goes_on = (~(terminated | truncated) & valid).to(values.dtype)
    advantages = torch.zeros_like(values)  # (T, B)
    running = torch.zeros_like(values[0])  # (B,) advantage of the following sample
    for t in reversed(range(rewards.shape[0])):
        delta = rewards[t] + gamma * not_terminated[t] * next_values[t] - values[t]
        running = torch.where(valid[t], delta + gamma * gae_lambda * goes_on[t] * running, 0.0)
        advantages[t] = running
    returns = torch.where(valid, advantages + values, 0.0)
    return advantages, returns


@dataclass(frozen=True)
class LossTerms:
    loss: torch.Tensor  # scalar to minimise
    policy: torch.Tensor  # the policy term
    value: torch.Tensor  # E[(R - V)^2]
    entropy: torch.Tensor  # E[H(pi(.|s))]
    approx_kl: torch.Tensor  # E[log pi_old - log pi] (0 without old log-probabilities)
    clip_fraction: torch.Tensor  # share of samples whose ratio was clipped (ppo)


def masked_logits(logits: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """`logits` (M, A) with -inf where `mask` (M, A; nonzero = allowed) is 0; None leaves them as they are. Every row
    must allow an action (the env's idle always is)."""
    return logits if mask is None else logits.masked_fill(mask.to(logits.device) == 0, float("-inf"))


def normalize(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / (x.std() + 1e-8) if x.numel() > 1 else x - x.mean()


def actor_critic_loss(
    logits: torch.Tensor,
    values: torch.Tensor,
    actions: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    entropy_coef: float,
    value_coef: float,
    old_logp: torch.Tensor | None = None,
    clip_range: float | None = None,
    mask: torch.Tensor | None = None,
) -> LossTerms:
    """Loss over M samples: logits (M, A), values (M,), actions (M,), advantages (M,), returns (M,) (the
    critic's targets, in the critic's own scale), old_logp (M,) (needed with `clip_range`), mask (M, A) (the
    action masks the actions were sampled under, or None)."""
    advantages, returns = advantages.detach(), returns.detach()
    dist = torch.distributions.Categorical(logits=masked_logits(logits, mask))
    logp = dist.log_prob(actions)
    zero = torch.zeros((), device=logits.device)
    approx_kl, clipped = zero, zero
    if old_logp is not None:
        log_ratio = logp - old_logp
        approx_kl = ((log_ratio.exp() - 1) - log_ratio).mean().detach()  # k3 estimator, >= 0
    if clip_range is None:
        policy = -(logp * advantages).mean()
    else:
        if old_logp is None:
            raise ValueError("actor_critic_loss: clip_range needs old_logp")
        ratio = (logp - old_logp).exp()
        policy = -torch.min(ratio * advantages, ratio.clamp(1 - clip_range, 1 + clip_range) * advantages).mean()
        clipped = ((ratio - 1).abs() > clip_range).float().mean().detach()
    value = (returns - values).pow(2).mean()
    entropy = dist.entropy().mean()
    return LossTerms(policy + value_coef * value - entropy_coef * entropy, policy, value, entropy, approx_kl,
                     clipped)


class ValueNorm(torch.nn.Module):
    """Running mean and variance of the critic's targets (exponential with weight `beta` per update, debiased)."""

    def __init__(self, beta: float = 0.995, eps: float = 1e-5) -> None:
        super().__init__()
        self.beta, self.eps = beta, eps
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean_sq", torch.zeros((), dtype=torch.float64))
        self.register_buffer("debias", torch.zeros((), dtype=torch.float64))

    def stats(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self.debias == 0:
            return torch.zeros((), dtype=torch.float64), torch.ones((), dtype=torch.float64)
        mean = self.mean / self.debias
        var = (self.mean_sq / self.debias - mean * mean).clamp(min=self.eps)
        return mean, var.sqrt()

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.detach().to(torch.float64)
        self.mean.mul_(self.beta).add_((1 - self.beta) * x.mean())
        self.mean_sq.mul_(self.beta).add_((1 - self.beta) * (x * x).mean())
        self.debias.mul_(self.beta).add_(1 - self.beta)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.stats()
        return ((x - mean) / std).to(x.dtype)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.stats()
        return (x * std + mean).to(x.dtype)


def _adam(params: Iterable[nn.Parameter], tc: TrainConfig) -> torch.optim.Optimizer:
    # Fused: one kernel over all parameters. torch's default on the CPU is a loop over them, 8x slower for the
    # default network's 2 M parameters (17 against 2 ms per step on one thread; docs/speed.md).
    return torch.optim.Adam(params, lr=tc.lr, eps=tc.optimizer_eps, fused=True)


def _rmsprop(params: Iterable[nn.Parameter], tc: TrainConfig) -> torch.optim.Optimizer:
    # torch has no fused RMSprop; foreach batches its per-parameter loop (the CPU's default is the plain loop).
    return torch.optim.RMSprop(params, lr=tc.lr, alpha=0.99, eps=tc.optimizer_eps, foreach=True)


OPTIMIZERS: dict[str, Callable[[Iterable[nn.Parameter], TrainConfig], torch.optim.Optimizer]] = {
    "adam": _adam,
    "rmsprop": _rmsprop,
}
