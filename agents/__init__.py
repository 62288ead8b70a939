"""Multi-agent actor-critic learning for the cosim merge env (paper: Toghi et al., Sections 4-5, Table 1).

Modules: `config` (the `train:` section), `model` (the Conv3D encoder and actor-critic), `losses` (GAE, the
A2C / PPO-clip loss, value normalisation, optimizers), `multiagent` (one shared network or per-AV networks with
the paper's semi-sequential schedule; acting and updates), `rollout` (where rollout workers run: local processes,
`cosim.workers`, or Ray), `ray_pool` (the same contract on Ray actors), `collect` (whole-episode rollouts with
inference batched across workers), `validation` (greedy episodes on the validation seeds during training, the best
kept), `checkpoint` (atomic save, validated load, `load_policy`, `export_policy`), `logs` (CSV + TensorBoard),
`train` (the loop, `train()`, `cosim train`), `sweep` (`cosim sweep`), `sb3` (Stable-Baselines3 on the env:
encoder, vector env, `--policy sb3`; the `sb3` extra), `fake_env` (a tiny env with the real one's spaces, for tests
and benchmarks). Evaluation and reports are `cosim.evaluation`'s.

Entry points: `agents.train.train` (`cosim train`), `agents.load_policy`.
`agents` never imports libsumo: it meets `cosim` through its config, errors, files and the PettingZoo env.
The names below are imported lazily so that rollout workers (which import `agents.rollout`) skip torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "TrainResult": "agents.train",
    "load_policy": "agents.checkpoint",
    "CheckpointError": "agents.checkpoint",
    "TrainConfig": "agents.config",
    "train_config": "agents.config",
    "ActorCritic": "agents.model",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
