"""SUMO co-simulation of an on-ramp merge for multi-agent RL: `cosim.parallel_env(config, overrides)`, or the
AEC form `cosim.env(config, overrides)`."""

from typing import Any

__all__ = ["env", "parallel_env"]


def __getattr__(name: str) -> Any:
    # Lazy, so `import cosim.config` stays light (no gymnasium / pettingzoo import).
    if name in __all__:
        import cosim.environment.merge_env

        return getattr(cosim.environment.merge_env, name)
    raise AttributeError(name)
