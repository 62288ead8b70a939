"""The one way to make the env, for users and for the toolkit's own commands, trainer and runner alike.

Contract: `parallel_env(config, overrides, render_mode)` loads the config (`cosim.config.load_config`) and returns
the episode env (`cosim.environment.merge_env.MergeEnv`) or, with `demand.enabled`, the merge under traffic demand
(`cosim.environment.demand_env.DemandEnv`); `env(...)` the same in PettingZoo's AEC form.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from cosim.config import Config, load_config
from cosim.environment.demand_env import DemandEnv
from cosim.environment.merge_env import MergeEnv


def parallel_env(config: str | Path | Mapping[str, Any] | Config | None = None,
                 overrides: Mapping[str, Any] | list[str] | None = None,
                 render_mode: str | None = None) -> ParallelEnv:
    """The PettingZoo way: `cosim.parallel_env(config="configs/default.yaml", overrides={"reward.phi": 0.785})`;
    without a config, the built-in defaults on the bundled merge net. A config with `demand.enabled` gives the
    merge under traffic demand (`cosim.environment.demand_env.DemandEnv`), else the episode env."""
    cfg = load_config(config, overrides)
    if cfg.demand.enabled:
        return DemandEnv(cfg, render_mode=render_mode)
    return MergeEnv(cfg, render_mode=render_mode)


def env(config: str | Path | Mapping[str, Any] | Config | None = None,
        overrides: Mapping[str, Any] | list[str] | None = None, render_mode: str | None = None) -> AECEnv:
    """The same env in PettingZoo's AEC form (agents act in turn; SUMO advances once all have acted), for
    libraries that expect it: `cosim.env(config=..., overrides=...)`."""
    return parallel_to_aec(parallel_env(config, overrides, render_mode))
