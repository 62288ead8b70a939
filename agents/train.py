"""Multi-agent A2C training loop (paper Section 4) over W rollout workers; the `cosim train` entry point.

Contract: `train(cfg, out_dir, ...)` trains the AVs of `cfg` until `episodes` episodes have finished in
total, writing into `out_dir`: `config.yaml` (the resolved config), `checkpoint.pt` (every
`train.checkpoint_every` updates, at the end, and on Ctrl-C), `updates.csv`, `episodes.csv` and TensorBoard
files under `tb/`. `resume=True` continues the run in `out_dir` from its checkpoint (same parameters,
optimizer state, RNG states and counters). It returns a `TrainResult`. `add_arguments` / `run`
are the argparse pair behind `cosim train`.

One update: every worker steps its env `rollout_steps` times with all AVs acting (the learner AV with
its live network, the others with frozen copies, see agents.multiagent); then the learner's network
trains on the learner's valid samples with GAE advantages. Samples of absent agents and the rollout's
steps of an episode lost to a worker failure are masked out, never padded into the loss.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import logging
import random
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm import tqdm

from agents.a2c import a2c_loss, gae
from agents.checkpoint import (
    CHECKPOINT_NAME,
    CheckpointError,
    check_spec,
    read_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from agents.config import TrainConfig, check_device, train_config
from agents.logs import RunLogger
from agents.multiagent import MultiAgentPolicy
from agents.rollout import EnvFactory, WorkerPool
from cosim.cli import add_config_arguments
from cosim.config import Config, load_config
from cosim.errors import ConfigError
from cosim.files import atomic_write_text

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainResult:
    out_dir: Path
    checkpoint: Path
    episodes: int  # finished episodes counted as data, over the whole run
    updates: int
    samples: int  # valid agent-samples collected, over the whole run
    restarts: int  # rollout worker restarts, over the whole run
    lost_episodes: int  # episodes dropped because their worker failed
    interrupted: bool  # stopped by Ctrl-C (a checkpoint was written)
    recent_return: float  # mean per-agent episode return over the last 100 episodes
    wall_s: float  # [s] of this call
    rollout_s: float  # [s] of this call spent collecting (env steps + acting)
    update_s: float  # [s] of this call spent in gradient updates
    new_samples: int  # agent-samples collected by this call


@dataclass
class Rollout:
    """One update's storage, allocated once; time first. Row T of obs/alive is the bootstrap state."""

    obs: torch.Tensor  # (T+1, W, N, F, C, H, W) env dtype
    alive: torch.Tensor  # (T+1, W, N) bool: the agent acts at that step
    actions: torch.Tensor  # (T, W, N) int64
    rewards: torch.Tensor  # (T, W, N) float32
    terminated: torch.Tensor  # (T, W, N) bool
    truncated: torch.Tensor  # (T, W, N) bool
    valid: torch.Tensor  # (T, W, N) bool: alive and its episode not lost
    final_obs: dict[tuple[int, int, int], torch.Tensor]  # (t, w, i) -> (F, C, H, W) of truncated samples

    @classmethod
    def allocate(cls, steps: int, workers: int, agents: int, obs_shape: tuple[int, ...], dtype: torch.dtype
                 ) -> Rollout:
        twn = (steps, workers, agents)
        return cls(torch.zeros((steps + 1, workers, agents, *obs_shape), dtype=dtype),
                   torch.zeros((steps + 1, workers, agents), dtype=torch.bool),
                   torch.zeros(twn, dtype=torch.int64), torch.zeros(twn), torch.zeros(twn, dtype=torch.bool),
                   torch.zeros(twn, dtype=torch.bool), torch.zeros(twn, dtype=torch.bool), {})


def learner_update(policy: MultiAgentPolicy, learner: int, ro: Rollout, tc: TrainConfig) -> dict[str, float]:
    """One gradient step of AV `learner`'s network on that AV's valid samples; returns loss statistics."""
    k = policy.owner(learner)
    net, opt, dev = policy.nets[k], policy.optimizers[k], policy.device
    sel = ro.valid[:, :, learner]  # (T, W) samples that train this update
    if not sel.any():
        return {"batch": 0.0}
    obs = ro.obs[:, :, learner]  # (T+1, W, F, C, H, W)
    logits, values = net(obs[:-1][sel].to(dev))  # (M, A), (M,)
    with torch.no_grad():  # V(s_{t+1}) of each sample: next row, bootstrap row T, or a truncated final obs
        all_values = torch.zeros(sel.shape[0] + 1, sel.shape[1], device=dev)  # (T+1, W)
        all_values[:-1][sel] = values.detach()
        boot = ro.alive[-1, :, learner]  # (W,)
        if boot.any():
            all_values[-1][boot.to(dev)] = net.value(obs[-1][boot].to(dev))
        next_values = all_values[1:].clone()  # (T, W)
        final = [(t, w) for (t, w, i) in ro.final_obs if i == learner]
        if final:
            fin = torch.stack([ro.final_obs[(t, w, learner)] for t, w in final]).to(dev)
            next_values[tuple(torch.tensor(final, device=dev).T)] = net.value(fin)
    adv, ret = gae(ro.rewards[:, :, learner].to(dev), all_values[:-1], next_values,
                   ro.terminated[:, :, learner].to(dev), ro.truncated[:, :, learner].to(dev),
                   tc.gamma, tc.gae_lambda, valid=sel.to(dev))  # (T, W) each
    sel = sel.to(dev)
    terms = a2c_loss(logits, values, ro.actions[:, :, learner].to(dev)[sel], adv[sel], ret[sel],
                     tc.entropy_coef, tc.value_coef, tc.normalize_advantage)
    opt.zero_grad(set_to_none=True)
    terms.loss.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(net.parameters(), tc.max_grad_norm)
    opt.step()
    return {"batch": float(sel.sum()), "loss": terms.loss.item(), "policy_loss": terms.policy.item(),
            "value_loss": terms.value.item(), "entropy": terms.entropy.item(), "grad_norm": grad_norm.item(),
            "advantage": adv[sel].mean().item(), "value": values.mean().item()}


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _default_env_factory(cfg: Config) -> EnvFactory:
    from cosim.env import parallel_env  # the meeting point of agents/ and cosim/, through PettingZoo

    return functools.partial(parallel_env, cfg.to_dict())


def train(cfg: Config, out_dir: Path, *, workers: int | None = None, episodes: int | None = None,
          resume: bool = False, device: str | None = None, env_factory: EnvFactory | None = None,
          progress: bool | None = None) -> TrainResult:
    """Train (or, with `resume`, continue training) the AVs of `cfg` into `out_dir` (see module doc)."""
    tc = train_config(cfg)
    tc = dataclasses.replace(tc, workers=workers or tc.workers, episodes=episodes or tc.episodes,
                             device=device or tc.device)
    check_device(tc.device, "--device")
    if tc.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"--device {tc.device}: CUDA is not available on this machine")
    if tc.torch_threads:
        torch.set_num_threads(tc.torch_threads)
    out_dir = Path(out_dir)
    ckpt_path = out_dir / CHECKPOINT_NAME
    if not resume and ckpt_path.exists():
        raise CheckpointError(f"checkpoint {ckpt_path}: exists already; pass --resume to continue that run or "
                              "choose another --out")
    payload = read_checkpoint(ckpt_path) if resume else None
    counters = {"episodes": 0, "updates": 0, "samples": 0, "restarts": 0, "lost_episodes": 0}
    if payload is not None:
        counters.update({k: int(v) for k, v in payload["counters"].items() if k in counters})
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "config.yaml", yaml.safe_dump({**cfg.to_dict(), "train": dataclasses.asdict(tc)},
                                                              sort_keys=False))
    _seed_everything(tc.seed)
    pool = WorkerPool(env_factory or _default_env_factory(cfg), tc.workers, seed=tc.seed + counters["updates"],
                      max_restarts=tc.max_restarts)
    spec = pool.spec
    n_agents, obs_shape = len(spec.agents), spec.obs_shape
    spec_dict = {"agents": list(spec.agents), "obs_shape": list(obs_shape), "obs_dtype": spec.obs_dtype,
                 "n_actions": spec.n_actions, "shared_policy": tc.shared_policy, "feature_dim": tc.feature_dim,
                 "head_hidden": tc.head_hidden}
    try:
        policy = MultiAgentPolicy(n_agents, obs_shape, spec.n_actions, tc, tc.device)
        if payload is not None:
            check_spec(payload, spec_dict, ckpt_path)
            policy.load_state_dict(payload["policy"])
            set_rng_state(payload["rng"])
            log.info("resumed %s at update %d, episode %d", ckpt_path, counters["updates"], counters["episodes"])
    except BaseException:
        pool.close()
        raise
    logger = RunLogger(out_dir)

    def checkpoint() -> None:
        save_checkpoint(ckpt_path, {"spec": spec_dict, "policy": policy.state_dict(), "counters": dict(counters),
                                    "rng": rng_state(), "train": dataclasses.asdict(tc), "config": cfg.to_dict(),
                                    "phis": list(cfg.phis())})

    # Storage, allocated once. T decision steps x W workers x N agents.
    T, W, N = tc.rollout_steps, tc.workers, n_agents
    ro = Rollout.allocate(T, W, N, obs_shape, getattr(torch, spec.obs_dtype))
    ep_return = np.zeros((W, N))  # running per-agent return of each worker's episode
    ep_terms: list[dict[str, np.ndarray]] = [defaultdict(lambda: np.zeros(N)) for _ in range(W)]
    timing = {"rollout": 0.0, "update": 0.0}
    start, start_samples, interrupted = time.perf_counter(), counters["samples"], False
    restarts_before = counters["restarts"]
    bar = tqdm(total=tc.episodes, initial=min(counters["episodes"], tc.episodes), unit="ep", dynamic_ncols=True,
               disable=(not progress) if progress is not None else None, desc="train")
    try:
        obs, alive = pool.reset()  # (W, N, F, C, H, W), (W, N)
        while counters["episodes"] < tc.episodes:
            update = counters["updates"]
            learner = policy.learner(update)
            # --- rollout: T synchronous steps of every worker ---
            t0 = time.perf_counter()
            ro.final_obs.clear()
            ep_start = [0] * W  # the step where each worker's running episode entered this rollout
            for t in range(T):
                ro.obs[t] = torch.from_numpy(obs)
                ro.alive[t] = torch.from_numpy(alive)
                ro.actions[t] = policy.act(ro.obs[t], ro.alive[t], update)
                ro.valid[t] = ro.alive[t]
                results = pool.step(ro.actions[t].numpy())
                for w, res in enumerate(results):
                    obs[w], alive[w] = res.next_obs, res.alive
                    if res.lost:  # the worker failed: drop its running episode from the data
                        ro.valid[ep_start[w]: t + 1, w] = False
                        counters["lost_episodes"] += 1
                        ep_return[w] = 0.0
                        ep_terms[w].clear()
                        ep_start[w] = t + 1
                        continue
                    ro.rewards[t, w] = torch.from_numpy(res.reward)
                    ro.terminated[t, w] = torch.from_numpy(res.terminated)
                    ro.truncated[t, w] = torch.from_numpy(res.truncated)
                    for i, final in res.final_obs.items():
                        ro.final_obs[(t, w, i)] = torch.from_numpy(final)
                    ep_return[w] += res.reward
                    for name, values in res.reward_terms.items():
                        ep_terms[w][name] += values
                    if res.episode is not None:
                        counters["episodes"] += 1
                        _log_episode(logger, counters["episodes"], spec.agents, ep_return[w], ep_terms[w],
                                     res.episode)
                        ep_return[w] = 0.0
                        ep_terms[w].clear()
                        ep_start[w] = t + 1
                        bar.update(1)
            ro.obs[T] = torch.from_numpy(obs)
            ro.alive[T] = torch.from_numpy(alive)
            counters["samples"] += int(ro.valid.sum())
            # --- update: the learner AV's network; dissemination at the end of its block ---
            t1 = time.perf_counter()
            stats = learner_update(policy, learner, ro, tc)
            if policy.ends_block(update):
                policy.disseminate(learner)
            counters["updates"] += 1
            t2 = time.perf_counter()
            timing["rollout"] += t1 - t0
            timing["update"] += t2 - t1
            counters["restarts"] = restarts_before + pool.restarts
            sps = (counters["samples"] - start_samples) / max(t2 - start, 1e-9)
            if counters["updates"] % tc.log_every == 0:
                logger.update(counters["updates"], {"update": counters["updates"], "episodes": counters["episodes"],
                                                    "samples": counters["samples"], "learner": learner,
                                                    "samples_per_s": sps, "restarts": counters["restarts"],
                                                    **stats})
            bar.set_postfix(sps=f"{sps:.0f}", crash=f"{logger.rate('crashed'):.2f}",
                            merge=f"{logger.rate('merged'):.2f}", ret=f"{logger.rate('return_mean'):.2f}",
                            refresh=False)
            if counters["updates"] % tc.checkpoint_every == 0:
                checkpoint()
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted at update %d; writing a checkpoint to %s", counters["updates"], ckpt_path)
    finally:
        bar.close()
        pool.close()
        logger.close()
    counters["restarts"] = restarts_before + pool.restarts
    checkpoint()
    wall = time.perf_counter() - start
    return TrainResult(out_dir, ckpt_path, counters["episodes"], counters["updates"], counters["samples"],
                       counters["restarts"], counters["lost_episodes"], interrupted, logger.rate("return_mean"),
                       wall, timing["rollout"], timing["update"], counters["samples"] - start_samples)


def _log_episode(logger: RunLogger, n: int, agents: tuple[str, ...], returns: np.ndarray,
                 terms: dict[str, np.ndarray], info: dict[str, Any]) -> None:
    row: dict[str, Any] = {"episode": n, "return_mean": float(returns.mean())}
    row.update({f"return_{a}": float(r) for a, r in zip(agents, returns, strict=True)})
    for key in ("crashed", "merged", "mean_distance", "merger_distance", "length"):
        row[key] = float(info.get(key, float("nan")))
    row.update({f"term_{name}": float(values.mean()) for name, values in sorted(terms.items())})
    logger.episode(n, row)


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The `cosim train` options."""
    add_config_arguments(parser)
    parser.add_argument("--out", type=Path, default=None, help="run folder (default: runs/<config stem>)")
    parser.add_argument("--workers", type=int, default=None, help="rollout worker processes (default: train.workers)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes in total (default: train.episodes)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: train.device)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Run `cosim train` from parsed arguments; returns the exit code (130 when interrupted)."""
    for name in ("workers", "episodes"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            raise ConfigError(f"--{name}: must be > 0, got {value}")
    cfg = load_config(args.config, overrides=args.overrides)
    out = args.out or Path("runs") / Path(args.config).stem
    result = train(cfg, out, workers=args.workers, episodes=args.episodes, resume=args.resume, device=args.device)
    log.info("trained %d episodes (%d updates, %d agent-samples) into %s", result.episodes, result.updates,
             result.samples, result.out_dir)
    return 130 if result.interrupted else 0

