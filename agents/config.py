"""The `train:` section of an experiment config, validated into a frozen dataclass, and its schedules.

Contract: `train_config(cfg)` takes a `cosim.config.Config` (or the raw `train` mapping) and returns a
`TrainConfig`, or raises `cosim.errors.ConfigError` naming the bad key as `train.<key>`. Unknown keys
are errors; missing keys keep the defaults below. This module does not import torch, so rollout
workers and the CLI can read it cheaply.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cosim.config import Config, parse_section
from cosim.errors import ConfigError

OPTIMIZER_NAMES = ("adam", "rmsprop")  # keys of agents.losses.OPTIMIZERS
ALGOS = ("a2c", "ppo")
PRECISIONS = ("auto", "float32", "bfloat16")


@dataclass(frozen=True)
class TrainConfig:
    """Multi-agent actor-critic hyper-parameters. A "step" is one decision period of one env.

    One update: every worker plays one whole episode (seeded by the run's seed, the update and the worker);
    the network(s) then learn from the batch: every live AV's samples with `shared_policy` (the default),
    the learner AV's samples with per-AV networks (the paper's semi-sequential scheme). `a2c` takes one
    gradient step per batch (the paper's algorithm), `ppo` several epochs of clipped updates over it.
    Schedules run from the start value to the `_final` one over the run's progress: the larger of the
    fraction of `episodes` done and, with a `budget_min`, of the budget used.
    """

    algo: str = "a2c"  # one of ALGOS
    shared_policy: bool = True  # one network for all AVs; false: one per AV, trained semi-sequentially
    workers: int = 4  # rollout worker processes, one env (one SUMO) each; more than cores is fine
    episodes: int = 30000  # episodes to train for, in total over the run (resume continues to this)
    budget_min: float = 0.0  # [min] wall-clock training time over the run (resumes included); 0: no limit
    gamma: float = 0.95  # [-] discount per decision step
    gae_lambda: float = 0.95  # [-] GAE lambda; 1 gives Monte-Carlo returns within the episode
    lr: float = 2.5e-4  # learning rate at the start
    lr_final: float | None = None  # ... at the end of the run (linear schedule); None: lr throughout
    optimizer: str = "adam"  # one of OPTIMIZER_NAMES
    optimizer_eps: float = 1e-5  # epsilon of Adam / RMSprop
    entropy_coef: float = 0.01  # weight of the entropy bonus at the start
    entropy_final: float | None = None  # ... at the end of the run (linear schedule); None: constant
    value_coef: float = 0.5  # weight of the critic's squared error in the loss
    max_grad_norm: float = 0.5  # global L2 norm the gradient of one step is clipped to
    normalize_advantage: bool = True  # standardise advantages over each (mini)batch
    value_norm: bool = True  # the critic learns normalised returns (running mean and std of the targets)
    ppo_epochs: int = 4  # passes over each batch (ppo)
    ppo_minibatches: int = 4  # minibatches per pass (ppo)
    clip_range: float = 0.2  # [-] PPO's ratio clip
    disseminate_every: int = 10  # K: updates a learner AV trains before its weights are disseminated (per AV)
    checkpoint_every: int = 50  # updates between two checkpoints (one is also written at the end)
    log_every: int = 1  # updates between two rows of the update log
    log_every_s: float = 30.0  # [s] between two log lines when there is no terminal (no progress bar)
    seed: int = 0  # seeds python, numpy, torch and the episodes
    device: str = "cpu"  # torch device of the learner: cpu | cuda | cuda:N
    # Forward passes of training: float32, bfloat16 (autocast; weights stay float32), or auto: bfloat16 where
    # the hardware has it (CPUs with AMX / AVX512-BF16, GPUs that support it), else float32.
    precision: str = "auto"
    feature_dim: int = 512  # units of the feature extractor's FC layer (paper: 512)
    head_hidden: int = 256  # units of the actor's and critic's hidden FC layer (paper: 256)
    max_restarts: int = 100  # worker restarts tolerated over a run before it is stopped
    step_timeout: float = 60.0  # [s] a worker silent this long is killed and restarted like a crashed one
    torch_threads: int = 0  # torch intra-op threads of the learner; 0 keeps torch's default


_POSITIVE_INTS = ("workers", "episodes", "disseminate_every", "checkpoint_every", "log_every", "feature_dim",
                  "head_hidden", "ppo_epochs", "ppo_minibatches")
_NON_NEGATIVE = ("entropy_coef", "value_coef", "max_restarts", "torch_threads", "budget_min", "log_every_s")
_UNIT_INTERVAL = ("gamma", "gae_lambda", "clip_range")


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
    for name in ("lr", "optimizer_eps", "max_grad_norm", "step_timeout"):
        if getattr(tc, name) <= 0:
            raise ConfigError(f"train.{name}: must be > 0, got {getattr(tc, name)}")
    for name in ("lr_final", "entropy_final"):
        if getattr(tc, name) is not None and getattr(tc, name) < 0:
            raise ConfigError(f"train.{name}: must be >= 0 (or null: no schedule), got {getattr(tc, name)}")
    if tc.precision not in PRECISIONS:
        raise ConfigError(f"train.precision: expected one of {list(PRECISIONS)}, got {tc.precision!r}")
    if tc.algo not in ALGOS:
        raise ConfigError(f"train.algo: expected one of {list(ALGOS)}, got {tc.algo!r}")
    if tc.optimizer not in OPTIMIZER_NAMES:
        raise ConfigError(f"train.optimizer: expected one of {list(OPTIMIZER_NAMES)}, got {tc.optimizer!r}")
    check_device(tc.device, "train.device")


def use_bf16(precision: str, device: str) -> bool:
    """Whether training runs its forward passes in bfloat16 (see `TrainConfig.precision`)."""
    if precision != "auto":
        return precision == "bfloat16"
    if device.startswith("cuda"):
        import torch

        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    try:  # the CPU flags of Linux; elsewhere float32
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "amx_bf16" in flags or "avx512_bf16" in flags


def schedule(start: float, final: float | None, progress: float) -> float:
    """Linear from `start` at progress 0 to `final` at 1 (constant `start` without a final value)."""
    if final is None:
        return start
    return start + (final - start) * min(max(progress, 0.0), 1.0)


def check_device(device: str, where: str) -> None:
    """Accept cpu, cuda and cuda:N; availability is checked when the learner starts."""
    kind, _, index = device.partition(":")
    if kind not in ("cpu", "cuda") or (index and (kind != "cuda" or not index.isdigit())):
        raise ConfigError(f"{where}: expected cpu, cuda or cuda:N, got {device!r}")
