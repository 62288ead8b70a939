"""A full disk and a wrong model file through the `cosim` command: one line naming the file, exit 2, no
traceback, and nothing a user had lost (the last checkpoint stays whole and resumable). The full disk is a small
tmpfs the test mounts (root only: the tests run as root here and in CI), unmounted however the test ends."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from agents.checkpoint import (
    CHECKPOINT_NAME,
    POLICY_NAME,
    CheckpointError,
    load_policy,
    read_checkpoint,
    save_checkpoint,
)
from cosim.files import stale_temporaries

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SMOKE = str(Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml")


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory, cli_class: type) -> Path:
    """A finished one-update smoke run (real SUMO, two workers): its files, and their sizes for the tmpfs."""
    tmp = tmp_path_factory.mktemp("one_update")
    proc = cli_class(tmp).run("train", "--config", SMOKE, "--out", "run", "--set", "train.episodes=2")
    assert proc.returncode == 0, proc.stderr
    return tmp / "run"


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Callable[[int], Path]]:
    """`tmpfs(size)`: a tmpfs of `size` bytes mounted at tmp_path/disk."""
    where = tmp_path / "disk"
    mounted = False

    def mount(size: int) -> Path:
        nonlocal mounted
        where.mkdir()
        if shutil.which("mount") is None:
            pytest.skip("no mount command: a full disk is simulated with a small tmpfs")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                              capture_output=True, text=True)
        if done.returncode:
            pytest.skip(f"a full disk is simulated with a small tmpfs, which needs root: {done.stderr.strip()}")
        mounted = True
        return where

    yield mount
    if mounted:
        subprocess.run(["umount", "-l", str(where)], check=True)  # lazy: a straggling process cannot keep it


def fill(folder: Path, leave: int = 0) -> None:
    """Take every free byte of the file system that holds `folder` but `leave` pages."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(bytes(1 << 20))
        except OSError:  # ENOSPC: full
            pass
    os.truncate(filler, filler.stat().st_size - leave * os.sysconf("SC_PAGE_SIZE"))


@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_full_disk_during_training_is_one_line_and_keeps_the_last_checkpoint(
        smoke_run: Path, cli: Any, tmpfs: Callable[[int], Path], tmp_path: Path) -> None:
    pair = (smoke_run / CHECKPOINT_NAME).stat().st_size + (smoke_run / POLICY_NAME).stat().st_size
    # Room for the first checkpoint and the logs, not for the second beside it (written in full before the first
    # is replaced).
    disk = tmpfs(pair + pair // 2)
    run = disk / "run"
    args = ("train", "--config", SMOKE, "--out", "disk/run", *cli.settings("train.episodes=4",
                                                                           "train.checkpoint_every=1"))
    proc = cli.run(*args)
    cli.assert_clean_error(proc, "checkpoint disk/run/checkpoint.pt: cannot write it (No space left on device)")
    assert read_checkpoint(run / CHECKPOINT_NAME)["counters"]["updates"] == 1
    assert load_policy(run / POLICY_NAME)[1]["counters"]["updates"] == 1  # the pair of the same update
    assert not stale_temporaries(run, CHECKPOINT_NAME) + stale_temporaries(run, POLICY_NAME)
    assert cli.no_leftovers()


def test_a_checkpoint_that_does_not_fit_leaves_the_previous_pair_unchanged(tmpfs: Callable[[int], Path]) -> None:
    disk = tmpfs(9 << 19)  # 4.5 MiB

    def payload(updates: int, optimizer_mib: int) -> dict[str, Any]:  # policy.pt: 1 MiB; checkpoint.pt: more
        return {"spec": {}, "policy": {"nets": [{"w": torch.full((1 << 18,), float(updates))}],
                                       "optimizer": torch.zeros(optimizer_mib << 18)}, "counters": {"updates": updates}}

    path = disk / CHECKPOINT_NAME
    save_checkpoint(path, payload(1, optimizer_mib=1))  # 3 MiB of 4.5
    before = {p.name: p.read_bytes() for p in disk.iterdir()}
    # The new checkpoint.pt (2 MiB) does not fit; then one that fits, but its policy.pt beside it does not.
    with pytest.raises(CheckpointError, match=rf"checkpoint {path}: cannot write it \(No space left on device\); "
                                              r"the previous checkpoint \(checkpoint.pt, policy.pt\) is unchanged"):
        save_checkpoint(path, payload(2, optimizer_mib=1))
    with pytest.raises(CheckpointError, match=rf"checkpoint {disk / POLICY_NAME}: cannot write it"):
        save_checkpoint(path, payload(2, optimizer_mib=0))
    assert {p.name: p.read_bytes() for p in disk.iterdir()} == before  # and no temporary left


def test_evaluation_into_a_full_disk_names_the_file_not_its_temporary(
        smoke_run: Path, cli: Any, tmpfs: Callable[[int], Path]) -> None:
    disk = tmpfs(1 << 20)
    fill(disk, leave=1)  # a page for the folder's lock file: the evaluation's own files find no room
    proc = cli.run("evaluate", "--run", str(smoke_run), "--episodes", "1", "--no-plots", "--out", "disk/eval")
    cli.assert_clean_error(proc, f"cosim evaluate: {disk.resolve() / 'eval'}/")
    error = next(line for line in proc.stderr.splitlines() if " ERROR " in line)
    assert error.endswith(": No space left on device") and "/." not in error  # the file, not its temporary
    assert not [p for p in disk.rglob(".*") if p.is_file()]  # and no temporary left behind
    assert cli.no_leftovers()


@pytest.mark.parametrize(("command", "destination"), [
    (("build-net", "--out", "disk/net"), "disk/net/merge.nod.xml"),
    (("run-scenario", "--config", SMOKE, "--episodes", "1", "--policy", "idle", "--save-routes", "disk/routes"),
     "disk/routes/episode_"),
    (("compare", "ev", "--out", "disk/report"), "disk/report/"),
], ids=["build-net", "run-scenario", "compare"])
def test_a_full_disk_is_one_line_naming_the_destination_and_leaves_no_partial_file(
        command: tuple[str, ...], destination: str, cli: Any, tmpfs: Callable[[int], Path]) -> None:
    if command[0] == "compare":
        proc = cli.run("evaluate", "--config", SMOKE, "--policy", "idle", "--episodes", "1", "--trajectories", "0",
                       "--no-plots", "--out", "ev")
        assert proc.returncode == 0, proc.stderr
    disk = tmpfs(1 << 20)
    fill(disk)
    proc = cli.run(*command)
    cli.assert_clean_error(proc, destination)
    assert next(line for line in proc.stderr.splitlines() if " ERROR " in line).endswith(": No space left on device")
    assert [p.name for p in disk.rglob("*") if p.is_file()] == ["filler"]  # no empty file, no temporary
    assert cli.no_leftovers()


def test_sb3_evaluation_of_a_cosim_policy_file_is_one_line_before_anything_is_written(
        smoke_run: Path, cli: Any, tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3")
    proc = cli.run("evaluate", "--config", SMOKE, "--policy", "sb3", "--checkpoint", str(smoke_run / POLICY_NAME),
                   "--episodes", "1", "--out", "eval")
    cli.assert_clean_error(proc, f"--checkpoint {smoke_run / POLICY_NAME}: a PyTorch file, not a Stable-Baselines3 "
                                 "model; for cosim's own policy.pt or checkpoint.pt use --policy checkpoint")
    assert not (tmp_path / "eval").exists()
    assert cli.no_leftovers()
