"""The trainer end to end on the fake env: learning, checkpoints, resume, worker restarts, Ctrl-C, CLI."""

import argparse
import csv
from pathlib import Path

import pytest
import torch

import agents.train as train_module
from agents.checkpoint import CheckpointError, load_policy, read_checkpoint
from agents.config import train_config
from agents.fake_env import CueEnv, make_fake_env
from agents.model import ActorCritic
from agents.multiagent import MultiAgentPolicy
from agents.train import add_arguments, run, train
from cosim.config import load_config

SMALL = {"feature_dim": 32, "head_hidden": 32, "optimizer": "adam", "lr": 0.002, "disseminate_every": 4, "gamma": 0.5,
         "checkpoint_every": 10, "seed": 3}


def cfg_with(**train: object):
    return load_config({"train": {**SMALL, **train}})


def mean_return(policies: dict[str, ActorCritic], episodes: int = 40, seed: int = 100) -> float:
    """Mean per-agent episode return of sampled actions on the fake env, in this process."""
    torch.manual_seed(seed)
    env, total = CueEnv(n_agents=2), 0.0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        while env.agents:
            actions = {a: int(policies[a].act(obs[a][None])[0]) for a in env.agents}
            obs, rewards, *_ = env.step(actions)
            total += sum(rewards.values()) / len(env.possible_agents)
    return total / episodes


def episode_rows(run: Path) -> list[dict[str, str]]:
    with (run / "episodes.csv").open() as f:
        return list(csv.DictReader(f))


def test_training_improves_the_return_over_the_untrained_policy(tmp_path: Path) -> None:
    cfg = cfg_with()
    torch.manual_seed(SMALL["seed"])
    untrained = MultiAgentPolicy(2, (2, 4, 8, 16), 5, train_config(cfg))
    before = mean_return({"av_0": untrained.nets[0], "av_1": untrained.nets[1]})
    result = train(cfg, tmp_path / "run", workers=2, episodes=300, env_factory=make_fake_env(n_agents=2),
                   progress=False)
    policies, meta = load_policy(result.checkpoint)
    after = mean_return(policies)
    # random play scores about 0 per episode, the optimum 8 (horizon 8, reward 1 per correct answer)
    assert after > before + 4.0, (before, after)
    assert result.episodes >= 300 and meta["counters"]["episodes"] == result.episodes
    assert len(episode_rows(tmp_path / "run")) == result.episodes
    assert (tmp_path / "run" / "config.yaml").is_file() and (tmp_path / "run" / "updates.csv").is_file()
    assert any((tmp_path / "run" / "tb").iterdir())


def test_checkpoint_round_trip_and_resume_continues(tmp_path: Path) -> None:
    run, cfg = tmp_path / "run", cfg_with(shared_policy=True)
    first = train(cfg, run, workers=1, episodes=6, env_factory=make_fake_env(n_agents=2), progress=False)
    saved = read_checkpoint(first.checkpoint)
    policies, meta = load_policy(run)
    assert policies["av_0"] is policies["av_1"]  # shared policy
    assert all(torch.equal(v, saved["policy"]["nets"][0][k]) for k, v in policies["av_0"].state_dict().items())
    assert meta["spec"]["obs_shape"] == [2, 4, 8, 16] and meta["counters"]["updates"] == first.updates

    # resuming with nothing left to do keeps parameters and counters
    same = train(cfg, run, workers=1, episodes=6, resume=True, env_factory=make_fake_env(n_agents=2),
                 progress=False)
    again = read_checkpoint(same.checkpoint)
    assert (same.updates, same.episodes) == (first.updates, first.episodes)
    assert all(torch.equal(v, again["policy"]["nets"][0][k]) for k, v in saved["policy"]["nets"][0].items())
    assert all(torch.equal(v, again["policy"]["optimizers"][0]["state"][0][k])
               for k, v in saved["policy"]["optimizers"][0]["state"][0].items() if isinstance(v, torch.Tensor))

    more = train(cfg, run, workers=1, episodes=12, resume=True, env_factory=make_fake_env(n_agents=2),
                 progress=False)
    assert more.updates > first.updates and more.episodes >= 12
    numbers = [int(r["episode"]) for r in episode_rows(run)]
    assert numbers == list(range(1, more.episodes + 1))  # the logs continue the same run


def test_fresh_run_refuses_an_existing_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(cfg_with(), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2), progress=False)
    with pytest.raises(CheckpointError, match="--resume"):
        train(cfg_with(), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2), progress=False)


def test_incompatible_and_corrupt_checkpoints_are_clear_errors(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(cfg_with(), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2), progress=False)
    with pytest.raises(CheckpointError, match=r"checkpoint .*checkpoint\.pt: incompatible agents"):
        train(cfg_with(), run, workers=1, episodes=4, resume=True, env_factory=make_fake_env(n_agents=3),
              progress=False)
    with pytest.raises(CheckpointError, match="incompatible obs_shape"):
        train(cfg_with(), run, workers=1, episodes=4, resume=True,
              env_factory=make_fake_env(n_agents=2, obs_shape=(3, 4, 8, 16)), progress=False)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match=r"checkpoint .*bad\.pt: corrupt"):
        load_policy(bad)
    torch.save({"something": "else"}, bad)
    with pytest.raises(CheckpointError, match="not a cosim-ma-a2c checkpoint"):
        load_policy(bad)
    with pytest.raises(CheckpointError, match="not found"):
        train(cfg_with(), tmp_path / "nothing", workers=1, episodes=2, resume=True,
              env_factory=make_fake_env(n_agents=2), progress=False)


def test_worker_failure_restarts_and_the_episode_is_not_counted(tmp_path: Path) -> None:
    flag = tmp_path / "failed"
    run = tmp_path / "run"
    result = train(cfg_with(), run, workers=2, episodes=8,
                   env_factory=make_fake_env(n_agents=2, fail_once_file=str(flag), fail_at_step=3), progress=False)
    assert flag.exists()
    assert result.restarts == 1 and result.lost_episodes == 1
    assert len(episode_rows(run)) == result.episodes >= 8


def test_ctrl_c_writes_a_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    original = train_module.learner_update

    def interrupt_on_third(*args: object, **kwargs: object) -> dict[str, float]:
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(train_module, "learner_update", interrupt_on_third)
    result = train(cfg_with(), tmp_path / "run", workers=1, episodes=1000, env_factory=make_fake_env(n_agents=2),
                   progress=False)
    assert result.interrupted and result.updates == 2
    assert read_checkpoint(result.checkpoint)["counters"]["updates"] == 2


def test_cli_arguments_reach_the_trainer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = tmp_path / "smoke.yaml"
    config.write_text("train:\n  feature_dim: 16\n  head_hidden: 16\n")
    monkeypatch.setattr(train_module, "_default_env_factory", lambda cfg: make_fake_env(n_agents=2))
    parser = add_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--config", str(config), "--out", str(tmp_path / "run"), "--workers", "1",
                              "--episodes", "2", "--set", "train.lr=0.01", "--set", "train.rollout_steps=2"])
    assert run(args) == 0
    _, meta = load_policy(tmp_path / "run")
    assert meta["train"]["lr"] == 0.01 and meta["train"]["rollout_steps"] == 2 and meta["train"]["workers"] == 1
    saved = load_config(tmp_path / "run" / "config.yaml")  # the resolved config loads back
    assert train_config(saved).lr == 0.01 and train_config(saved).episodes == 2
