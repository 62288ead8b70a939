"""Where rollout workers run: local processes (`cosim.workers.WorkerPool`) or Ray actors (`agents.ray_pool`).

Contract: `Backend(name, ray_address).pool(env_factory, workers, max_restarts, timeout)` starts a pool with
`WorkerPool`'s interface; `check()` raises `ConfigError` for an unknown backend or an address without Ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cosim.errors import ConfigError
from cosim.workers import EnvFactory, WorkerPool

BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class Backend:
    """Where rollout workers run: `local` processes (`WorkerPool`) or Ray actors (`agents.ray_pool`)."""

    name: str = "local"  # one of BACKENDS
    ray_address: str | None = None  # ray: a cluster to join ("auto" | HOST:PORT); None: a local Ray

    def check(self) -> None:
        if self.name not in BACKENDS:
            raise ConfigError(f"--backend {self.name}: expected one of {list(BACKENDS)}")
        if self.ray_address is not None and self.name != "ray":
            raise ConfigError(f"--ray-address {self.ray_address}: only with --backend ray")

    def pool(self, env_factory: EnvFactory, workers: int, max_restarts: int, timeout: float) -> Any:
        """A started pool of `workers` envs (`WorkerPool`'s interface)."""
        self.check()
        if self.name == "ray":
            from agents.ray_pool import RayWorkerPool  # Ray only where it is asked for

            return RayWorkerPool(env_factory, workers, max_restarts, timeout, self.ray_address)
        return WorkerPool(env_factory, workers, max_restarts, timeout)
