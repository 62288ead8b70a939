"""One update's data: every worker plays one whole episode, the learner acting for all of them in batches.

Contract: `collect(pool, policy, batch, seeds, update)` resets workers `0 .. len(seeds) - 1` with the given
episode seeds and steps them until each episode is over, filling `batch` (agents.multiagent.Batch) and
returning a `Collected` with each finished episode's summary, per-agent returns and reward terms. The
workers are split into two halves that take turns: while one half's envs step (in their processes), the
learner acts for the other half, one batched forward over all its live agents. Observations come from the
pool's shared slots, each live agent's action mask with its worker's result (`StepResult.action_mask`, kept in
`Batch.masks` for the update); the values of truncated agents' final observations are computed as they arrive.
A worker that fails is replaced by the pool; its fresh replacement plays the episode again (the same seed and
actions: SUMO is deterministic) up to the command that failed. A failure that comes back there is no bad luck
but the episode's own (SUMO refusing an input, say): training stops at once with `EpisodeError` naming it,
instead of cycling through restarts. Otherwise the episode goes on from there; one whose replay failed
elsewhere is dropped from the batch (`valid` cleared) and counted as lost, not as an episode.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from agents.multiagent import Batch, MultiAgentPolicy
from cosim.errors import EpisodeError
from cosim.workers import StepResult, WorkerPool


@dataclass
class Episode:
    worker: int
    seed: int  # the env's episode seed
    info: dict[str, Any]  # the env's episode summary
    returns: np.ndarray  # (N,) per-agent return
    terms: dict[str, np.ndarray]  # reward term -> (N,) per-agent sum


@dataclass
class Collected:
    episodes: list[Episode] = field(default_factory=list)
    lost: int = 0
    samples: int = 0  # valid agent-samples


def collect(pool: WorkerPool, policy: MultiAgentPolicy, batch: Batch, seeds: list[int], update: int) -> Collected:
    out = Collected()
    n_workers, n_agents = len(seeds), batch.valid.shape[2]
    batch.clear()
    half = (n_workers + 1) // 2
    groups = [list(range(half)), list(range(half, n_workers))]
    step = np.zeros(n_workers, dtype=np.int64)  # next step index of each worker's episode
    returns = np.zeros((n_workers, n_agents))
    terms: list[dict[str, np.ndarray]] = [defaultdict(lambda: np.zeros(n_agents)) for _ in range(n_workers)]
    running = set(range(n_workers))
    for g in groups:
        pool.send_reset(g, [seeds[w] for w in g])
    while running:
        for g in groups:
            ws = [w for w in g if w in running]
            if not ws:
                continue
            results = pool.recv(ws)
            final: list[tuple[int, int, int]] = []  # (t, w, i) of truncated agents
            live = []
            for w, res in zip(ws, results, strict=True):
                t = step[w] - 1  # the step this result answers; -1 for a reset
                if res.lost:
                    res = _replay(pool, batch, w, seeds[w], t, res.error)
                if res.lost:
                    batch.valid[:, w] = False
                    out.lost += 1
                    running.discard(w)
                    continue
                if t >= 0:
                    batch.rewards[t, w] = torch.from_numpy(res.reward)
                    batch.terminated[t, w] = torch.from_numpy(res.terminated)
                    batch.truncated[t, w] = torch.from_numpy(res.truncated)
                    final += [(t, w, int(i)) for i in np.flatnonzero(res.truncated)]
                    returns[w] += res.reward
                    for name, values in res.reward_terms.items():
                        terms[w][name] += values
                if res.episode is not None:
                    out.episodes.append(Episode(w, seeds[w], res.episode, returns[w].copy(), dict(terms[w])))
                    running.discard(w)
                elif t + 1 >= batch.valid.shape[0]:
                    raise RuntimeError(f"an episode ran past {batch.valid.shape[0]} steps, the env's max_steps")
                else:
                    live.append((w, res))
            if final:
                t_, w_, i_ = (torch.tensor(x) for x in zip(*final, strict=True))
                obs = torch.from_numpy(pool.final[w_.numpy(), i_.numpy()])
                batch.final_values[t_, w_, i_] = policy.value(obs, i_, update)
            if live:
                _act(pool, policy, batch, live, step, update)
    out.samples = int(batch.valid.sum())
    return out


def _replay(pool: WorkerPool, batch: Batch, w: int, seed: int, t: int, error: str) -> StepResult:
    """Worker w failed answering decision step `t` (-1: the reset) of episode `seed` with `error`: its replacement
    plays the episode again with the actions already taken; returns the answer to step `t`, or a lost result
    where the replay failed before it. `EpisodeError` where it fails at `t` again (see the module doc)."""
    pool.send_reset([w], [seed])
    (res,) = pool.recv([w])
    at = -1  # the command the replay is at: -1 the reset, k decision step k + 1
    while not res.lost and at < t:
        at += 1
        pool.send_step([w], batch.actions[at, w].numpy()[None])  # what was sent (absent agents' are ignored)
        (res,) = pool.recv([w])
    if res.lost and at == t:
        where = "its reset" if t < 0 else f"decision step {t + 1}"
        raise EpisodeError(f"training episode (seed {seed}) fails the same way on a fresh worker at {where}: "
                              f"{res.error or error}; a fault of this config or net, not bad luck")
    return res


def _act(pool: WorkerPool, policy: MultiAgentPolicy, batch: Batch, live: list[tuple[int, StepResult]],
         step: np.ndarray, update: int) -> None:
    """One batched forward for the live agents of `live` workers (each with its last result: who is alive, their
    action masks); their actions go out at once."""
    ws = [w for w, _ in live]
    rows, agents, times = [], [], []
    for w, res in live:
        t = step[w]
        batch.obs[t, w] = torch.from_numpy(pool.obs[w])  # a copy out of the shared slot
        batch.masks[t, w] = torch.from_numpy(res.action_mask)
        idx = np.flatnonzero(res.alive)
        batch.valid[t, w, idx] = True
        rows += [w] * len(idx)
        agents += idx.tolist()
        times += [t] * len(idx)
    w_, i_, t_ = torch.tensor(rows), torch.tensor(agents), torch.tensor(times)
    actions, logp, values = policy.act(batch.obs[t_, w_, i_], i_, update, batch.masks[t_, w_, i_])
    batch.actions[t_, w_, i_], batch.logp[t_, w_, i_], batch.values[t_, w_, i_] = actions, logp, values
    full = np.ones((len(ws), batch.valid.shape[2]), dtype=np.int64)  # idle for agents that are gone
    pos = {w: k for k, w in enumerate(ws)}
    full[[pos[w] for w in rows], agents] = actions.numpy()
    pool.send_step(ws, full)
    for w in ws:
        step[w] += 1
