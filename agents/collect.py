"""One update's data: every worker plays one whole episode, the learner acting for all of them in batches.

Contract: `collect(pool, policy, batch, seeds, update, egoistic=False)` resets workers `0 .. len(seeds) - 1` with
the given episode seeds and steps them until each episode is over, filling `batch` (agents.multiagent.Batch) and
returning a `Collected` with each finished episode's summary, per-agent returns and reward terms. The batch's
rewards are the env's, or with `egoistic` each agent's own utility (`training_reward`); the returns reported are
the env's either way. The
workers are split into two halves that take turns: while one half's envs step (in their processes), the
learner acts for the other half, one batched forward over all its live agents. Observations come from the
pool's shared slots, each live agent's action mask with its worker's result (`StepResult.action_mask`, kept in
`Batch.masks` for the update); the values of truncated agents' final observations are computed in one forward
when the collection ends (`Bootstraps`).
A worker that fails is replaced by the pool; its fresh replacement plays the episode again (the same seed and
actions: SUMO is deterministic) up to the command that failed. A failure that comes back there is no bad luck
but the episode's own (SUMO refusing an input, say): training stops at once with `EpisodeError` naming it,
instead of cycling through restarts. Otherwise the episode goes on from there; one whose replay failed
elsewhere is dropped from the batch (`valid` cleared) and counted as lost, not as an episode.

Under traffic demand (`Segments`) a worker's run lasts minutes, longer than an update should wait: each update is a
fixed-length segment of every worker's continuing simulation (`Segments.collect(policy, batch, update, seed_of)`:
`batch`'s T decision steps on each worker, agents indexed by observation slot), as CleanRL's and SB3's rollouts of
`num_steps` / `n_steps` are. An agent that goes on past the segment is truncated at its last step and bootstrapped
from the value of the observation it goes on from; a run that reaches its horizon inside a segment is counted as an
episode and the worker starts its next run at once (seed `seed_of(worker)`). A worker that fails loses its run:
its samples of the segment are dropped (`valid` cleared), it is counted lost, and its replacement starts a new run.
`Segments.drop()` forgets the runs in progress (after validation played other episodes on the workers, at a resume):
the next segment starts new ones. With `train.segments` episodes are collected the same way (`Segments(pool,
demand=False)`): a worker whose episode ends starts its next one in the same segment, so that no worker waits for
the longest episode of an update, and every update holds the same number of decisions; an episode's returns are
then per agent, as `collect`'s, where a demand run's are per AV released.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
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


def training_reward(res: StepResult, egoistic: bool) -> np.ndarray:
    """The rewards (N,) a step trains on: the env's, or with `egoistic` each agent's own utility, the sum of its
    weighted reward terms (the SVO reward at phi = 0; `train.egoistic_episodes`)."""
    return sum(res.reward_terms.values(), np.zeros_like(res.reward)) if egoistic else res.reward


def collect(pool: WorkerPool, policy: MultiAgentPolicy, batch: Batch, seeds: list[int], update: int,
            egoistic: bool = False) -> Collected:
    out = Collected()
    n_workers, n_agents = len(seeds), batch.valid.shape[2]
    batch.clear()
    half = (n_workers + 1) // 2
    groups = [list(range(half)), list(range(half, n_workers))]
    step = np.zeros(n_workers, dtype=np.int64)  # next step index of each worker's episode
    returns = np.zeros((n_workers, n_agents))
    terms: list[dict[str, np.ndarray]] = [defaultdict(lambda: np.zeros(n_agents)) for _ in range(n_workers)]
    running = set(range(n_workers))
    cut = Bootstraps()
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
                    batch.rewards[t, w] = torch.from_numpy(training_reward(res, egoistic))
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
            cut.add(pool.final, final)
            if live:
                _act(pool, policy, batch, live, step, update)
    cut.value(policy, batch, update)
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
    n_workers, n_agents = batch.valid.shape[1:]
    flat = (t_ * n_workers + w_) * n_agents + i_
    # A worker's live agents act on one decision of its env: its team (a central critic's).
    actions, logp, values = policy.act(batch.observations(flat), i_, update, batch.masks[t_, w_, i_],
                                       slots=w_ * n_agents + i_, continues=batch.continues(flat), teams=w_)
    batch.actions[t_, w_, i_], batch.logp[t_, w_, i_], batch.values[t_, w_, i_] = actions, logp, values
    full = np.ones((len(ws), batch.valid.shape[2]), dtype=np.int64)  # idle for agents that are gone
    pos = {w: k for k, w in enumerate(ws)}
    full[[pos[w] for w in rows], agents] = actions.numpy()
    pool.send_step(ws, full)
    for w in ws:
        step[w] += 1


class Segments:
    """The continuing runs (under demand) or episodes of each worker, and their segments (module doc)."""

    def __init__(self, pool: WorkerPool, demand: bool = True) -> None:
        self.pool, self.demand = pool, demand
        self.runs: dict[int, tuple[int, StepResult]] = {}  # worker -> (its run's seed, its answer to act on)
        # worker -> its run's rewards and reward terms so far, per agent (per slot under demand)
        self.sums: dict[int, tuple[np.ndarray, dict[str, np.ndarray]]] = {}

    def drop(self) -> None:
        self.runs.clear()
        self.sums.clear()

    def collect(self, policy: MultiAgentPolicy, batch: Batch, update: int, seed_of: Callable[[int], int],
                egoistic: bool = False) -> Collected:
        out = Collected()
        pool, (steps, n_workers, n_agents) = self.pool, batch.valid.shape
        batch.clear()
        half = (n_workers + 1) // 2
        groups = [list(range(half)), list(range(half, n_workers))]
        step = np.zeros(n_workers, dtype=np.int64)  # next decision of each worker's segment
        seeds = {w: run[0] for w, run in self.runs.items()}
        ready = {w: run[1] for w, run in self.runs.items()}  # workers that act first, on their last answer
        resetting: set[int] = set()  # workers whose next answer is a reset's
        self.runs = {}

        def start(ws: list[int]) -> None:
            for w in ws:
                seeds[w] = seed_of(w)
                self.sums[w] = (np.zeros(n_agents), defaultdict(lambda: np.zeros(n_agents)))
            resetting.update(ws)
            pool.send_reset(ws, [seeds[w] for w in ws])

        start([w for w in range(n_workers) if w not in ready])
        running = set(range(n_workers))
        cut = Bootstraps()
        while running:
            for g in groups:
                waiting = [w for w in g if w in running and w not in ready]
                answers = dict(zip(waiting, pool.recv(waiting), strict=True)) if waiting else {}
                at_horizon: list[tuple[int, int, int]] = []  # (t, w, i): truncated at the run's end
                going_on: list[tuple[int, int, int]] = []  # (t, w, i): alive past the segment's end
                restart, live = [], []
                for w in [w for w in g if w in running]:
                    stepped = w in answers and w not in resetting  # an answer to a decision of this segment
                    res = answers[w] if w in answers else ready.pop(w)
                    resetting.discard(w)
                    if res.lost:
                        batch.valid[:, w] = False  # its trajectories in this segment lost their ends
                        out.lost += 1
                        restart.append(w)
                        continue
                    t = step[w] - 1
                    if stepped:
                        batch.rewards[t, w] = torch.from_numpy(training_reward(res, egoistic))
                        batch.terminated[t, w] = torch.from_numpy(res.terminated)
                        batch.truncated[t, w] = torch.from_numpy(res.truncated)
                        at_horizon += [(t, w, int(i)) for i in np.flatnonzero(res.truncated)]
                        reward, terms = self.sums[w]
                        reward += res.reward
                        for name, values in res.reward_terms.items():
                            terms[name] += values
                    if res.episode is not None:  # the run (or episode) is over: the next one starts at once
                        reward, terms = self.sums.pop(w)
                        if self.demand:  # slots are held by many AVs in turn: the run's sum per AV released
                            reward, terms = (np.array([per_av_released(float(reward.sum()), res.episode)]),
                                             {k: np.array([per_av_released(float(v.sum()), res.episode)])
                                              for k, v in terms.items()})
                        out.episodes.append(Episode(w, seeds[w], res.episode, reward, dict(terms)))
                        restart.append(w)
                    elif step[w] >= steps:  # the segment is complete; the run goes on in the next one
                        if stepped:
                            on = res.alive & batch.valid[t, w].numpy() & ~res.terminated
                            going_on += [(t, w, int(i)) for i in np.flatnonzero(on)]
                        self.runs[w] = (seeds[w], res)
                        running.discard(w)
                    else:
                        live.append((w, res))
                cut.add(pool.final, at_horizon)
                cut.add(pool.obs, going_on)
                if restart:
                    start(restart)
                if live:
                    _act(pool, policy, batch, live, step, update)
        cut.value(policy, batch, update)
        out.samples = int(batch.valid.sum())
        return out


def per_av_released(total: float, run: dict[str, Any]) -> float:
    """A demand run's summed reward (or term) per AV it released, as an episode's return is per AV."""
    return total / max(int(run["avs_released"]), 1)


class Bootstraps:
    """Samples (t, w, i) whose trajectory is cut after decision t (truncated), with a copy of the observation each goes
    on from, to bootstrap from its value: all valued in one forward when the collection ends (`value`)."""

    def __init__(self) -> None:
        self.cut: list[tuple[int, int, int]] = []
        self.obs: list[np.ndarray] = []

    def add(self, source: Any, cut: list[tuple[int, int, int]]) -> None:
        """Samples `cut`, going on from `source[w, i]` (the pool's final observations, or its current ones), copied
        now: the pool writes the next ones into the same slots."""
        if cut:
            self.cut += cut
            _, w_, i_ = (np.array(x) for x in zip(*cut, strict=True))
            self.obs.append(source[w_, i_])

    def value(self, policy: MultiAgentPolicy, batch: Batch, update: int) -> None:
        # One forward, not one per round for the few agents cut in it: those were a tenth of the learner's time while
        # collecting (py-spy, A2C, 2 cores of an AMD EPYC), the network's per-call cost paid for a handful of samples.
        if not self.cut:
            return
        t_, w_, i_ = (torch.tensor(x) for x in zip(*self.cut, strict=True))
        batch.truncated[t_, w_, i_] = True
        batch.final_values[t_, w_, i_] = policy.value(torch.from_numpy(np.concatenate(self.obs)), i_, update,
                                                      teams=t_ * batch.valid.shape[1] + w_)
