"""SUMO co-simulation of an on-ramp merge for multi-agent RL: `cosim.parallel_env(config, overrides)`."""

from typing import Any

__all__ = ["parallel_env"]


def __getattr__(name: str) -> Any:
    # Lazy, so `import cosim.config` stays light (no gymnasium / pettingzoo import).
    if name == "parallel_env":
        from cosim.env import parallel_env

        return parallel_env
    raise AttributeError(name)
