"""The trainer end to end on the fake env: learning, checkpoints, resume, worker restarts, Ctrl-C, CLI."""

import csv
import json
import os
import signal
from pathlib import Path

import pytest
import torch
import yaml

import agents.train as train_module
from agents.checkpoint import CheckpointError, load_policy, read_checkpoint
from agents.config import train_config
from agents.fake_env import CueEnv, make_fake_env
from agents.model import ActorCritic
from agents.multiagent import MultiAgentPolicy
from agents.train import train
from cosim.cli import main
from cosim.config import load_config
from cosim.errors import ConfigError, EpisodeError, SimulationError

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SMALL = {"feature_dim": 32, "head_hidden": 32, "optimizer": "adam", "lr": 0.002, "disseminate_every": 4, "gamma": 0.5,
         "checkpoint_every": 10, "seed": 3, "precision": "float32"}


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


@pytest.mark.parametrize("algo,shared",
                         [pytest.param("a2c", True, marks=pytest.mark.slow), ("ppo", True),
                          pytest.param("a2c", False, marks=pytest.mark.slow)])  # A2C: 19-22 s each
def test_training_improves_the_return_over_the_untrained_policy(tmp_path: Path, algo: str, shared: bool) -> None:
    cfg = cfg_with(algo=algo, shared_policy=shared)
    torch.manual_seed(SMALL["seed"])
    untrained = MultiAgentPolicy(2, (2, 4, 8, 16), 5, train_config(cfg))
    before = mean_return({"av_0": untrained.nets[0], "av_1": untrained.nets[-1]})
    result = train(cfg, tmp_path / "run", workers=2, episodes=300, env_factory=make_fake_env(n_agents=2),
                   progress=False)
    policies, meta = load_policy(result.checkpoint)
    after = mean_return(policies)
    # random play scores about 0 per episode, the optimum 8 (horizon 8, reward 1 per correct answer)
    assert after > before + 4.0, (before, after)
    assert result.episodes == 300 and meta["counters"]["episodes"] == result.episodes
    assert len(episode_rows(tmp_path / "run")) == result.episodes
    assert (tmp_path / "run" / "config.yaml").is_file() and (tmp_path / "run" / "updates.csv").is_file()
    assert any((tmp_path / "run" / "tb").iterdir())


@pytest.mark.slow  # 19 s; under demand, segments train in the default tier (tests/agents/test_demand_training.py)
def test_segments_of_continuing_episodes_learn_and_seed_every_episode_apart(tmp_path: Path) -> None:
    # Segments of 12 decisions of episodes of 8: most episodes span two updates, bootstrapped at the cut.
    cfg = cfg_with(algo="ppo", segments=True, segment_steps=12)
    torch.manual_seed(SMALL["seed"])
    untrained = MultiAgentPolicy(2, (2, 4, 8, 16), 5, train_config(cfg))
    before = mean_return({"av_0": untrained.nets[0], "av_1": untrained.nets[-1]})
    result = train(cfg, tmp_path / "run", workers=2, episodes=300, env_factory=make_fake_env(n_agents=2),
                   progress=False)
    after = mean_return(load_policy(result.checkpoint)[0])
    assert after > before + 4.0, (before, after)
    rows = episode_rows(tmp_path / "run")
    assert 300 <= len(rows) == result.episodes < 300 + 2 * 12  # the last update's episodes end where they end
    assert len({r["seed"] for r in rows}) == len(rows)
    assert {"return_av_0", "return_av_1"} <= set(rows[0])  # per agent, as whole episodes' rows
    with (tmp_path / "run" / "updates.csv").open() as f:
        updates = list(csv.DictReader(f))
    # 2 workers x 12 decisions x 2 agents a segment, where no agent crashed: no worker waits for another.
    samples = [int(float(u["samples"])) for u in updates]
    assert max(b - a for a, b in zip(samples, samples[1:], strict=False)) == 48


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
    assert more.updates > first.updates and more.episodes == 12
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


def test_a_failed_worker_is_replaced_and_its_episode_goes_on_from_a_replay(tmp_path: Path) -> None:
    flag = tmp_path / "failed"
    run = tmp_path / "run"
    result = train(cfg_with(), run, workers=2, episodes=8,
                   env_factory=make_fake_env(n_agents=2, fail_once_file=str(flag), fail_at_step=3), progress=False)
    assert flag.exists()
    # The replacement played the episode again up to the failed step and went on: nothing lost.
    assert result.restarts == 1 and result.lost_episodes == 0
    assert len(episode_rows(run)) == result.episodes == 8


@pytest.mark.parametrize("resume", [False, True])
def test_an_episode_that_fails_again_on_a_fresh_worker_stops_at_once_leaving_the_folder(tmp_path: Path,
                                                                                       resume: bool) -> None:
    run = tmp_path / "run"
    if resume:
        train(cfg_with(), run, workers=2, episodes=4, env_factory=make_fake_env(n_agents=2), progress=False)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} if resume else {}
    with pytest.raises(EpisodeError, match=r"fails the same way on a fresh worker at decision step 3: "
                                           r"SimulationError: Departure speed"):
        train(cfg_with(), run, workers=2, episodes=8, resume=resume, progress=False,
              env_factory=make_fake_env(n_agents=2, fail_always=True, fail_at_step=3))
    assert run.exists() == resume  # a new run's folder is gone; a resumed one's is as it was, byte for byte
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


def test_too_many_worker_failures_stop_the_run_with_a_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(SimulationError, match="exceed train.max_restarts = 0"):
        train(cfg_with(max_restarts=0), run, workers=2, episodes=8, progress=False,
              env_factory=make_fake_env(n_agents=2, fail_once_file=str(tmp_path / "failed"), fail_at_step=3))
    counters = read_checkpoint(run / "checkpoint.pt")["counters"]  # the run at its last update boundary
    assert counters["episodes"] == 2 * counters["updates"] < 8
    result = train(cfg_with(max_restarts=0), run, workers=2, episodes=8, resume=True, progress=False,
                   env_factory=make_fake_env(n_agents=2))
    assert result.episodes == 8 and result.lost_episodes == 0


def signal_during_update(monkeypatch: pytest.MonkeyPatch, at: int, times: int = 1) -> None:
    """Ctrl-C `times` times while update number `at` (1-based) is learning."""
    calls = {"n": 0}
    original = MultiAgentPolicy.update

    def update(*args: object, **kwargs: object) -> dict[str, float]:
        calls["n"] += 1
        if calls["n"] == at:
            for _ in range(times):
                os.kill(os.getpid(), signal.SIGINT)
        return original(*args, **kwargs)

    monkeypatch.setattr(MultiAgentPolicy, "update", update)


def test_ctrl_c_finishes_the_update_checkpoints_and_resumes_bitwise(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = cfg_with(algo="ppo")
    whole = train(cfg, tmp_path / "whole", workers=2, episodes=12, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    signal_during_update(monkeypatch, at=3)
    cut = train(cfg, tmp_path / "cut", workers=2, episodes=12, env_factory=make_fake_env(n_agents=2), progress=False)
    assert cut.interrupted and cut.updates == 3
    assert read_checkpoint(cut.checkpoint)["counters"]["updates"] == 3
    monkeypatch.undo()
    resumed = train(cfg, tmp_path / "cut", workers=2, episodes=12, resume=True,
                    env_factory=make_fake_env(n_agents=2), progress=False)
    assert not resumed.interrupted and resumed.updates == whole.updates
    a, b = read_checkpoint(whole.checkpoint)["policy"], read_checkpoint(resumed.checkpoint)["policy"]
    assert all(torch.equal(v, b["nets"][0][k]) for k, v in a["nets"][0].items())
    assert episode_rows(tmp_path / "whole") == episode_rows(tmp_path / "cut")


def test_a_second_ctrl_c_stops_at_once_and_checkpoints_the_last_complete_update(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    signal_during_update(monkeypatch, at=4, times=2)
    result = train(cfg_with(checkpoint_every=2), tmp_path / "run", workers=1, episodes=100,
                   env_factory=make_fake_env(n_agents=2), progress=False)
    assert result.interrupted and result.updates == 3
    assert read_checkpoint(result.checkpoint)["counters"]["updates"] == 3  # not the half-done update 4


def test_cli_arguments_reach_the_trainer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = tmp_path / "smoke.yaml"
    config.write_text("train:\n  feature_dim: 16\n  head_hidden: 16\n")
    monkeypatch.setattr(train_module, "_default_env_factory", lambda cfg: make_fake_env(n_agents=2))
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run"), "--workers", "1",
                 "--episodes", "2", "--set", "train.lr=0.01", "--set", "train.algo=ppo"]) == 0
    _, meta = load_policy(tmp_path / "run")
    assert meta["train"]["lr"] == 0.01 and meta["train"]["algo"] == "ppo" and meta["train"]["workers"] == 1
    saved = load_config(tmp_path / "run" / "config.yaml")  # the resolved config loads back
    assert train_config(saved).lr == 0.01 and train_config(saved).episodes == 2


def test_resume_continues_the_same_sequence_bitwise(tmp_path: Path) -> None:
    cfg = cfg_with(algo="ppo", checkpoint_every=2)
    whole = train(cfg, tmp_path / "whole", workers=2, episodes=16, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    train(cfg, tmp_path / "split", workers=2, episodes=8, env_factory=make_fake_env(n_agents=2), progress=False)
    split = train(cfg, tmp_path / "split", workers=2, episodes=16, resume=True, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    assert (split.updates, split.episodes, split.samples) == (whole.updates, whole.episodes, whole.samples)
    a, b = read_checkpoint(whole.checkpoint)["policy"], read_checkpoint(split.checkpoint)["policy"]
    assert all(torch.equal(v, b["nets"][0][k]) for k, v in a["nets"][0].items())
    assert episode_rows(tmp_path / "whole") == episode_rows(tmp_path / "split")


def test_with_policy_ema_a_resume_goes_on_with_the_averages_and_the_policy_files_hold_them(tmp_path: Path) -> None:
    cfg = cfg_with(algo="ppo", checkpoint_every=2, policy_ema=0.9)
    whole = train(cfg, tmp_path / "whole", workers=2, episodes=16, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    train(cfg, tmp_path / "split", workers=2, episodes=8, env_factory=make_fake_env(n_agents=2), progress=False)
    split = train(cfg, tmp_path / "split", workers=2, episodes=16, resume=True, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    a, b = read_checkpoint(whole.checkpoint)["policy"], read_checkpoint(split.checkpoint)["policy"]
    assert a["averaged_counts"] == b["averaged_counts"] == [whole.updates]
    assert all(torch.equal(v, b["averaged"][0][k]) for k, v in a["averaged"][0].items())
    held = torch.load(tmp_path / "whole" / "policy.pt", weights_only=True)["nets"][0]
    assert all(torch.equal(v, a["averaged"][0][k]) for k, v in held.items())
    assert not all(torch.equal(v, a["nets"][0][k]) for k, v in held.items())


def test_resume_refuses_a_changed_config_before_touching_the_run(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(cfg_with(), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2), progress=False)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with pytest.raises(ConfigError, match=r"train\.lr: 0\.002 -> 0\.01.*--allow-config-change"):
        train(cfg_with(lr=0.01), run, workers=1, episodes=4, resume=True, env_factory=make_fake_env(n_agents=2),
              progress=False)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before  # nothing changed
    # More episodes is what a resume is for: allowed. A deliberate change is allowed and recorded.
    train(cfg_with(), run, workers=1, episodes=4, resume=True, env_factory=make_fake_env(n_agents=2), progress=False)
    train(cfg_with(lr=0.01), run, workers=1, episodes=6, resume=True, allow_config_change=True,
          env_factory=make_fake_env(n_agents=2), progress=False)
    changes = yaml.safe_load((run / "config_changes.yaml").read_text())
    assert changes[0]["changes"] == {"train.lr": {"from": 0.002, "to": 0.01}}
    assert train_config(load_config(run / "config.yaml")).lr == 0.01


def test_a_run_from_before_the_masks_and_safety_measures_resumes_as_it_trained(tmp_path: Path) -> None:
    """Its config.yaml has no safety section (which only counts) and no train.action_mask (it trained without):
    resuming it unmasked needs nothing more; with masks is a change of what it learns, refused naming the key."""
    run = tmp_path / "run"
    train(cfg_with(action_mask=False), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2),
          progress=False)
    saved = yaml.safe_load((run / "config.yaml").read_text())
    del saved["safety"], saved["train"]["action_mask"]
    (run / "config.yaml").write_text(yaml.safe_dump(saved))
    with pytest.raises(ConfigError, match=r"\(train\.action_mask: False -> True\); resume with the run's config "
                       r"\(cosim train --config RUN/config.yaml --set train.action_mask=false: the run is from before "
                       r"that key existed\)"):
        train(cfg_with(), run, workers=1, episodes=4, resume=True, env_factory=make_fake_env(n_agents=2),
              progress=False)
    resumed = train(cfg_with(action_mask=False), run, workers=1, episodes=4, resume=True,
                    env_factory=make_fake_env(n_agents=2), progress=False)
    assert resumed.episodes == 4


def test_a_killed_run_resumes_with_logs_cut_to_its_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = cfg_with(checkpoint_every=2)
    train(cfg, run, workers=1, episodes=4, env_factory=make_fake_env(n_agents=2), progress=False)
    # A run killed after the checkpoint of episode 4: two more episodes logged, a checkpoint write half done.
    rows = episode_rows(run)
    with (run / "episodes.csv").open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writerows([{**rows[-1], "episode": "5"}, {**rows[-1], "episode": "6"}])
    (run / ".checkpoint.x1y2z3.pt").write_bytes(b"half")
    train(cfg, run, workers=1, episodes=8, resume=True, env_factory=make_fake_env(n_agents=2), progress=False)
    assert [int(r["episode"]) for r in episode_rows(run)] == list(range(1, 9))
    assert not (run / ".checkpoint.x1y2z3.pt").exists()


def test_policy_file_is_small_and_loads_like_the_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(cfg_with(shared_policy=False), run, workers=1, episodes=2, env_factory=make_fake_env(n_agents=2),
          progress=False)
    assert (run / "policy.pt").stat().st_size < (run / "checkpoint.pt").stat().st_size / 3
    small, meta = load_policy(run)  # the policy file, since the run has one
    full, _ = load_policy(run / "checkpoint.pt")
    assert meta["path"].endswith("policy.pt") and set(small) == {"av_0", "av_1"}
    for a in small:
        assert all(torch.equal(v, full[a].state_dict()[k]) for k, v in small[a].state_dict().items())


@pytest.mark.parametrize("action_mask", [True, False])
def test_masked_actions_are_never_taken_in_training_and_the_setting_is_recorded(tmp_path: Path,
                                                                               action_mask: bool) -> None:
    """The fake env masks accelerate (its crash): with train.action_mask no training episode crashes; without it,
    the untrained policy takes it about one step in five. The checkpoint records the setting for evaluation."""
    run = tmp_path / "run"
    result = train(cfg_with(action_mask=action_mask), run, workers=2, episodes=12,
                   env_factory=make_fake_env(n_agents=2, masked=(3,)), progress=False)
    crashes = sum(float(r["crashed"]) for r in episode_rows(run))
    assert (crashes == 0) if action_mask else (crashes > 0)
    assert read_checkpoint(result.checkpoint)["train"]["action_mask"] is action_mask
    assert load_policy(run)[1]["train"]["action_mask"] is action_mask


def test_init_from_starts_a_new_run_from_a_policys_weights_with_a_fresh_optimizer(tmp_path: Path) -> None:
    from agents.checkpoint import export_policy

    first = train(cfg_with(), tmp_path / "first", workers=1, episodes=4, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    export_policy(first.checkpoint, tmp_path / "half.pt")  # a committed float16 snapshot
    second = train(cfg_with(), tmp_path / "second", workers=1, episodes=1, env_factory=make_fake_env(n_agents=2),
                   progress=False, init_from=tmp_path / "half.pt")
    assert second.episodes == 1  # a new run: its own counters
    # one episode of learning from the float16 weights: close to them, not a fresh initialisation
    a = load_policy(tmp_path / "half.pt")[0]["av_0"].state_dict()
    b = load_policy(second.checkpoint)[0]["av_0"].state_dict()
    assert all(torch.allclose(a[k], b[k], atol=0.05) for k in a)
    fresh = load_policy(train(cfg_with(seed=9), tmp_path / "fresh", workers=1, episodes=1,
                              env_factory=make_fake_env(n_agents=2), progress=False).checkpoint)[0]["av_0"]
    assert not all(torch.allclose(a[k], fresh.state_dict()[k], atol=0.05) for k in a)
    assert read_checkpoint(second.checkpoint)["policy"]["optimizers"][0]["state"][0]["step"] == 1  # fresh Adam
    with pytest.raises(ConfigError, match="--init-from .*: starts a new run; --resume continues one"):
        train(cfg_with(), tmp_path / "second", resume=True, init_from=tmp_path / "half.pt", progress=False,
              env_factory=make_fake_env(n_agents=2))
    with pytest.raises(CheckpointError, match="incompatible feature_dim"):
        train(cfg_with(feature_dim=16), tmp_path / "third", workers=1, episodes=1, progress=False,
              env_factory=make_fake_env(n_agents=2), init_from=tmp_path / "half.pt")


def test_separate_encoders_train_save_and_load_and_a_shared_policy_cannot_start_them(tmp_path: Path) -> None:
    from agents.checkpoint import check_spec, export_policy

    first = train(cfg_with(shared_encoder=False), tmp_path / "sep", workers=1, episodes=2,
                  env_factory=make_fake_env(n_agents=2), progress=False)
    export_policy(first.checkpoint, tmp_path / "sep.pt")
    policies, meta = load_policy(tmp_path / "sep.pt")
    assert meta["spec"]["shared_encoder"] is False and not policies["av_0"].shared_encoder
    shared = train(cfg_with(), tmp_path / "shared", workers=1, episodes=1, env_factory=make_fake_env(n_agents=2),
                   progress=False)
    with pytest.raises(CheckpointError, match="incompatible shared_encoder: checkpoint has True, this run needs False"):
        train(cfg_with(shared_encoder=False), tmp_path / "third", workers=1, episodes=1, progress=False,
              env_factory=make_fake_env(n_agents=2), init_from=shared.checkpoint)
    # Checkpoints from before the key trained one shared encoder: their spec has no entry, read as shared.
    check_spec({"spec": {"feature_dim": 32}}, {"feature_dim": 32, "shared_encoder": True}, tmp_path / "old.pt")


def test_a_central_critic_trains_saves_and_loads_and_a_run_without_one_cannot_start_from_it(tmp_path: Path) -> None:
    from agents.checkpoint import export_policy

    first = train(cfg_with(central_critic=True), tmp_path / "central", workers=2, episodes=4,
                  env_factory=make_fake_env(n_agents=2), progress=False)
    export_policy(first.checkpoint, tmp_path / "central.pt")
    policies, meta = load_policy(tmp_path / "central.pt")
    assert meta["spec"]["central_critic"] is True and policies["av_0"].central_critic
    assert policies["av_0"].act(torch.zeros((1, *policies["av_0"].obs_shape))).shape == (1,)
    with pytest.raises(CheckpointError, match="incompatible central_critic: checkpoint has True, this run needs False"):
        train(cfg_with(), tmp_path / "second", workers=1, episodes=1, progress=False,
              env_factory=make_fake_env(n_agents=2), init_from=tmp_path / "central.pt")


def test_obs_norm_learns_the_inputs_statistics_keeps_them_exact_in_float16_files_and_must_match(tmp_path: Path) -> None:
    from agents.checkpoint import check_spec, export_policy

    run = train(cfg_with(obs_norm=True), tmp_path / "norm", workers=1, episodes=2,
                env_factory=make_fake_env(n_agents=2), progress=False)
    payload = read_checkpoint(run.checkpoint)
    stats = {k: v for k, v in payload["policy"]["nets"][0].items() if k.startswith("obs_norm.")}
    assert float(stats["obs_norm.count"]) == payload["counters"]["samples"]  # every trained sample's newest frame
    assert stats["obs_norm.var"].min() < stats["obs_norm.var"].max()  # per pixel, not one figure
    export_policy(run.checkpoint, tmp_path / "norm.pt")
    policies, meta = load_policy(tmp_path / "norm.pt")
    net = policies["av_0"]
    assert meta["spec"]["obs_norm"] is True and net.obs_norm is not None
    assert all(torch.equal(net.state_dict()[k], v) for k, v in stats.items())  # not rounded to float16
    plain = train(cfg_with(), tmp_path / "plain", workers=1, episodes=1, env_factory=make_fake_env(n_agents=2),
                  progress=False)
    with pytest.raises(CheckpointError, match=r"incompatible obs_norm: checkpoint has False, this run needs True \(it "
                                              r"trained with train.obs_norm=false\)"):
        train(cfg_with(obs_norm=True), tmp_path / "third", workers=1, episodes=1, progress=False,
              env_factory=make_fake_env(n_agents=2), init_from=plain.checkpoint)
    # Checkpoints from before the key trained on the unstandardised input: read as off.
    check_spec({"spec": {"feature_dim": 32}}, {"feature_dim": 32, "obs_norm": False}, tmp_path / "old.pt")


def test_feature_norm_travels_with_the_policy_file_and_must_match(tmp_path: Path) -> None:
    from agents.checkpoint import check_spec, export_policy

    run = train(cfg_with(feature_norm=True), tmp_path / "ln", workers=1, episodes=1,
                env_factory=make_fake_env(n_agents=2), progress=False)
    export_policy(run.checkpoint, tmp_path / "ln.pt")
    policies, meta = load_policy(tmp_path / "ln.pt")
    net = policies["av_0"]
    assert meta["spec"]["feature_norm"] is True
    assert any(isinstance(m, torch.nn.LayerNorm) for m in net.features.modules())
    trained = read_checkpoint(run.checkpoint)["policy"]["nets"][0]
    gains = [k for k in trained if k.startswith("features.fc.1.")]
    assert gains and all(torch.equal(net.state_dict()[k].float(), trained[k].float().half().float()) for k in gains)
    with pytest.raises(CheckpointError, match=r"incompatible feature_norm: checkpoint has True, this run needs False "
                                              r"\(it trained with train.feature_norm=true\)"):
        train(cfg_with(), tmp_path / "plain", workers=1, episodes=1, progress=False,
              env_factory=make_fake_env(n_agents=2), init_from=run.checkpoint)
    # Checkpoints from before the key trained without it: read as off.
    check_spec({"spec": {"feature_dim": 32}}, {"feature_dim": 32, "feature_norm": False}, tmp_path / "old.pt")


def _learning_state(checkpoint: Path) -> tuple[int, float, int]:
    """Adam's steps so far, the value normaliser's debiasing weight and the warm-up's end (counters)."""
    payload = read_checkpoint(checkpoint)
    policy = payload["policy"]
    steps = int(next(iter(policy["optimizers"][0]["state"].values()))["step"])
    return steps, float(policy["value_norms"][0]["debias"]), int(payload["counters"].get("egoistic_until", 0))


def test_the_egoistic_warm_up_ends_once_with_a_fresh_optimizer_and_value_normaliser(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("INFO", logger="agents.train")
    per_update = 1  # SMALL trains with A2C, the built-in default: one step per update, of one episode each
    altruistic = load_config({"train": {**SMALL, "egoistic_episodes": 2}, "reward": {"phi": 0.7854}})
    env = make_fake_env(n_agents=2, social=100.0)  # the env's reward: each AV's terms + 100 for the others
    run = train(altruistic, tmp_path / "warm", workers=1, episodes=3, env_factory=env, progress=False)
    # Updates 1 and 2 trained on the AVs' own utility (returns of at most 1 / (1 - gamma) = 2), the third on the
    # env's reward, starting afresh.
    with (tmp_path / "warm" / "updates.csv").open() as f:
        returns = [float(row["return"]) for row in csv.DictReader(f)]
    assert max(returns[:2]) <= 2 and returns[2] > 50
    assert _learning_state(run.checkpoint) == (per_update, pytest.approx(1 - 0.995), 2)
    assert caplog.text.count("egoistic warm-up over at episode 2") == 1
    run = train(altruistic, tmp_path / "warm", workers=1, episodes=4, env_factory=env, progress=False, resume=True)
    assert _learning_state(run.checkpoint) == (2 * per_update, pytest.approx(1 - 0.995 ** 2), 2)  # not again
    assert caplog.text.count("egoistic warm-up over") == 1
    # A run that starts from a trained policy has learnt to drive: no warm-up, over a resume too.
    tuned = train(altruistic, tmp_path / "tuned", workers=1, episodes=1, env_factory=env, progress=False,
                  init_from=run.checkpoint)
    tuned = train(altruistic, tmp_path / "tuned", workers=1, episodes=3, env_factory=env, progress=False,
                  resume=True)
    assert _learning_state(tuned.checkpoint) == (3 * per_update, pytest.approx(1 - 0.995 ** 3), -1)
    assert caplog.text.count("egoistic warm-up over") == 1
    # Where every angle is 0 the reward is the egoistic one already: nothing to switch.
    egoistic = load_config({"train": {**SMALL, "egoistic_episodes": 2}, "reward": {"phi": 0.0}})
    run = train(egoistic, tmp_path / "ego", workers=1, episodes=3, env_factory=make_fake_env(n_agents=2),
                progress=False)
    assert _learning_state(run.checkpoint) == (3 * per_update, pytest.approx(1 - 0.995 ** 3), 0)


def test_a_resumed_fine_tune_still_names_the_policy_it_started_from(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    # The resume rewrote net.json from its own command line, which has no --init-from: the fine-tune's origin was lost.
    from agents.checkpoint import export_policy

    monkeypatch.setattr(train_module, "_default_env_factory", lambda cfg: make_fake_env(n_agents=2))
    first = train(cfg_with(), tmp_path / "first", workers=1, episodes=2, progress=False)
    export_policy(first.checkpoint, tmp_path / "start.pt")
    tune = tmp_path / "tune"
    train(cfg_with(), tune, workers=1, episodes=2, progress=False, init_from=tmp_path / "start.pt")
    started = json.loads((tune / "net.json").read_text())["init_from"]
    assert Path(started).resolve() == (tmp_path / "start.pt").resolve()
    # Its config named it too, so that `--config RUN/config.yaml` starts the same way: no longer null.
    assert load_config(tune / "config.yaml").train.init_from == str((tmp_path / "start.pt").resolve())
    train(cfg_with(), tune, workers=1, episodes=4, resume=True, progress=False)
    assert json.loads((tune / "net.json").read_text())["init_from"] == started
    assert load_config(tune / "config.yaml").train.init_from == str((tmp_path / "start.pt").resolve())
    # A run from scratch names none, before and after a resume.
    assert load_config(tmp_path / "first" / "config.yaml").train.init_from is None


def test_a_signal_during_a_checkpoint_write_waits_until_the_write_is_whole(caplog: pytest.LogCaptureFixture) -> None:
    # Cut by KeyboardInterrupt, torch's zip writer raised a RuntimeError of its own: a traceback, exit 1 (seen in CI
    # when a second Ctrl-C landed in the final checkpoint's write).
    steps = []
    with train_module.StopRequest() as stop:
        with train_module.StopRequest.held():
            signal.raise_signal(signal.SIGINT)
            steps.append("written")  # the write goes on
            assert not stop.requested
        assert stop.requested  # the signal, replayed once the write is whole, asks for the stop
        with pytest.raises(KeyboardInterrupt), train_module.StopRequest.held():
            signal.raise_signal(signal.SIGINT)  # a second one: stop at once, but after the write
            steps.append("written again")
    with train_module.StopRequest.held(replay=False):  # the final checkpoint: the run is stopping already
        signal.raise_signal(signal.SIGINT)
        steps.append("final")
    assert steps == ["written", "written again", "final"]
    assert "SIGINT: writing the final checkpoint, then stopping" in caplog.text
