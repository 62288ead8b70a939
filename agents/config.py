"""The `train:` section of an experiment config and its schedules.

Contract: `TrainConfig` is the typed `train:` section, defined with the other sections in `cosim.config`
(`Config.train`, validated when the config is loaded) and re-exported here with its choices (`ALGOS`,
`OPTIMIZER_NAMES`, `PRECISIONS`). `train_config(source)` returns `source.train` for a `Config`, or validates a
raw `train` mapping (None: the defaults) into a `TrainConfig`, raising `cosim.errors.ConfigError` that names the
bad key as `train.<key>`. This module does not import torch (`use_bf16` does on a CUDA device only), so rollout
workers and the CLI can read it cheaply.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cosim.config import ALGOS, OPTIMIZER_NAMES, PRECISIONS, Config, TrainConfig, check_device, parse_section

__all__ = ["ALGOS", "OPTIMIZER_NAMES", "PRECISIONS", "TrainConfig", "check_device", "schedule", "train_config",
           "use_bf16"]


def train_config(source: Config | TrainConfig | Mapping[str, Any] | None) -> TrainConfig:
    """The `train` section of a `Config`, or a raw mapping validated into a `TrainConfig`."""
    if isinstance(source, Config):
        return source.train
    return parse_section(TrainConfig, source, "train")


def use_bf16(precision: str, device: str) -> bool:
    """Whether training runs its forward passes in bfloat16 (see `TrainConfig.precision`): with `auto`, on a CPU
    whose flags (those `lscpu` lists, from /proc/cpuinfo) include `amx_bf16` or `avx512_bf16`, and on a GPU that
    supports it. bfloat16 kernels are not reproducible bit for bit run to run; float32 is, on the same machine
    and thread count (README)."""
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
