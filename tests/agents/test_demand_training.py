"""Training under demand on real SUMO: segments of continuing runs, who is bootstrapped, runs as episodes, the CLI."""

import csv
import functools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import CheckpointError, load_policy, read_checkpoint
from agents.collect import Segments
from agents.config import train_config
from agents.multiagent import Batch, MultiAgentPolicy
from agents.train import train
from cosim.cli import main
from cosim.config import load_config
from cosim.environment.factory import parallel_env
from cosim.errors import ConfigError
from cosim.sumo.setting import Setting
from cosim.workers import WorkerPool

pytestmark = pytest.mark.sumo

# Runs of 60 decisions (30 s warm-up, 30 s window) with many AVs, a small network from scratch.
SHORT = {"demand.warmup": 30.0, "demand.window": 30.0, "demand.av_penetration": 0.3, "train.feature_dim": 16,
         "train.head_hidden": 16, "train.precision": "float32", "train.seed": 4, "train.segment_steps": 16,
         "train.init_from": None}


def demand_cfg(**extra: object):
    return load_config("configs/demand.yaml", {**SHORT, **extra})


def test_segments_continue_each_run_and_bootstrap_the_agents_that_go_on() -> None:
    cfg = demand_cfg()
    pool = WorkerPool(functools.partial(parallel_env, cfg.to_dict()), 2, 0, 60.0)
    try:
        spec = pool.spec
        assert spec.agents == tuple(f"slot_{k}" for k in range(Setting.of(cfg).demand.slots))
        torch.manual_seed(0)
        policy = MultiAgentPolicy(len(spec.agents), spec.obs_shape, spec.n_actions, train_config(cfg))
        steps = 8
        batch = Batch.allocate(steps, 2, len(spec.agents), spec.obs_shape, getattr(torch, spec.obs_dtype),
                               spec.n_actions)
        segments, seeds, episodes, checked = Segments(pool), iter(range(100, 200)), [], 0
        left: np.ndarray | None = None  # the observations the last segment ended on
        for update in range(10):  # 80 decisions a worker: each run of 60 ends inside a segment, the next starts
            got = segments.collect(policy, batch, update, lambda w: next(seeds))
            episodes += got.episodes
            assert batch.valid.any(dim=2).all()  # every worker played every decision of the segment
            if left is not None and not got.episodes:  # the runs went on: no reset in between
                acting = batch.valid[0].numpy()
                assert np.array_equal(batch.obs[0].numpy()[acting], left[acting])
            for w in range(2):
                seed, res = segments.runs[w]
                if all(ep.worker != w for ep in got.episodes):  # the same run from the first decision to the last
                    # Who acted at the last decision and goes on is cut there, bootstrapped from where it goes on.
                    on = res.alive & batch.valid[-1, w].numpy() & ~batch.terminated[-1, w].numpy()
                    assert on.any() and batch.truncated[-1, w].numpy()[on].all()
                    idx = np.flatnonzero(on)
                    expect = policy.value(torch.from_numpy(pool.obs[w, idx]), torch.from_numpy(idx), update)
                    torch.testing.assert_close(batch.final_values[-1, w, idx], expect)
                    checked += 1
                # At a run's horizon every live agent is truncated with its last map, never zeros.
                ended = batch.truncated[:-1, w].any(dim=1).nonzero().flatten()  # before the last decision
                for t in ended.tolist():
                    cut = batch.truncated[t, w].nonzero().flatten().numpy()
                    assert all(pool.final[w, i].any() for i in cut)
                    assert (batch.final_values[t, w, cut] != 0).all()
            left = pool.obs.copy()
        # A run of 60 decisions (the first ones simulated until an AV enters) ended on each worker within its 80;
        # the next began with the next seed.
        assert checked >= 15 and sorted(ep.seed for ep in episodes) == [100, 101]
        assert all(ep.info["length"] == 60 and ep.info["avs_released"] > 0 for ep in episodes)
        assert sorted(seed for seed, _ in segments.runs.values()) == [102, 103]
    finally:
        pool.close()


def demand_train_args(run: Path, eval_every: int = 2) -> list[str]:
    """`cosim train` under demand on the short runs of SHORT, validated on 2 runs every `eval_every` (0: never)."""
    return ["train", "--config", "configs/demand.yaml", *(f"--set={k}={'null' if v is None else v}"
                                                          for k, v in SHORT.items()),
            f"--set=train.eval_every={eval_every}", "--set=train.eval_episodes=2", "--workers", "2", "--out", str(run)]


def test_cosim_train_under_demand_trains_runs_validates_resumes_and_evaluates(tmp_path: Path) -> None:
    run = tmp_path / "run"
    args = demand_train_args(run)
    assert main([*args, "--episodes", "2"]) == 0
    with (run / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(float(r["avs_released"]) > 0 and r["collisions"] != "" for r in rows)
    assert all(float(r["throughput_total_vph"]) > 0 for r in rows)  # each run's window flow, as evaluation's
    assert all(float(r["throughput_total_vph"]) == pytest.approx(float(r["throughput_mainline_vph"])
                                                                 + float(r["throughput_ramp_vph"])) for r in rows)
    # Validated on greedy runs of the validation seeds: the window's collisions, merges, throughput and delay.
    with (run / "validation.csv").open() as f:
        (val,) = list(csv.DictReader(f))
    assert float(val["episodes_validated"]) == 2 and float(val["throughput"]) > 0
    assert float(val["collisions_low"]) <= float(val["collisions"]) <= float(val["collisions_high"])
    assert {"merge", "delay", "return"} <= set(val) and (run / "best.pt").is_file()
    assert read_checkpoint(run / "checkpoint.pt")["spec"]["agents"][0] == "slot_0"
    assert main([*args, "--episodes", "4", "--resume"]) == 0
    with (run / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and len({r["seed"] for r in rows}) == 4  # a resumed run plays new runs
    policies, _ = load_policy(run)
    assert len(set(map(id, policies.values()))) == 1  # one shared network
    out = tmp_path / "eval"
    assert main(["evaluate", "--run", str(run), "--config", "configs/demand.yaml",
                 *(f"--set={k}={v}" for k, v in SHORT.items() if k.startswith("demand")),
                 "--set", "demand.seeds=1", "--out", str(out)]) == 0
    assert (out / "summary.json").is_file()


@pytest.mark.slow  # 20 s in CI: a short training run, then the headline's six demand runs
def test_the_demand_headline_weighs_a_trained_run_against_all_human_traffic_and_scripted(tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert main([*demand_train_args(run, eval_every=0), "--episodes", "2"]) == 0
    # The headline: the run against all-human traffic and `scripted` at a penetration and a demand level.
    headline = tmp_path / "headline"
    done = subprocess.run([sys.executable, "scripts/demand_headline.py", str(run), "--levels", "near capacity",
                           "--penetrations", "0.3", "--seeds", "2", "--out", str(headline),
                           *(f"--set={k}={v}" for k, v in SHORT.items() if k.startswith("demand"))],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    text = (headline / "headline.md").read_text()
    assert "## near capacity, 30% AVs" in text and "run: throughput" in text and "against scripted" in text
    for player in ("all-human", "scripted", "run"):
        assert len(list((headline / "near_capacity" / "30pct" / player).glob("sumo/run_*"))) == 2
    assert (headline / "headline.png").is_file()


@pytest.mark.parametrize("key,value,says", [
    ("train.shared_policy", False, "train.shared_policy: false: under demand"),
    ("train.segment_steps", 60, r"train.segment_steps: 60 decisions, not shorter than a run \(60 decisions"),
])
def test_what_demand_training_cannot_do_is_refused_in_one_line(tmp_path: Path, key: str, value: object,
                                                                   says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        train(demand_cfg(**{key: value}), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # 16 s
def test_training_under_demand_starts_from_the_shipped_episode_policy_by_default(tmp_path: Path,
                                                                                   caplog: pytest.LogCaptureFixture
                                                                                   ) -> None:
    default = {k: v for k, v in SHORT.items() if k not in ("train.feature_dim", "train.head_hidden", "train.init_from")}
    cfg = load_config("configs/demand.yaml", {**default, "reward.phi": 0.7854})
    assert cfg.train.egoistic_episodes  # configs/default.yaml's warm-up, which was measured on episodes only
    assert cfg.train.init_from == str(Path("policies/egoistic/best.pt").resolve())  # relative to the YAML file
    with caplog.at_level("INFO", logger="agents.train"):
        train(cfg, tmp_path / "run", episodes=1, workers=1, progress=False)
    assert "starting from the networks of " + cfg.train.init_from in caplog.text
    assert "no egoistic warm-up under demand" in caplog.text and "egoistic warm-up over" not in caplog.text
    assert json.loads((tmp_path / "run" / "net.json").read_text())["init_from"] == cfg.train.init_from
    # A network the shipped policy does not fit is one line naming the key and the way out; nothing is left behind.
    with pytest.raises(CheckpointError, match=r"train\.init_from: .*incompatible feature_dim.*train\.init_from=null"):
        train(demand_cfg(**{"train.init_from": cfg.train.init_from}), tmp_path / "small", progress=False)
    assert not (tmp_path / "small").exists()
