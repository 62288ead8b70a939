"""The AVs' networks and the paper's semi-sequential training scheme.

Contract (N AVs, K = `disseminate_every`):
- Networks: `nets[k]` are the trained networks, one per AV (decentralised, default) or a single one shared
  by all AVs (`shared_policy`); `owner(i)` is the index of AV i's network. Each trained network has a
  frozen *acting copy* `acting[k]` and its own optimizer.
- Learner: update u trains the network of AV `learner(u) = (u // K) % N` only, on that AV's samples
  only, so the learner's data are on-policy. The learner acts with its live network `nets[owner(l)]`;
  every other AV acts with its frozen acting copy.
- Dissemination: after the K-th update of a learner's block, `nets[owner(l)]` is copied into
  `acting[owner(l)]` (decentralised: AV l's own copy; shared: the copy all AVs act with) and the next AV
  becomes the learner. Between disseminations no acting copy and no other AV's network changes.
"""

from __future__ import annotations

import copy
from typing import Any

import torch

from agents.a2c import OPTIMIZERS
from agents.config import TrainConfig
from agents.model import ActorCritic


class MultiAgentPolicy:
    """Trained networks, acting copies and optimizers of N AVs, with the learner schedule."""

    def __init__(self, n_agents: int, obs_shape: tuple[int, ...], n_actions: int, tc: TrainConfig,
                 device: torch.device | str = "cpu") -> None:
        self.n_agents = n_agents
        self.shared = tc.shared_policy
        self.disseminate_every = tc.disseminate_every
        self.device = torch.device(device)
        n_nets = 1 if self.shared else n_agents
        self.nets = [ActorCritic(obs_shape, n_actions, feature_dim=tc.feature_dim, head_hidden=tc.head_hidden)
                     .to(self.device) for _ in range(n_nets)]
        self.acting = [copy.deepcopy(net).requires_grad_(False) for net in self.nets]
        self.optimizers = [OPTIMIZERS[tc.optimizer](net.parameters(), tc) for net in self.nets]

    def owner(self, agent: int) -> int:
        """Index into `nets` / `acting` of AV `agent`'s network."""
        return 0 if self.shared else agent

    def learner(self, update: int) -> int:
        """The AV whose network update number `update` (0-based) trains."""
        return (update // self.disseminate_every) % self.n_agents

    def acting_net(self, agent: int, update: int) -> ActorCritic:
        """The network AV `agent` acts with while update `update` is being collected."""
        k = self.owner(agent)
        return self.nets[k] if agent == self.learner(update) else self.acting[k]

    def ends_block(self, update: int) -> bool:
        """Whether update `update` is the last of its learner's block, i.e. dissemination follows it."""
        return (update + 1) % self.disseminate_every == 0

    def disseminate(self, agent: int) -> None:
        """Copy AV `agent`'s trained network into its acting copy (all AVs' copy when shared)."""
        k = self.owner(agent)
        self.acting[k].load_state_dict(self.nets[k].state_dict())

    @torch.no_grad()
    def act(self, obs: torch.Tensor, alive: torch.Tensor, update: int) -> torch.Tensor:
        """Sampled actions (W, N) int64 for observations (W, N, F, C, H, W) of the AVs where alive (W, N).

        AVs acting with the same network are batched into one forward; absent AVs get action 1 (idle).
        """
        actions = torch.ones(alive.shape, dtype=torch.int64)  # (W, N)
        groups: dict[int, list[int]] = {}
        for i in range(self.n_agents):
            groups.setdefault(id(self.acting_net(i, update)), []).append(i)
        for agents in groups.values():
            net = self.acting_net(agents[0], update)
            sel = torch.zeros(alive.shape, dtype=torch.bool)
            sel[:, agents] = alive[:, agents]
            if sel.any():
                logits, _ = net(obs[sel].to(self.device))  # (M, A)
                actions[sel] = torch.distributions.Categorical(logits=logits).sample().cpu()
        return actions

    def state_dict(self) -> dict[str, Any]:
        return {
            "nets": [net.state_dict() for net in self.nets],
            "acting": [net.state_dict() for net in self.acting],
            "optimizers": [opt.state_dict() for opt in self.optimizers],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for modules, key in ((self.nets, "nets"), (self.acting, "acting"), (self.optimizers, "optimizers")):
            if len(state[key]) != len(modules):
                raise ValueError(f"{key}: expected {len(modules)} entries, got {len(state[key])}")
            for module, sd in zip(modules, state[key], strict=True):
                module.load_state_dict(sd)


def parameters_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether two networks hold exactly the same parameters and buffers."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
