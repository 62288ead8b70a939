"""The `train:` section of an experiment config, validated into a frozen dataclass.

Contract: `train_config(cfg)` takes a `cosim.config.Config` (or the raw `train` mapping) and returns a
`TrainConfig`, or raises `cosim.errors.ConfigError` naming the bad key as `train.<key>`. Unknown keys
are errors; missing keys keep the defaults below. This module does not import torch, so rollout
workers and the CLI can read it cheaply.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from cosim.config import Config, parse_section
from cosim.errors import ConfigError

OPTIMIZER_NAMES = ("adam", "rmsprop")  # keys of agents.a2c.OPTIMIZERS


@dataclass(frozen=True)
class TrainConfig:
    """Multi-agent A2C hyper-parameters. Counts are plain integers; a "step" is one decision period."""

    workers: int = 4  # rollout worker processes, one env (one SUMO) each
    episodes: int = 30000  # episodes to train for, in total over the run (resume continues to this)
    rollout_steps: int = 5  # n: decision steps per worker between two updates (n-step returns)
    gamma: float = 0.99  # [-] discount per decision step
    gae_lambda: float = 1.0  # [-] GAE lambda; 1 gives n-step returns, n=1 gives r + gamma V(s') - V(s)
    # Learning rate. On the merge env (reward ~3 per step, time limits bootstrapped, so V ~ 300 at gamma 0.99)
    # rmsprop at 7e-4 and adam at 7e-4 made the critic diverge within ~30 updates; adam at 1e-4 stayed stable.
    lr: float = 1e-4
    optimizer: str = "adam"  # one of OPTIMIZER_NAMES
    optimizer_eps: float = 1e-5  # epsilon of Adam / RMSprop
    entropy_coef: float = 0.01  # weight of the entropy bonus in the loss
    value_coef: float = 0.5  # weight of the critic's squared error in the loss
    max_grad_norm: float = 0.5  # global L2 norm the gradient of one update is clipped to
    normalize_advantage: bool = False  # standardise advantages over the update's batch
    shared_policy: bool = False  # one network for all AVs instead of one per AV (decentralised)
    disseminate_every: int = 10  # K: updates the learner AV trains before its weights are disseminated
    checkpoint_every: int = 100  # updates between two checkpoints (one is also written at the end)
    log_every: int = 1  # updates between two rows of the update log
    seed: int = 0  # seeds python, numpy, torch and the workers' first episodes
    device: str = "cpu"  # torch device of the learner: cpu | cuda | cuda:N
    feature_dim: int = 512  # units of the feature extractor's FC layer (paper: 512)
    head_hidden: int = 256  # units of the actor's and critic's hidden FC layer (paper: 256)
    max_restarts: int = 100  # worker restarts tolerated over a run before it is aborted
    torch_threads: int = 0  # torch intra-op threads of the learner; 0 keeps torch's default


_POSITIVE_INTS = ("workers", "episodes", "rollout_steps", "disseminate_every", "checkpoint_every", "log_every",
                  "feature_dim", "head_hidden")
_NON_NEGATIVE = ("entropy_coef", "value_coef", "max_restarts", "torch_threads")
_UNIT_INTERVAL = ("gamma", "gae_lambda")


def train_config(source: Config | Mapping[str, Any] | None) -> TrainConfig:
    """Validate `cfg.train` (or a raw mapping) into a `TrainConfig`."""
    tc = parse_section(TrainConfig, source.train if isinstance(source, Config) else source, "train")
    _validate(tc)
    return tc


def _validate(tc: TrainConfig) -> None:
    for name in _POSITIVE_INTS:
        if getattr(tc, name) <= 0:
            raise ConfigError(f"train.{name}: must be > 0, got {getattr(tc, name)}")
    for name in _NON_NEGATIVE:
        if getattr(tc, name) < 0:
            raise ConfigError(f"train.{name}: must be >= 0, got {getattr(tc, name)}")
    for name in _UNIT_INTERVAL:
        if not 0.0 <= getattr(tc, name) <= 1.0:
            raise ConfigError(f"train.{name}: must be within [0, 1], got {getattr(tc, name)}")
    for name in ("lr", "optimizer_eps", "max_grad_norm"):
        if getattr(tc, name) <= 0:
            raise ConfigError(f"train.{name}: must be > 0, got {getattr(tc, name)}")
    if tc.optimizer not in OPTIMIZER_NAMES:
        raise ConfigError(f"train.optimizer: expected one of {list(OPTIMIZER_NAMES)}, got {tc.optimizer!r}")
    check_device(tc.device, "train.device")


def check_device(device: str, where: str) -> None:
    """Accept cpu, cuda and cuda:N; availability is checked when the learner starts."""
    kind, _, index = device.partition(":")
    if kind not in ("cpu", "cuda") or (index and (kind != "cuda" or not index.isdigit())):
        raise ConfigError(f"{where}: expected cpu, cuda or cuda:N, got {device!r}")
