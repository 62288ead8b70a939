"""Nothing outlives a run, whatever ended it, and a hung worker is found in bounded time, through the `cosim`
command on real SUMO (configs/smoke.yaml): a `kill -9` leaves temporary files and shared memory named after
the killed process, which the next run removes, never a live process's; a stopped evaluation worker is
replaced within `evaluate.step_timeout`.

/dev/shm is the whole machine's: these tests look only at names holding the pids of processes they started."""

from __future__ import annotations

import csv
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SHM = Path("/dev/shm")


def _start_time(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])


def _owned_by(folder: Path, pid: int) -> list[Path]:
    return sorted(folder.glob(f"cosim_{pid}-*"))


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False


def _wait_until(condition: Any, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            pytest.fail(f"not within {timeout} s: {condition}")
        time.sleep(0.2)


def _evaluate_beside(cli: Any) -> None:
    """The next run: a two-worker evaluation (its pool's start removes what dead runs left)."""
    proc = cli.run("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "2", "--workers", "2",
                   "--out", "ev_next")
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_kill_9_of_training_then_resume_leaves_nothing(cli: Any) -> None:
    settings = cli.settings("train.workers=1", "train.episodes=2", "train.checkpoint_every=1")
    proc = cli.start("train", "--config", cli.SMOKE, "--out", "run", *settings)
    cli.wait_for(proc, "update 1,")
    _wait_until(lambda: (cli.folder / "run" / "checkpoint.pt").is_file())
    helpers = cli.children(proc.pid) + cli.workers(proc)  # forkserver, worker
    proc.kill()
    proc.wait()
    # What the kill left is named after the killed process ...
    assert _owned_by(cli.tmpdir, proc.pid) and len(_owned_by(SHM, proc.pid)) == 2
    assert any(p.name.startswith("pymp-") for p in cli.leftovers()) or any(
        p.name.startswith("pymp-") for d in _owned_by(cli.tmpdir, proc.pid) for p in d.iterdir())
    _wait_until(lambda: not any(_running(p) for p in helpers), 60)  # ... and no process of it lives on
    resumed = cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume", *settings)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert cli.no_leftovers(), cli.leftovers()
    assert not _owned_by(SHM, proc.pid)


@pytest.mark.slow  # 9-10 s; kill -9 of an evaluation stays in the default tier
def test_kill_9_of_a_sweep_then_the_next_run_leaves_nothing(cli: Any) -> None:
    proc = cli.start("sweep", "--config", cli.SMOKE, "--phi", "0", "--seeds", "0", "--budget-min", "0.05",
                     "--eval-episodes", "2", "--baselines", "idle", "--out", "sweep")
    try:
        _wait_until(lambda: proc.poll() is None and len(cli.workers(proc)) == 2)  # its evaluation's pool
    finally:
        proc.kill()
        proc.wait()
    assert any(p.name.startswith("pymp-") for p in cli.leftovers()) or any(
        p.name.startswith("pymp-") for d in _owned_by(cli.tmpdir, proc.pid) for p in d.iterdir())
    _evaluate_beside(cli)
    assert cli.no_leftovers(), cli.leftovers()
    assert not _owned_by(SHM, proc.pid)


def test_kill_9_of_a_one_process_evaluation_then_the_next_run_leaves_nothing(cli: Any) -> None:
    """No pool: the env runs in the command's own process, and its SUMO files are named after that process."""
    proc = cli.start("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "500", "--workers", "1",
                     "--out", "ev")
    _wait_until(lambda: any(list(d.glob("env_*")) for d in _owned_by(cli.tmpdir, proc.pid)))
    proc.kill()
    proc.wait()
    assert _owned_by(cli.tmpdir, proc.pid)
    again = cli.run("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "1", "--workers", "1",
                    "--out", "ev_next")
    assert again.returncode == 0, again.stdout + again.stderr
    assert cli.no_leftovers(), cli.leftovers()


def test_a_live_processs_files_and_other_programs_files_are_kept(cli: Any) -> None:
    # This test's process is the live owner; the same pid with another start time is a dead one (pid reuse).
    me, start = os.getpid(), _start_time(os.getpid())
    live = [cli.tmpdir / f"cosim_{me}-{start}", SHM / f"cosim_{me}-{start}_obs_test"]
    dead = [cli.tmpdir / f"cosim_{me}-{start + 1}", SHM / f"cosim_{me}-{start + 1}_obs_test"]
    others = [cli.tmpdir / "pymp-notours", cli.tmpdir / "cosim_obs_old", cli.tmpdir / "cosim_run"]
    try:
        for path in live + dead + others:
            if path.parent == SHM:
                path.write_bytes(b"\0" * 64)
            else:
                path.mkdir()
                (path / "inside").write_text("x")
        _evaluate_beside(cli)
        assert all(p.exists() for p in live + others) and not any(p.exists() for p in dead)
    finally:
        for path in live + dead:
            if path.parent == SHM:
                path.unlink(missing_ok=True)


@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_a_stopped_evaluation_worker_is_replaced_within_the_step_timeout(cli: Any) -> None:
    proc = cli.start("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "10", "--workers", "2",
                     "--out", "ev", *cli.settings("evaluate.step_timeout=5"))
    cli.wait_for(proc, "1 of 10 episodes")
    os.kill(cli.workers(proc)[0], signal.SIGSTOP)
    out = cli.finish(proc, timeout=240)  # far less than the fixed 600 s of before
    assert proc.returncode == 0, out
    assert "no answer in 5 s (evaluate.step_timeout)); replacing it (restart 1 of at most 3)" in out, out
    with open(cli.folder / "ev" / "episodes.csv") as f:
        assert sorted(int(r["seed"]) for r in csv.DictReader(f)) == list(range(10_000_000, 10_000_010))
    assert cli.no_leftovers(), cli.leftovers()
