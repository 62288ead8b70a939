"""The AVs' networks and how they learn from one batch: a shared network, or the paper's per-AV scheme.

Contract (N AVs):
- `shared_policy` (the default): one network `nets[0]`; every AV acts with it and every live AV's sample
  trains it (the VelocityMap is ego-centred, so one network serves every AV).
- Per AV (the paper's semi-sequential scheme, K = `disseminate_every`): `nets[i]` is AV i's network, with a
  frozen *acting copy* `acting[i]`. Update u trains only the network of AV `learner(u) = (u // K) % N`, on
  every sample of that AV in the batch (all workers, all steps: the data this scheme allows, since the
  other AVs' networks stay frozen); the learner acts with its live network, the others with their frozen
  copies. After the K-th update of a block the learner's network is copied into its acting copy
  (dissemination) and the next AV becomes the learner.
- `act(obs, agents, update, masks)` samples actions for a flat batch of observations of the given AV indices, one
  forward per network in play, and returns the log-probabilities and values (in the critic's scale) the
  update needs; `value(...)` gives values alone (final observations of truncated agents). With
  `train.action_mask` the env's action masks (`Batch.masks`) bound the policy: masked actions get logit -inf when
  acting and in the update's log-probabilities and entropy (`agents.losses.masked_logits`); without it the masks
  are stored and ignored.
- With `train.policy_ema` each network has an *averaged copy* `averaged[k]`: after every update that trains
  network k, its weights move toward the trained ones by the decay (TensorFlow's ExponentialMovingAverage warm-up:
  at most (1 + n) / (10 + n) after n averages; the first copies them) and its input statistics (`ObsNorm`) are
  the trained network's. Greedy acting (`act(..., greedy=True)`: validation) plays the averaged copies once they
  have begun, and the policy files hold them (`agents.checkpoint.played_nets`); sampling acts with the trained ones.
- `update(batch, tc, progress)` runs A2C (one gradient step over the batch) or PPO (`ppo_epochs` passes of
  `ppo_minibatches` minibatches, clipped) for each network that trains this update, with advantages from
  GAE over the batch, advantage normalisation and value normalisation as configured, the learning rate
  and entropy weight of the schedules at `progress` in [0, 1]; returns loss statistics.
- With `train.central_critic` the critic pools the features of each sample's team, the AVs of its worker at its
  decision (`teams` in `act` and `value`, the collector's; `ActorCritic.forward`): the update draws its minibatches team
  by team and cuts them into chunks that hold whole teams (`_chunks`).
- A frame goes through the network's first two layers once where samples share it (the first's depth kernel is 1,
  the second's depth stride 1, and an agent's stack shifts by one frame per decision: `ActorCritic.frame_features`):
  the update reads each minibatch's distinct frames (`Batch.frame_sources`), and acting in a collecting region keeps
  each slot's last frame features (`agents.model.FrameMemory`).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from torch.optim.swa_utils import get_ema_multi_avg_fn

from agents.config import TrainConfig, schedule, use_bf16
from agents.losses import OPTIMIZERS, ValueNorm, actor_critic_loss, gae, masked_logits, normalize
from agents.model import BF16_GRADIENT_TOL, ActorCritic, FrameMemory, bf16_gradient_error
from cosim.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class Batch:
    """One update's samples, time first, allocated once for T steps of W workers with N agents."""

    obs: torch.Tensor  # (T, W, N, F, C, H, W) env dtype, stored channels last: the observation acted on
    valid: torch.Tensor  # (T, W, N) bool: the agent acted at that step of an episode that was not lost
    actions: torch.Tensor  # (T, W, N) int64
    logp: torch.Tensor  # (T, W, N) log-probability of the action when it was chosen
    values: torch.Tensor  # (T, W, N) the acting critic's value, in its own (normalised) scale
    rewards: torch.Tensor  # (T, W, N)
    terminated: torch.Tensor  # (T, W, N) bool
    truncated: torch.Tensor  # (T, W, N) bool
    final_values: torch.Tensor  # (T, W, N) value of the final observation of a truncated sample
    masks: torch.Tensor  # (T, W, N, A) int8: the env's action mask each action was chosen under (1 = allowed)

    @classmethod
    def allocate(cls, steps: int, workers: int, agents: int, obs_shape: tuple[int, ...], dtype: torch.dtype,
                 n_actions: int) -> Batch:
        twn = (steps, workers, agents)
        # Stored channels last, (F, H, W, C) per observation, and read as (F, C, H, W): what the network's input
        # copy walks (agents.model.VelocityMapEncoder). Its copy from this layout is a plain conversion, about 6x
        # faster than the gather from the env's layout, and it runs on every acting forward and every update pass,
        # where the one permuting copy into this batch runs once per sample.
        f, c, h, w = obs_shape
        obs = torch.zeros((*twn, f, h, w, c), dtype=dtype).permute(0, 1, 2, 3, 6, 4, 5)
        return cls(obs, torch.zeros(twn, dtype=torch.bool),
                   torch.zeros(twn, dtype=torch.int64), torch.zeros(twn), torch.zeros(twn), torch.zeros(twn),
                   torch.zeros(twn, dtype=torch.bool), torch.zeros(twn, dtype=torch.bool), torch.zeros(twn),
                   torch.ones((*twn, n_actions), dtype=torch.int8))  # every action allowed until collect writes

    def clear(self) -> None:
        for t in (self.valid, self.rewards, self.terminated, self.truncated, self.final_values):
            t.zero_()

    def observations(self, rows: torch.Tensor) -> torch.Tensor:
        """The observations (M, F, C, H, W) of samples `rows` (M,), flat indices into (T, W, N), in the batch's
        channels-last layout."""
        # One row copy each, in the layout they are stored in: advanced indexing (obs[t, w, i], or a flat obs[rows])
        # took 12-18 times as long (1.0 against 0.05 ms for an acting batch of 20, 6.9 against 0.6 for a PPO
        # minibatch of 140; one thread, AMD EPYC): a tenth of the learner's time while collecting.
        return self._stored().flatten(0, 2).index_select(0, rows).permute(0, 1, 4, 2, 3)

    def frames(self, ids: torch.Tensor) -> torch.Tensor:
        """Frames (K, C, H, W) by flat index `sample * F + frame` (`sample` as in `observations`), copied."""
        return self._stored().flatten(0, 3).index_select(0, ids).permute(0, 3, 1, 2)

    def continues(self, rows: torch.Tensor) -> torch.Tensor:
        """For samples `rows` (M,) (flat, as in `observations`), whether the same agent's sample one step earlier is
        valid and its observation's frames but the oldest are this one's but the newest (M,) bool: a stack that
        shifted by one frame (not one that began anew, after a reset or in a slot another agent took over)."""
        step = self.valid[0].numel()
        earlier = rows - step
        out = (earlier >= 0) & self.valid.flatten()[earlier.clamp(min=0)]
        at = out.nonzero().squeeze(1)
        stored = self._stored().flatten(0, 2)  # (T * W * N, F, H, W, C)
        now, before = stored.index_select(0, rows[at]), stored.index_select(0, earlier[at])
        out[at] = (now[:, :-1] == before[:, 1:]).flatten(1).all(1)
        return out

    def frame_sources(self, rows: torch.Tensor) -> torch.Tensor:
        """For samples `rows` (M,), where each of their frames is stored first (M, F), as a flat index (`frames`):
        back through the same agent's samples that continue one another (`continues`), in the one where the frame
        was the newest, or in the first of them. Samples that share a frame get the same index."""
        f = self.obs.shape[3]
        step = self.valid[0].numel()
        earlier = torch.full((self.valid.numel(),), -1, dtype=torch.long)
        earlier[rows] = torch.where(self.continues(rows), rows - step, -1)
        sample, frame = rows[:, None].repeat(1, f), torch.arange(f).repeat(len(rows), 1)
        for _ in range(f - 1):  # frame k of a continuing sample is frame k + 1 of the one before it
            back = earlier[sample]
            move = (frame < f - 1) & (back >= 0)
            sample, frame = torch.where(move, back, sample), frame + move
        return sample * f + frame

    def _stored(self) -> torch.Tensor:
        """The observations as stored, (T, W, N, F, H, W, C) contiguous."""
        return self.obs.permute(0, 1, 2, 3, 5, 6, 4)


# The most samples one forward+backward of the update takes: a larger minibatch (A2C's whole batch, PPO's of a large
# update) is split into equal chunks whose gradients add up to its own before the one optimizer step. Its activations
# then stay within what the cores' caches hold: A2C's pass over a batch of 358 samples took 1.03-1.10 ms per sample in
# chunks of 128 against 1.19-1.47 in one (2 cores of an AMD EPYC with AVX512-BF16, bfloat16; docs/speed.md).
UPDATE_CHUNK = 128


def bucket(n: int) -> int:
    """`n` rounded up to one of eight sizes per octave (a step of 2^(floor(log2 n) - 3)): at most 1/8 more.

    oneDNN builds its kernels for each input shape it meets and caches them: a forward+backward of the network at a
    batch size it has not met costs about 1.5 times one at a size it has (0.60 against 0.41 ms per sample, 2 cores of
    an Intel Xeon with AMX). The update's batch, the samples its episodes made, is a new size almost every time;
    rounded, the sizes of a whole run fit in a few dozen, each built once."""
    step = 1 << max(n.bit_length() - 4, 0)
    return -(-n // step) * step


def _bf16_sound(obs_shape: tuple[int, ...], n_actions: int, tc: TrainConfig, device: torch.device) -> bool:
    """Whether this machine's bfloat16 kernels give right gradients for this network (`bf16_gradient_error`):
    if not, `auto` falls back to float32 with a warning and an explicit `bfloat16` is refused."""
    name, err = bf16_gradient_error(obs_shape, n_actions, tc.feature_dim, tc.head_hidden, device)
    if err <= BF16_GRADIENT_TOL:
        return True
    problem = (f"bfloat16 gradients on this {device.type.upper()} are wrong for observation shape {tuple(obs_shape)}: "
               f"{name} is off float32's by {err:.3g} (relative; sound kernels stay within 0.003)")
    if tc.precision == "bfloat16":
        raise ConfigError(f"train.precision: bfloat16: {problem}; use float32, or auto, which falls back to it")
    log.warning("%s; training in float32 instead (train.precision: auto)", problem)
    return False


def _chunks(n: int, teams: torch.Tensor | None = None) -> list[slice]:
    """A minibatch of n samples cut into equal chunks of at most `UPDATE_CHUNK`; given each sample's team (n,), in
    an order that keeps teams together, each cut moved on to the next team's start (a chunk holds whole teams)."""
    size = -(-n // -(-n // UPDATE_CHUNK))
    cuts = list(range(size, n, size))
    if teams is not None and cuts:
        starts = torch.cat([torch.tensor([0]), (teams[1:] != teams[:-1]).nonzero().squeeze(1) + 1, torch.tensor([n])])
        cuts = sorted({int(starts[torch.searchsorted(starts, cut)]) for cut in cuts} - {n})
    bounds = [0, *cuts, n]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


class MultiAgentPolicy:
    """Networks, acting copies, optimizers and value normalisers of N AVs (see the module doc)."""

    def __init__(self, n_agents: int, obs_shape: tuple[int, ...], n_actions: int, tc: TrainConfig,
                 device: torch.device | str = "cpu") -> None:
        self.n_agents = n_agents
        self.shared = tc.shared_policy
        self.disseminate_every = tc.disseminate_every
        self.action_mask = tc.action_mask  # whether the env's action masks bound the policy
        self.device = torch.device(device)
        n_nets = 1 if self.shared else n_agents
        self.bf16 = use_bf16(tc.precision, tc.device) and _bf16_sound(obs_shape, n_actions, tc, self.device)
        self.nets = [ActorCritic(obs_shape, n_actions, feature_dim=tc.feature_dim, head_hidden=tc.head_hidden,
                                 bf16=self.bf16, shared_encoder=tc.shared_encoder,
                                 obs_norm=tc.obs_norm, feature_norm=tc.feature_norm,
                                 central_critic=tc.central_critic).to(self.device)
                     for _ in range(n_nets)]
        self.acting = [] if self.shared else [copy.deepcopy(net).requires_grad_(False) for net in self.nets]
        self.optimizers: list[torch.optim.Optimizer]
        self.value_norms: list[ValueNorm | None]
        self.restart_learning(tc)
        self.ema = tc.policy_ema
        self.averaged = [copy.deepcopy(net).requires_grad_(False) for net in self.nets] if self.ema else []
        self.averaged_counts = [0] * len(self.averaged)  # averages taken into each averaged copy so far
        self._memories: dict[int, FrameMemory] | None = None  # in a collecting region: network id -> its memory

    def owner(self, agent: int) -> int:
        """Index into `nets` of AV `agent`'s network."""
        return 0 if self.shared else agent

    def learner(self, update: int) -> int | None:
        """The AV whose network update number `update` (0-based) trains; None when all AVs learn (shared)."""
        return None if self.shared else (update // self.disseminate_every) % self.n_agents

    def trains(self, agent: int, update: int) -> bool:
        """Whether AV `agent`'s samples of update `update` train a network."""
        learner = self.learner(update)
        return learner is None or agent == learner

    def acting_net(self, agent: int, update: int) -> ActorCritic:
        """The network AV `agent` acts with while update `update` is being collected."""
        k = self.owner(agent)
        return self.nets[k] if self.trains(agent, update) else self.acting[k]

    def played_net(self, agent: int, update: int) -> ActorCritic:
        """The network AV `agent` plays greedily while update `update` is being collected: its averaged copy where
        `train.policy_ema` keeps one and it has begun, else the network it acts with."""
        k = self.owner(agent)
        return self.averaged[k] if self.averaged and self.averaged_counts[k] else self.acting_net(agent, update)

    def _average(self, k: int) -> None:
        """Move network k's averaged copy toward its trained weights (module doc)."""
        n, avg, net = self.averaged_counts[k], self.averaged[k], self.nets[k]
        if n == 0:
            avg.load_state_dict(net.state_dict())
        else:
            decay = min(self.ema, (1 + n) / (10 + n))
            get_ema_multi_avg_fn(decay)(list(avg.parameters()), [p.detach() for p in net.parameters()], n)
            for mine, trained in zip(avg.buffers(), net.buffers(), strict=True):
                mine.copy_(trained)
        self.averaged_counts[k] = n + 1

    def ends_block(self, update: int) -> bool:
        """Whether dissemination follows update `update` (per AV: the last update of its learner's block)."""
        return not self.shared and (update + 1) % self.disseminate_every == 0

    def disseminate(self, agent: int) -> None:
        """Copy AV `agent`'s trained network into its acting copy."""
        k = self.owner(agent)
        self.acting[k].load_state_dict(self.nets[k].state_dict())

    def _groups(self, agents: torch.Tensor, update: int,
                played: bool = False) -> list[tuple[ActorCritic, torch.Tensor | slice]]:
        """The networks in play for AVs `agents` (M,) (`played`: those they play greedily), each with the rows it
        acts for (all of them as a slice in the shared network's case: read without a copy of the observations)."""
        pick = self.played_net if played else self.acting_net
        if self.shared:
            return [(pick(0, update), slice(None))]
        nets: dict[int, tuple[ActorCritic, list[int]]] = {}
        for i in range(self.n_agents):
            net = pick(i, update)
            nets.setdefault(id(net), (net, []))[1].append(i)
        out: list[tuple[ActorCritic, torch.Tensor | slice]] = []
        for net, members in nets.values():
            sel = torch.isin(agents, torch.tensor(members))
            if sel.any():
                out.append((net, sel))
        return out

    @contextmanager
    def collecting(self) -> Iterator[None]:
        """A region in which the networks' weights do not change (one update's collection): where they act in
        bfloat16, autocast casts each weight once for the region and reuses it, instead of at every forward (0.8-1.5
        ms of the 2-9 ms of an acting forward of 1-24 samples on one thread, Intel Xeon with AMX); and each network
        keeps the frame features of the observations it acted on (`FrameMemory`, `act`'s `slots`)."""
        self._memories = {}
        try:
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
                yield
        finally:
            self._memories = None

    @torch.no_grad()
    def act(self, obs: torch.Tensor, agents: torch.Tensor, update: int, masks: torch.Tensor | None = None,
            greedy: bool = False, slots: torch.Tensor | None = None, continues: torch.Tensor | None = None,
            teams: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sampled actions, their log-probabilities and values (M,) for observations (M, F, C, H, W) of the AVs
        `agents` (M,) under their action masks (M, A; None: every action allowed), one forward per network in
        play; `greedy`: the most probable actions of the networks they play (`played_net`) instead, in float32 as
        evaluation plays them (validation). In a collecting region, `slots` (M,) (worker and agent) and `continues`
        (M,) (`Batch.continues`) let a network run its first two layers on the newest frame of an observation that
        continues its slot's last one only (`FrameMemory`). `teams` (M,): the observations of one env at one decision
        share a number, for a central critic (`ActorCritic.forward`)."""
        m = len(agents)
        actions, logp, values = torch.zeros(m, dtype=torch.int64), torch.zeros(m), torch.zeros(m)
        for net, rows in self._groups(agents, update, played=greedy):
            team = None if teams is None else teams[rows].to(self.device)
            if slots is not None and self._memories is not None and not greedy:
                memory = self._memories.setdefault(id(net), FrameMemory(net))
                logits, v = memory(obs[rows].to(self.device), slots[rows].to(self.device),
                                   continues[rows].to(self.device), team)
            else:
                logits, v = net(obs[rows].to(self.device), float32=greedy, teams=team)
            # validate_args=False: the checks of its arguments were a tenth of a small batch's acting.
            dist = torch.distributions.Categorical(
                logits=logits if masks is None else masked_logits(logits, self._mask(masks[rows])), validate_args=False)
            a = dist.probs.argmax(-1) if greedy else dist.sample()
            actions[rows], logp[rows], values[rows] = a.cpu(), dist.log_prob(a).cpu(), v.cpu()
        return actions, logp, values

    def restart_learning(self, tc: TrainConfig) -> None:
        """A fresh optimizer and value normaliser for every network, as a run started from these networks
        (`--init-from`) begins with (`train.egoistic_episodes`' switch)."""
        self.optimizers = [OPTIMIZERS[tc.optimizer](net.parameters(), tc) for net in self.nets]
        self.value_norms = [ValueNorm().to(self.device) if tc.value_norm else None for _ in self.nets]

    def _mask(self, masks: torch.Tensor) -> torch.Tensor | None:
        """The masks the policy applies: the env's with `train.action_mask`, else none."""
        return masks if self.action_mask else None

    @torch.no_grad()
    def value(self, obs: torch.Tensor, agents: torch.Tensor, update: int,
              teams: torch.Tensor | None = None) -> torch.Tensor:
        """Values (M,) of observations (M, F, C, H, W) of the AVs `agents`, in the critic's scale (`teams` as in
        `act`)."""
        values = torch.zeros(len(agents))
        for net, rows in self._groups(agents, update):
            values[rows] = net.value(obs[rows].to(self.device),
                                     None if teams is None else teams[rows].to(self.device)).cpu()
        return values

    # -- learning -----------------------------------------------------------------------------------------
    def update(self, batch: Batch, tc: TrainConfig, update: int, progress: float) -> dict[str, float]:
        """Train the networks of update number `update` on `batch` (module doc); returns statistics."""
        lr, ent = schedule(tc.lr, tc.lr_final, progress), schedule(tc.entropy_coef, tc.entropy_final, progress)
        stats: dict[str, float] = {"lr": lr, "entropy_coef": ent, "batch": 0.0}
        learner = self.learner(update)
        for k in range(len(self.nets)):
            if learner is not None and k != self.owner(learner):
                continue
            agents = torch.zeros(batch.valid.shape[2], dtype=torch.bool)
            agents[[i for i in range(self.n_agents) if self.owner(i) == k and self.trains(i, update)]] = True
            sel = batch.valid & agents  # (T, W, N) samples that train network k
            if sel.any():
                stats.update(self._train_net(k, batch, sel, tc, lr, ent))
                if self.averaged:
                    self._average(k)
        return stats

    def _train_net(self, k: int, b: Batch, sel: torch.Tensor, tc: TrainConfig, lr: float,
                   ent: float) -> dict[str, float]:
        net, opt, vn = self.nets[k], self.optimizers[k], self.value_norms[k]
        for group in opt.param_groups:
            group["lr"] = lr
        scale = (lambda v: vn.denormalize(v)) if vn is not None else (lambda v: v)
        # GAE on every (worker, agent) column; samples that do not train are masked out afterwards.
        steps = b.valid.shape[0]
        values = scale(b.values).reshape(steps, -1)  # (T, B)
        following = torch.cat([values[1:], torch.zeros_like(values[:1])])  # V(s_{t+1}) of the same agent
        next_values = torch.where(b.truncated.reshape(steps, -1), scale(b.final_values).reshape(steps, -1),
                                  following)
        adv, ret = gae(b.rewards.reshape(steps, -1), values, next_values, b.terminated.reshape(steps, -1),
                       b.truncated.reshape(steps, -1), tc.gamma, tc.gae_lambda, valid=b.valid.reshape(steps, -1))
        flat = sel.reshape(steps, -1)
        adv, ret = adv[flat], ret[flat]  # (M,)
        if vn is not None:
            vn.update(ret.to(self.device))
            target = vn.normalize(ret.to(self.device))
        else:
            target = ret.to(self.device)
        # The samples' frames are read from the batch chunk by chunk, not gathered here first: a copy of every
        # observation of the update (tens of MB) cost more than the standardisation of its input.
        rows = flat.flatten().nonzero().squeeze(1)
        sources = b.frame_sources(rows)  # (m, F)
        # Samples ordered agent by agent, then in time, within a minibatch: a chunk then holds runs of an agent's
        # consecutive samples, which share all their frames but one. A central critic needs each sample's team (its
        # env's AVs at its decision) in its chunk: minibatches are then drawn team by team, and ordered worker by
        # worker, in time, agent by agent, which keeps teams together and an agent's next sample a team further.
        n_agents = b.valid.shape[2]
        team = rows // n_agents  # t * W + w
        if net.central_critic:
            order_key = (rows % flat.shape[1] // n_agents * steps + rows // flat.shape[1]) * n_agents + rows % n_agents
            team_ids, team_of = team.unique(return_inverse=True)
        else:
            order_key = (rows % flat.shape[1]) * steps + rows // flat.shape[1]
        actions, old_logp, masks = b.actions[sel], b.logp[sel], b.masks[sel]
        adv, old_logp, actions = adv.to(self.device), old_logp.to(self.device), actions.to(self.device)
        m = len(adv)
        if tc.algo == "ppo":
            epochs, minibatches, clip = tc.ppo_epochs, min(tc.ppo_minibatches, m), tc.clip_range
        else:
            epochs, minibatches, clip = 1, 1, None
        totals: dict[str, float] = {}
        n_steps = 0
        for _ in range(epochs):
            if net.central_critic:
                picks = (torch.randperm(len(team_ids)) if minibatches > 1 else torch.arange(len(team_ids))).chunk(
                    min(minibatches, len(team_ids)))
                draws = [torch.isin(team_of, pick).nonzero().squeeze(1) for pick in picks]
            else:
                draws = list((torch.randperm(m) if minibatches > 1 else torch.arange(m)).chunk(minibatches))
            for idx in draws:
                idx = idx[order_key[idx].argsort()]
                n = len(idx)
                dev_idx = idx.to(self.device)
                a = adv[dev_idx]
                a = normalize(a) if tc.normalize_advantage else a  # over the minibatch, not the chunk
                opt.zero_grad(set_to_none=True)
                for at in _chunks(n, team[idx] if net.central_critic else None):
                    part = idx[at]
                    c, pad = len(part), bucket(len(part)) - len(part)
                    # Padded with repeats of its own samples to a size `bucket` rounds to (its frames too), each a
                    # team of its own; only the first c outputs reach the loss, so the gradient is the unpadded one.
                    ids, index = sources[torch.cat([part, part[:pad]])].unique(return_inverse=True)
                    ids = torch.cat([ids, ids[:bucket(len(ids)) - len(ids)]])
                    teams = torch.cat([team[part], -1 - torch.arange(pad)]) if net.central_critic else None
                    logits, v = net.forward_frames(b.frames(ids).to(self.device), index.to(self.device),
                                                   None if teams is None else teams.to(self.device))
                    terms = actor_critic_loss(logits[:c], v[:c], actions[dev_idx[at]], a[at], target[dev_idx[at]],
                                              ent, tc.value_coef, old_logp[dev_idx[at]], clip,
                                              self._mask(masks[part]))
                    (terms.loss * (c / n)).backward()  # the chunks' means weighted into the minibatch's
                    for name, value in (("loss", terms.loss), ("policy_loss", terms.policy),
                                        ("value_loss", terms.value), ("entropy", terms.entropy),
                                        ("approx_kl", terms.approx_kl), ("clip_fraction", terms.clip_fraction)):
                        totals[name] = totals.get(name, 0.0) + float(value.detach()) * c / n
                grad_norm = torch.nn.utils.clip_grad_norm_(net.parameters(), tc.max_grad_norm)
                opt.step()
                n_steps += 1
                totals["grad_norm"] = totals.get("grad_norm", 0.0) + float(grad_norm)
        if net.obs_norm is not None:  # after the update: the next batch is acted on and trained on alike
            net.obs_norm.update(b.frames(rows * sources.shape[1] + sources.shape[1] - 1))
        with torch.no_grad():
            predicted = values[flat].to(self.device)  # as the critic predicted them, before this update's vn stats
            ret_dev = ret.to(self.device)
            explained = 1 - (ret_dev - predicted).var() / ret_dev.var() if m > 1 and ret_dev.var() > 0 else 0.0
        return {**{k: v / n_steps for k, v in totals.items()}, "batch": float(m), "advantage": float(adv.mean()),
                "return": float(ret.mean()), "explained_variance": float(explained)}

    def state_dict(self) -> dict[str, Any]:
        state = {
            "nets": [net.state_dict() for net in self.nets],
            "acting": [net.state_dict() for net in self.acting],
            "optimizers": [opt.state_dict() for opt in self.optimizers],
            "value_norms": [vn.state_dict() if vn is not None else {} for vn in self.value_norms],
        }
        if self.averaged:
            state["averaged"] = [avg.state_dict() for avg in self.averaged]
            state["averaged_counts"] = list(self.averaged_counts)
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for modules, key in ((self.nets, "nets"), (self.acting, "acting"), (self.optimizers, "optimizers")):
            if len(state[key]) != len(modules):
                raise ValueError(f"{key}: expected {len(modules)} entries, got {len(state[key])}")
            for module, sd in zip(modules, state[key], strict=True):
                module.load_state_dict(sd)
        for vn, sd in zip(self.value_norms, state.get("value_norms", []), strict=False):
            if vn is not None and sd:
                vn.load_state_dict(sd)
        # A run that kept no averages (or resumes with train.policy_ema newly set) begins them at its next update.
        if self.averaged and state.get("averaged"):
            for avg, sd in zip(self.averaged, state["averaged"], strict=True):
                avg.load_state_dict(sd)
            self.averaged_counts = [int(n) for n in state["averaged_counts"]]
