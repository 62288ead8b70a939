"""Bad input and faults through the `cosim` command, as a user meets them: one clear line, the exit code, no
traceback, nothing in a run folder changed, nothing left in the temporary folder; signals and killed or
stopped rollout workers during real training on SUMO (configs/smoke.yaml)."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from agents.checkpoint import read_checkpoint

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")


def cosim_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "cosim.cli", *args]


def settings(*pairs: str) -> list[str]:
    return [a for kv in pairs for a in ("--set", kv)]


def run_cli(tmp: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cosim_cmd(*args), cwd=tmp, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "TMPDIR": str(_tmpdir(tmp))})


def _tmpdir(tmp: Path) -> Path:
    folder = tmp / "tmpdir"
    folder.mkdir(exist_ok=True)
    return folder


def no_leftovers(tmp: Path) -> bool:
    """No temporary folder or file of ours left (torch keeps its own caches there, which are not ours)."""
    return not [p for p in _tmpdir(tmp).iterdir() if p.name.startswith("cosim")]


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored, and Python keeps it ignored: give the command the
    # terminal's default, as when a user presses Ctrl-C.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def assert_clean_error(proc: subprocess.CompletedProcess[str], expected: str, code: int = 2) -> None:
    err = proc.stdout + proc.stderr
    assert proc.returncode == code, err
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if " ERROR " in line]
    assert len(errors) == 1 and expected in errors[0], err


def folder_state(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished 4-episode smoke run (real SUMO, two workers)."""
    tmp = tmp_path_factory.mktemp("smoke_run")
    proc = run_cli(tmp, "train", "--config", SMOKE, "--out", "run",
                   *settings("train.episodes=4", "train.checkpoint_every=2"))
    assert proc.returncode == 0, proc.stderr
    return tmp / "run"


@pytest.mark.parametrize("args,expected", [
    (["run-scenario", "--config", SMOKE, "--set", "scenario.nope=1"], "config key scenario.nope: unknown"),
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
    (["train", "--config", SMOKE, "--out", "run", "--backend", "ray", "--ray-address", "127.0.0.1:1"],
     "127.0.0.1:1: cannot reach it"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], expected: str) -> None:
    (tmp_path / "a_file").write_text("mine\n")
    assert_clean_error(run_cli(tmp_path, *args), expected)
    assert (tmp_path / "a_file").read_text() == "mine\n"  # a file in the way is not overwritten
    assert no_leftovers(tmp_path)


def test_refused_resume_and_refused_outputs_leave_the_run_unchanged(smoke_run: Path) -> None:
    before = folder_state(smoke_run)
    tmp = smoke_run.parent
    assert_clean_error(run_cli(tmp, "train", "--config", SMOKE, "--out", "run", "--resume",
                               *settings("train.episodes=8", "scenario.n_avs=3")), "scenario.n_avs: 2 -> 3")
    assert_clean_error(run_cli(tmp, "train", "--config", SMOKE, "--out", "run", "--set", "train.episodes=8"),
                       "exists already")
    (tmp / "taken").write_text("mine\n")
    assert_clean_error(run_cli(tmp, "evaluate", "--run", "run", "--episodes", "1", "--out", "taken"), "taken")
    assert folder_state(smoke_run) == before
    # The run is still usable: an evaluation of it works.
    assert run_cli(tmp, "evaluate", "--run", "run", "--episodes", "1", "--out", "eval").returncode == 0


def test_resume_on_real_sumo_is_bitwise_the_uninterrupted_run(smoke_run: Path, tmp_path: Path) -> None:
    common = ("--config", SMOKE, *settings("train.checkpoint_every=2", "train.episodes=8"))
    assert run_cli(tmp_path, "train", *common, "--out", "whole").returncode == 0
    split = tmp_path / "split"
    split.mkdir()
    for name in ("checkpoint.pt", "config.yaml", "episodes.csv", "updates.csv"):
        (split / name).write_bytes((smoke_run / name).read_bytes())  # the first 4 episodes, same config
    proc = run_cli(tmp_path, "train", *common, "--out", "split", "--resume")
    assert proc.returncode == 0, proc.stderr
    a, b = (read_checkpoint(tmp_path / r / "checkpoint.pt")["policy"]["nets"][0] for r in ("whole", "split"))
    assert all(torch.equal(v, b[k]) for k, v in a.items())
    assert (tmp_path / "whole" / "episodes.csv").read_text() == (split / "episodes.csv").read_text()


def _start_training(tmp: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(cosim_cmd("train", "--config", SMOKE, "--out", "run",
                                      *settings("train.episodes=400", "train.checkpoint_every=2", *extra)),
                            cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "TMPDIR": str(_tmpdir(tmp))}, preexec_fn=_default_sigint)


def _wait_for(proc: subprocess.Popen[str], text: str, timeout: float = 240) -> list[str]:
    """Lines of proc's output up to the first containing `text`."""
    lines, end = [], time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    proc.kill()
    pytest.fail(f"no {text!r} in: {''.join(lines)}")


def _finish(proc: subprocess.Popen[str], timeout: float = 120) -> str:
    try:
        return proc.communicate(timeout=timeout)[0]
    finally:
        proc.kill()  # a hung command must not outlive its test


def _workers(proc: subprocess.Popen[str]) -> list[int]:
    """Rollout worker pids: grandchildren of the trainer (its forkserver's children)."""
    def children(pid: int) -> list[int]:
        out = []
        for task in Path(f"/proc/{pid}/task").iterdir():
            out += [int(c) for c in (task / "children").read_text().split()]
        return out
    return [g for c in children(proc.pid) for g in children(c)]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_training_with_a_checkpoint_and_exit_130(tmp_path: Path, sig: signal.Signals) -> None:
    proc = _start_training(tmp_path)
    _wait_for(proc, "update 1,")
    proc.send_signal(sig)
    out = _finish(proc)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "stopping after the update in progress" in out
    assert read_checkpoint(tmp_path / "run" / "checkpoint.pt")["counters"]["episodes"] >= 2
    assert no_leftovers(tmp_path)


@pytest.mark.parametrize("fault", ["kill", "stop"])
def test_a_killed_or_stopped_worker_is_replaced_and_training_goes_on(tmp_path: Path, fault: str) -> None:
    proc = _start_training(tmp_path, "train.step_timeout=5", "train.episodes=12")
    _wait_for(proc, "update 1,")
    victim = _workers(proc)[0]
    os.kill(victim, signal.SIGKILL if fault == "kill" else signal.SIGSTOP)
    out = _finish(proc, timeout=300)
    assert proc.returncode == 0, out
    assert "replacing it (restart 1 of at most 100)" in out and "Traceback" not in out
    if fault == "stop":
        assert "no answer in 5 s (train.step_timeout)" in out
    assert read_checkpoint(tmp_path / "run" / "checkpoint.pt")["counters"]["episodes"] == 12
    assert no_leftovers(tmp_path)


def test_ctrl_c_during_a_two_worker_evaluation_exits_130_cleanly(tmp_path: Path) -> None:
    proc = subprocess.Popen(cosim_cmd("evaluate", "--config", SMOKE, "--policy", "idle", "--episodes", "5000",
                                      "--workers", "2", "--out", "eval"),
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "TMPDIR": str(_tmpdir(tmp_path))}, preexec_fn=_default_sigint)
    _wait_for(proc, "1 of 5000 episodes")
    proc.send_signal(signal.SIGINT)
    out = _finish(proc)
    assert proc.returncode == 130 and "Traceback" not in out, out
    assert no_leftovers(tmp_path)


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
