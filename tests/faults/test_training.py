"""Bad input and faults through the `cosim` command, as a user meets them: one clear line, the exit code, no
traceback, nothing in a run folder changed, nothing left in the temporary folder; signals and killed or
stopped rollout workers during real training on SUMO (configs/smoke.yaml)."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path
from typing import Any

import pytest
import torch

from agents.checkpoint import read_checkpoint

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "smoke.yaml")


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory, cli_class: type) -> Path:
    """A finished 4-episode smoke run (real SUMO, two workers), in float32: the bitwise resume below continues
    it, and bfloat16 (precision auto on CPUs with AVX512-BF16 / AMX) is not reproducible run to run."""
    tmp = tmp_path_factory.mktemp("smoke_run")
    cli = cli_class(tmp)
    proc = cli.run("train", "--config", SMOKE, "--out", "run",
                   *cli.settings("train.episodes=4", "train.checkpoint_every=2", "train.precision=float32"))
    assert proc.returncode == 0, proc.stderr
    return tmp / "run"


@pytest.mark.parametrize("args,expected", [
    (["run-scenario", "--config", SMOKE, "--set", "scenario.nope=1"], "--set scenario.nope=1: unknown key"),
    (["run-scenario", "--config", SMOKE, "--set", "reward.phi=abc"], "expected a number or a list of numbers"),
    (["run-scenario", "--config", SMOKE, "--set", "net.file=missing.net.xml"], "missing.net.xml: not found"),
    (["run-scenario", "--config", SMOKE, "--set", "sim.decision_period=0.25"], "whole number of"),
    (["build-net", "--accel-length", "0.5", "--out", "net"], "accel_length must be at least 20 m"),
    (["evaluate", "--config", SMOKE, "--policy", "idle", "--episodes", "0"], "--episodes: must be >= 1"),
    (["evaluate", "--config", SMOKE, "--policy", "idle", "--episodes", "1", "--out", "a_file"], "a_file"),
    (["train", "--config", SMOKE, "--out", "a_file"], "a_file: is a file, not a folder"),
    (["compare", "no_such_run", "--out", "report"], "no_such_run: no evaluation found"),
    (["run-scenario", "--config", SMOKE, "--episodes", "1", "--save-routes", "a_file/routes"], "a_file/routes"),
    (["train", "--config", SMOKE, "--out", "run", "--ray-address", "auto"], "only with --backend ray"),
    (["train", "--config", SMOKE, "--out", "run", "--set", "demand.enabled=true", "--set", "train.shared_policy=false"],
     "train.shared_policy: false: under demand AVs come and go"),
    (["check-net", "no_such.net.xml"], "no_such.net.xml: not found"),
    (["replay", "--config", str(ROOT / "configs" / "demand.yaml"), "--policy", "idle", "--out", "replay"],
     "demand.enabled: cosim replay films one episode of the episode scenario"),
    (["check-net", str(ROOT / "sumo_net" / "dilemma" / "dilemma.net.xml"), "--config",
      str(ROOT / "configs" / "demand.yaml")],
     "demand.enabled: check-net judges the episode scenario"),
    (["run-scenario", "--config", SMOKE, "--net", "no_such.net.xml"], "--net no_such.net.xml: not found"),
    (["evaluate", "--config", SMOKE, "--policy", "idle", "--out", "x", "--set", "demand.enabled=true",
      "--set", "demand.warmup=45"],
     "--set demand.warmup=45: must be a whole number of demand.interval"),
    (["train", "--config", SMOKE, "--out", "run", "--backend", "ray", "--ray-address", "127.0.0.1:1"],
     "127.0.0.1:1: cannot reach it"),
])
def test_bad_input_is_one_line_and_exit_2(cli: Any, tmp_path: Path, args: list[str], expected: str) -> None:
    (tmp_path / "a_file").write_text("mine\n")
    cli.assert_clean_error(cli.run(*args), expected)
    assert (tmp_path / "a_file").read_text() == "mine\n"  # a file in the way is not overwritten
    assert cli.no_leftovers()


@pytest.mark.slow  # 18 s
def test_refused_resume_and_refused_outputs_leave_the_run_unchanged(smoke_run: Path, cli_class: type) -> None:
    cli = cli_class(smoke_run.parent)
    before = cli.folder_state(smoke_run)
    tmp = smoke_run.parent
    cli.assert_clean_error(cli.run("train", "--config", SMOKE, "--out", "run", "--resume",
                                   *cli.settings("train.episodes=8", "scenario.n_avs=3", "train.precision=float32")),
                           "scenario.n_avs: 2 -> 3")
    cli.assert_clean_error(cli.run("train", "--config", SMOKE, "--out", "run", "--set", "train.episodes=8"),
                           "exists already")
    (tmp / "taken").write_text("mine\n")
    cli.assert_clean_error(cli.run("evaluate", "--run", "run", "--episodes", "1", "--out", "taken"), "taken")
    assert cli.folder_state(smoke_run) == before
    # The run is still usable: an evaluation of it works.
    assert cli.run("evaluate", "--run", "run", "--episodes", "1", "--out", "eval").returncode == 0


@pytest.mark.slow  # 20 s; the default tier resumes bitwise on the fake env (tests/agents/test_train.py)
def test_resume_on_real_sumo_is_bitwise_the_uninterrupted_run(smoke_run: Path, cli: Any, tmp_path: Path) -> None:
    common = ("--config", SMOKE,
              *cli.settings("train.checkpoint_every=2", "train.episodes=8", "train.precision=float32"))
    assert cli.run("train", *common, "--out", "whole").returncode == 0
    split = tmp_path / "split"
    split.mkdir()
    for name in ("checkpoint.pt", "config.yaml", "episodes.csv", "updates.csv"):
        (split / name).write_bytes((smoke_run / name).read_bytes())  # the first 4 episodes, same config
    proc = cli.run("train", *common, "--out", "split", "--resume")
    assert proc.returncode == 0, proc.stderr
    a, b = (read_checkpoint(tmp_path / r / "checkpoint.pt")["policy"]["nets"][0] for r in ("whole", "split"))
    assert all(torch.equal(v, b[k]) for k, v in a.items())
    assert (tmp_path / "whole" / "episodes.csv").read_text() == (split / "episodes.csv").read_text()


def _start_training(cli: Any, *extra: str) -> subprocess.Popen[str]:
    return cli.start("train", "--config", SMOKE, "--out", "run",
                     *cli.settings("train.episodes=400", "train.checkpoint_every=2", *extra))


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)])  # 8-10 s each
def test_a_signal_stops_training_with_a_checkpoint_and_exit_130(cli: Any, tmp_path: Path,
                                                               sig: signal.Signals) -> None:
    proc = _start_training(cli)
    cli.wait_for(proc, "update 1,")
    proc.send_signal(sig)
    out = cli.finish(proc)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "stopping after the update in progress" in out
    assert read_checkpoint(tmp_path / "run" / "checkpoint.pt")["counters"]["episodes"] >= 2
    assert cli.no_leftovers()


@pytest.mark.slow  # 11-14 s each
@pytest.mark.parametrize("fault", ["kill", "stop"])
def test_a_killed_or_stopped_worker_is_replaced_and_training_goes_on(cli: Any, tmp_path: Path,
                                                                     fault: str) -> None:
    proc = _start_training(cli, "train.step_timeout=5", "train.episodes=12")
    cli.wait_for(proc, "update 1,")
    victim = cli.workers(proc)[0]
    os.kill(victim, signal.SIGKILL if fault == "kill" else signal.SIGSTOP)
    out = cli.finish(proc, timeout=300)
    assert proc.returncode == 0, out
    assert "replacing it (restart 1 of at most 100)" in out and "Traceback" not in out
    if fault == "stop":
        assert "no answer in 5 s (train.step_timeout)" in out
    assert read_checkpoint(tmp_path / "run" / "checkpoint.pt")["counters"]["episodes"] == 12
    assert cli.no_leftovers()


def test_ctrl_c_during_a_two_worker_evaluation_exits_130_cleanly(cli: Any) -> None:
    proc = cli.start("evaluate", "--config", SMOKE, "--policy", "idle", "--episodes", "5000", "--workers", "2",
                     "--out", "eval")
    cli.wait_for(proc, "1 of 5000 episodes")
    proc.send_signal(signal.SIGINT)
    out = cli.finish(proc)
    assert proc.returncode == 130 and "Traceback" not in out, out
    assert cli.no_leftovers()


@pytest.mark.slow
def test_memory_stays_flat_over_2000_evaluation_episodes(tmp_path: Path) -> None:
    from cosim.config import load_config
    from cosim.evaluation.runner import Baseline, evaluate

    def rss_mib() -> float:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    cfg = load_config(SMOKE)
    evaluate(cfg, Baseline("idle"), tmp_path / "eval", episodes=200, trajectories=0, plots=False)
    warm = rss_mib()
    evaluate(cfg, Baseline("idle"), tmp_path / "eval", episodes=2000, trajectories=0, plots=False)  # resumes
    assert rss_mib() - warm < 50.0, (warm, rss_mib())
