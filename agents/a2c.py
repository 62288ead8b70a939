"""A2C's pure parts: GAE(lambda) advantages with terminated/truncated kept apart, the loss, optimizers.

Contract:
- `gae(...)` maps per-sample rewards, values, next-state values and end flags, all shaped (T, B) with time
  first, to advantages and returns (T, B). A terminated sample does not bootstrap (its next value counts
  as 0); a truncated one bootstraps from `next_values` (the value of its final observation) but, like a
  terminated one, cuts the lambda-trace. Invalid samples (agent absent, lost episode) get 0 and also cut
  the trace. With lambda = 1 the advantage is the n-step return minus V(s); with T = 1 it is the paper's
  r + gamma V(s') - V(s).
- `a2c_loss(...)` is the policy-gradient, value and entropy loss over a flat batch of valid samples.
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
    policy: torch.Tensor  # -E[log pi(a|s) A]
    value: torch.Tensor  # E[(R - V)^2]
    entropy: torch.Tensor  # E[H(pi(.|s))]


def a2c_loss(
    logits: torch.Tensor,
    values: torch.Tensor,
    actions: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    entropy_coef: float,
    value_coef: float,
    normalize_advantage: bool = False,
) -> LossTerms:
    """Loss over M valid samples: logits (M, A), values (M,), actions (M,), advantages (M,), returns (M,)."""
    advantages = advantages.detach()
    if normalize_advantage and advantages.numel() > 1:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    dist = torch.distributions.Categorical(logits=logits)
    policy = -(dist.log_prob(actions) * advantages).mean()
    value = (returns.detach() - values).pow(2).mean()
    entropy = dist.entropy().mean()
    return LossTerms(policy + value_coef * value - entropy_coef * entropy, policy, value, entropy)


def _adam(params: Iterable[nn.Parameter], tc: TrainConfig) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=tc.lr, eps=tc.optimizer_eps)


def _rmsprop(params: Iterable[nn.Parameter], tc: TrainConfig) -> torch.optim.Optimizer:
    return torch.optim.RMSprop(params, lr=tc.lr, alpha=0.99, eps=tc.optimizer_eps)


OPTIMIZERS: dict[str, Callable[[Iterable[nn.Parameter], TrainConfig], torch.optim.Optimizer]] = {
    "adam": _adam,
    "rmsprop": _rmsprop,
}
