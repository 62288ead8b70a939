"""How much the network's features and outputs vary from scene to scene: freshly initialised, with and without the
input standardised (`train.obs_norm`), and for trained policies.

Plays `--episodes` episodes of the config with every AV `idle` (78% of them end in a crash on the default scenario,
so the scenes before a crash are many), keeps every AV's observation, and reports per network:
- `dead`: the share of the encoder's FC units that are 0 (ReLU off) in every one of those scenes;
- `spread / size`: the features' standard deviation across scenes over their mean absolute value (averaged over the
  units): near 0, the encoder gives every scene about the same features, and the policy cannot tell them apart;
- `logit spread`: each action's logit's standard deviation across scenes, and the shares of the scenes in which each
  action has the largest logit (`greedy shares`; without the env's action masks).
A fresh network is built for each of `--init-seeds`; with obs_norm its statistics are those of the scenes themselves.
A trained policy (`--policy`, a run folder or policy file) is probed as it was saved.

Usage: python scripts/probe_features.py [--config configs/default.yaml] [--episodes 15] [--init-seeds 0 1 2]
       [--policy runs/learner/NAME/best.pt ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

# Run from a checkout without installing: the repository root holds the `agents` and `cosim` packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cosim  # noqa: E402
from agents.checkpoint import load_policy  # noqa: E402
from agents.model import ActorCritic, prepare  # noqa: E402
from cosim.config import load_config  # noqa: E402
from cosim.config.types import EVAL_SEED_START  # noqa: E402
from cosim.environment.control import N_ACTIONS, Action  # noqa: E402


def scenes(config: str, episodes: int) -> torch.Tensor:
    """Every AV's observation at every decision of `episodes` all-idle episodes, (S, F, C, H, W)."""
    env = cosim.parallel_env(config)
    seen = []
    try:
        for ep in range(episodes):
            # Between the evaluation seeds (from EVAL_SEED_START on, a few thousand) and the validation ones: no
            # training, validation or evaluation episode.
            obs, _ = env.reset(seed=EVAL_SEED_START + 5_000_000 + ep)
            while env.agents:
                seen += [obs[a] for a in env.agents]
                obs, *_ = env.step({a: int(Action.IDLE) for a in env.agents})
    finally:
        env.close()
    return torch.from_numpy(np.stack(seen))


def probe(net: ActorCritic, x: torch.Tensor) -> str:
    """The module doc's measures of `net` on scenes `x`, as one line."""
    with torch.no_grad():
        net = net.eval()
        features = net.features.encode(prepare(x, net.obs_norm)).float()
        logits = net.actor(features)  # the forward's logits, without encoding the scenes a second time
    greedy = np.bincount(logits.argmax(-1).numpy(), minlength=logits.shape[1]) / len(x)
    dead = float((features.max(0).values <= 0).float().mean())
    spread = float(features.std(0).mean() / features.abs().mean())
    return (f"dead {dead:.1%}, spread / size {spread:.2f}, logit spread "
            f"{' '.join(f'{v:.3f}' for v in logits.std(0).tolist())}, greedy shares "
            f"{' '.join(f'{v:.2f}' for v in greedy)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/default.yaml")
    ap.add_argument("--episodes", type=int, default=15)
    ap.add_argument("--init-seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--policy", nargs="*", default=[], help="trained policies: run folders, policy.pt or best.pt")
    args = ap.parse_args()
    torch.set_num_threads(1)
    x = scenes(args.config, args.episodes)
    nonzero = (x > 0).float()
    channels = load_config(args.config).observation.channels
    print(f"{len(x)} scenes of {args.episodes} all-idle episodes ({args.config}); non-zero input values: "
          f"{float(nonzero.mean()):.1%}, of which per channel: " + ", ".join(
              f"{name} {float(nonzero[:, :, c].sum() / nonzero.sum()):.0%}" for c, name in enumerate(channels)))
    for obs_norm in (False, True):
        for seed in args.init_seeds:
            torch.manual_seed(seed)
            net = ActorCritic(tuple(x.shape[1:]), N_ACTIONS, obs_norm=obs_norm)
            if net.obs_norm is not None:
                net.obs_norm.update(x[:, -1])
            print(f"fresh, init seed {seed}, obs_norm {str(obs_norm).lower()}: {probe(net, x)}")
    for path in args.policy:
        policies, meta = load_policy(path)
        print(f"{path} ({meta['counters'].get('episodes')} episodes, obs_norm "
              f"{str(meta['spec'].get('obs_norm', False)).lower()}): {probe(next(iter(policies.values())), x)}")


if __name__ == "__main__":
    main()
