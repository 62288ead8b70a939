"""SUMO co-simulation of an on-ramp merge for multi-agent RL: `cosim.parallel_env(config, overrides)`, or the
AEC form `cosim.env(config, overrides)`.

Module map (data flows down the list): `config` (the typed experiment config) -> `sumo` (the libsumo session
and its snapshots, the net and its geometry, an episode's routes, SUMO's output files) -> `environment`
(control, VelocityMap and renderer, reward terms, episode endings, collision attribution, the episode tracker,
hand-written policies, the PettingZoo envs on one template, `factory` making either) -> `workers` (the pool of
env processes) -> `evaluation` (runner, statistics, the evaluation folder, plots, compare, the sweep's report).
`cli` holds every `cosim` subcommand; `files` (atomic writes, the one CSV reader and writer), `scratch` (temporary
files named after their owner), `errors` and `progress` serve them all.
"""

from typing import Any

__all__ = ["env", "parallel_env"]


def __getattr__(name: str) -> Any:
    # Lazy, so `import cosim.config` stays light (no gymnasium / pettingzoo import).
    if name in __all__:
        import cosim.environment.factory

        return getattr(cosim.environment.factory, name)
    raise AttributeError(name)
