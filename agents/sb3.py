"""Stable-Baselines3 on the env (`pip install -e ".[sb3]"`): the paper's encoder as SB3's features extractor,
the vector env of SuperSuit's wrappers, and a saved SB3 model as a policy of `cosim evaluate --policy sb3`.

Contract: `make_vec_env(config, envs, seed)` gives an SB3 `VecEnv` over `envs` copies of the env, each in a
process of its own when there are several (libsumo allows one SUMO per process), every AV a sub-env
(SuperSuit's `black_death_v3` keeps an AV that has left with zero observations until its episode ends,
`pettingzoo_env_to_vec_env_v1` makes the AVs sub-envs, so one network serves them all); copy i plays its own
episode seeds, below the evaluation seeds. `ppo_kwargs(train_config)` sets SB3's PPO as `cosim train` is set
(`sb3_train_config` first leaves out `train.obs_norm`, `train.egoistic_episodes` and `train.central_critic`, which
SB3's PPO here has no counterpart of), with
`VelocityMapExtractor` (the paper's Conv3D stack) under its policy; a saved model loads by `load_actor(path)`
as an actor with `ActorCritic.act`'s signature, and a file that is no SB3 model (cosim's own policy.pt, say) is a
`ConfigError` naming it and what `--policy sb3` takes.
"""

from __future__ import annotations

import functools
import logging
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import gymnasium
import numpy as np
import supersuit as ss
import torch
from pettingzoo import ParallelEnv
from stable_baselines3 import PPO
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecMonitor
from supersuit.vector import MakeCPUAsyncConstructor
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from agents.checkpoint import act_agents
from agents.config import TrainConfig
from agents.model import VelocityMapEncoder
from cosim.config import EVAL_SEED_START, Config
from cosim.errors import ConfigError
from cosim.files import file_sha256

log = logging.getLogger(__name__)

EPISODES_PER_COPY = 1_000_000  # episode seeds set aside for each env copy of a run


class VelocityMapExtractor(BaseFeaturesExtractor):
    """`agents.model.VelocityMapEncoder` as SB3's features extractor."""

    def __init__(self, observation_space: gymnasium.spaces.Box, features_dim: int = 512,
                 layer_norm: bool = False) -> None:
        super().__init__(observation_space, features_dim)
        self.encoder = VelocityMapEncoder(observation_space.shape, features_dim, layer_norm)
        # SB3 hands over float copies of the env's uint8 maps: scale them as the encoder scales uint8.
        self.scale = 255.0 if observation_space.dtype == np.uint8 else 1.0

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.encoder(obs / self.scale)


def sb3_train_config(tc: TrainConfig) -> TrainConfig:
    """The train section as SB3's PPO here takes it: without `train.obs_norm`, cosim's own input standardisation
    (SB3's `VecNormalize` standardises without `agents.model.ObsNorm`'s floor on the std, and its statistics would
    not travel with the model to `cosim evaluate --policy sb3`), and without `train.egoistic_episodes` (SB3's PPO
    trains on the env's reward), and without `train.central_critic` (every AV is a sub-env of its own there), with a
    warning for each the config had on."""
    if tc.obs_norm:
        log.warning("train.obs_norm: cosim train's input standardisation has no counterpart in SB3's PPO here; it "
                    "trains on the input scaled to [0, 1], as the paper's network does")
    if tc.egoistic_episodes:
        log.warning("train.egoistic_episodes: cosim train's egoistic warm-up has no counterpart in SB3's PPO here; "
                    "it trains on reward.phi's reward from the first episode")
    if tc.central_critic:
        log.warning("train.central_critic: SB3's PPO here sees each AV as an env of its own; its critic reads the AV's "
                    "own map only")
    return tc.model_copy(update={"obs_norm": False, "egoistic_episodes": 0, "central_critic": False})


def ppo_kwargs(tc: TrainConfig, n_steps: int, batch: int) -> dict[str, Any]:
    """SB3 PPO's arguments from the config's `train:` section: the same network (the paper's encoder, then one
    hidden layer for the actor and one for the critic) and the same PPO settings as `cosim train`; `batch` is
    the agent-samples one rollout of `n_steps` per sub-env collects. `train.obs_norm` has no counterpart here: SB3's
    PPO takes the input scaled to [0, 1], as the paper's network does (`sb3_train_config` says so)."""
    return {"n_steps": n_steps, "batch_size": max(1, batch // tc.ppo_minibatches), "n_epochs": tc.ppo_epochs,
            "learning_rate": tc.lr, "gamma": tc.gamma, "gae_lambda": tc.gae_lambda, "clip_range": tc.clip_range,
            "ent_coef": tc.entropy_coef, "vf_coef": tc.value_coef, "max_grad_norm": tc.max_grad_norm,
            "normalize_advantage": tc.normalize_advantage,
            "policy_kwargs": {"features_extractor_class": VelocityMapExtractor,
                              "features_extractor_kwargs": {"features_dim": tc.feature_dim,
                                                            "layer_norm": tc.feature_norm},
                              "net_arch": [tc.head_hidden], "normalize_images": False,
                              "share_features_extractor": tc.shared_encoder}}


class _SummaryRenamed(VecEnvWrapper):
    """SB3 reads info["episode"] as its own statistics ({r, l, t}, from VecMonitor): the env's summary, which
    has that name too, moves to info["cosim_episode"]."""

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            if "episode" in info:
                info["cosim_episode"] = info.pop("episode")
        return obs, rewards, dones, infos


def _agents_as_envs(config: dict[str, Any], first_seed: int) -> Any:
    import cosim

    return ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(cosim.parallel_env(config, {"sim.seed": first_seed})))


def make_vec_env(config: Config, envs: int, seed: int) -> VecEnv:
    """`envs` env copies (each in a process of its own when there are several), all their AVs as sub-envs."""
    if (seed * envs + envs) * EPISODES_PER_COPY > EVAL_SEED_START:
        raise ConfigError(f"--seed {seed} with --envs {envs}: the episode seeds would reach the evaluation seeds "
                          f"({EVAL_SEED_START:,}); at most (seed + 1) * envs = {EVAL_SEED_START // EPISODES_PER_COPY}")
    # Not ss.concat_vec_envs_v1: it clones one env, so that every copy would play the same episodes.
    fns = [functools.partial(_agents_as_envs, config.to_dict(), (seed * envs + i) * EPISODES_PER_COPY)
           for i in range(envs)]
    example = fns[0]()
    spaces = example.observation_space, example.action_space
    example.close()  # libsumo's one simulation per process: SuperSuit builds another example here
    return VecMonitor(_SummaryRenamed(SB3VecEnvWrapper(MakeCPUAsyncConstructor(envs)(fns, *spaces))))


class Sb3Actor:
    """A saved SB3 model acting like `agents.model.ActorCritic.act`, so that the project's batching
    (`agents.checkpoint.act_agents`) serves it."""

    def __init__(self, model: PPO) -> None:
        self.model = model

    def act(self, obs: np.ndarray, greedy: bool = False) -> np.ndarray:
        """Actions (B,) for observations (B, F, C, H, W): the most likely if greedy, else sampled."""
        actions, _ = self.model.predict(obs, deterministic=greedy)
        return np.asarray(actions, dtype=np.int64)


def check_model_file(path: Path) -> None:
    """`ConfigError` naming `path` unless it is a zip with SB3's `data` entry, as `model.save` writes it (SB3's
    own load would fail on an assertion)."""
    expected = "--policy sb3 takes a Stable-Baselines3 model, the .zip that scripts/train_sb3.py saves"
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (OSError, zipfile.BadZipFile):
        raise ConfigError(f"--checkpoint {path}: not a zip file; {expected}") from None
    if "data" not in names:
        # torch.save writes a zip too, with ARCHIVE/data.pkl: most likely a policy.pt or checkpoint.pt of cosim's.
        torch_file = any(n.endswith("/data.pkl") for n in names)
        raise ConfigError(f"--checkpoint {path}: " + (
            "a PyTorch file, not a Stable-Baselines3 model; for cosim's own policy.pt or checkpoint.pt use "
            f"--policy checkpoint; {expected}" if torch_file else f"no Stable-Baselines3 model in it; {expected}"))


def load_actor(path: Path, obs_shape: tuple[int, ...], n_actions: int) -> Sb3Actor:
    """A saved SB3 PPO model, checked against the scenario's observation shape and actions."""
    check_model_file(path)
    try:
        model = PPO.load(path, device="cpu")
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError(f"--checkpoint {path}: not a Stable-Baselines3 PPO model ({exc})") from None
    if tuple(model.observation_space.shape) != tuple(obs_shape) or model.action_space.n != n_actions:
        raise ConfigError(f"--checkpoint {path}: trained on observations {model.observation_space.shape} with "
                          f"{model.action_space.n} actions; this scenario has {obs_shape} and {n_actions}")
    return Sb3Actor(model)


@dataclass(frozen=True)
class Sb3Policy:
    """A saved SB3 PPO model (`scripts/train_sb3.py`) as a policy of `cosim.evaluation.runner.evaluate`: one
    network for all AVs, batched as the project's own policies are (`agents.checkpoint.act_agents`)."""

    model: str  # the model .zip
    greedy: bool = True
    name: ClassVar[str] = "sb3"
    overrides: ClassVar[Mapping[str, Any]] = {}

    def identity(self) -> dict[str, Any]:
        # An SB3 model has no update counter: its content tells a retrained model from the evaluated one.
        sha = file_sha256(self.model)
        return {"checkpoint": self.model, "greedy": self.greedy, "trained_updates": None, "model_sha256": sha}

    def load(self, env: ParallelEnv, worker: bool) -> Callable[[int], Callable[[Mapping[str, np.ndarray]], dict]]:
        if worker:
            torch.set_num_threads(1)
        agents = env.possible_agents
        actor = load_actor(Path(self.model), tuple(env.observation_space(agents[0]).shape),
                           int(env.action_space(agents[0]).n))
        actors = dict.fromkeys(agents, actor)

        def for_episode(seed: int) -> Callable[[Mapping[str, np.ndarray]], dict]:
            torch.manual_seed(seed)
            return lambda obs: act_agents(actors, obs, self.greedy)

        return for_episode
