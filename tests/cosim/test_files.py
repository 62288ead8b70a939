"""Result files: atomic writes with the user's permissions, CSV logs that resume and never drop a value, damaged
CSV files named with their line, one writer per folder (a lock that a killed owner does not leave held)."""

from __future__ import annotations

import csv
import gzip
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cosim.errors import CosimError
from cosim.files import LOCK_NAME, AppendCsv, FolderLock, atomic_write_text, read_csv, stale_temporaries


def read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_append_csv_resumes_drops_a_partial_line_and_widens_for_new_columns(tmp_path: Path) -> None:
    path = tmp_path / "log.csv"
    AppendCsv(path).write({"a": 1, "b": 2})
    with path.open("a") as f:
        f.write("3,4")  # a write cut by a kill: no newline
    log = AppendCsv(path)
    log.write({"a": 5})  # a missing key is an empty cell
    log.write({"a": 6, "b": 7, "c": 8})  # a new key widens the header instead of being dropped
    assert read(path) == [{"a": "1", "b": "2", "c": ""}, {"a": "5", "b": "", "c": ""},
                          {"a": "6", "b": "7", "c": "8"}]


@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_atomic_files_get_the_users_permissions(tmp_path: Path, umask: int) -> None:
    old = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "summary.json", "{}")
        AppendCsv(tmp_path / "episodes.csv").write({"a": 1})
    finally:
        os.umask(old)
    for name in ("summary.json", "episodes.csv"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
    assert not stale_temporaries(tmp_path, "summary.json")


def test_read_csv_names_the_file_and_line_of_a_repeated_header_or_a_bad_integer(tmp_path: Path) -> None:
    path = tmp_path / "episodes.csv"
    path.write_text("seed,x\n1,a\n2,b\n3")  # the last line cut by a kill: dropped, as before
    assert [r["seed"] for r in read_csv(path, ints=("seed",))] == ["1", "2"]
    path.write_text("seed,x\n1,a\nseed,x\n1,a\n")  # two writers: each wrote its header
    with pytest.raises(CosimError, match=rf"{path}: line 3 repeats the header: two processes wrote"):
        read_csv(path)
    path.write_text("seed,x\n1,a\nx7,b\n")
    with pytest.raises(CosimError, match=rf"{path}: line 3: seed 'x7' is not an integer"):
        read_csv(path, ints=("seed",))
    assert len(read_csv(path)) == 2  # a column not checked stays as text


def test_read_csv_reads_a_gzipped_log_as_the_plain_one(tmp_path: Path) -> None:
    # A run kept in results/ has its episode log gzipped (scripts/snapshot_run.py); the plots read it unchanged.
    text = "episode,crashed\n1,1\n2,0\n3"
    (tmp_path / "episodes.csv").write_text(text)
    with gzip.open(tmp_path / "episodes.csv.gz", "wt") as f:
        f.write(text)
    assert read_csv(tmp_path / "episodes.csv.gz") == read_csv(tmp_path / "episodes.csv") == [
        {"episode": "1", "crashed": "1"}, {"episode": "2", "crashed": "0"}]


def test_a_folder_lock_has_one_holder_and_names_it(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    absent = FolderLock(folder, "cosim train")
    absent.acquire(create=False)  # no folder, nothing to guard: none is made
    assert not folder.exists() and absent.fd is None
    first = FolderLock(folder, "cosim train")
    first.acquire()
    assert (folder / LOCK_NAME).read_text() == f"pid {os.getpid()}, cosim train\n"
    with pytest.raises(CosimError, match=rf"{folder}: in use by another cosim process \(pid {os.getpid()}, cosim "
                                         r"train\); wait for it to finish or choose another --out"):
        FolderLock(folder, "cosim evaluate").acquire(create=False)
    first.release()
    assert not (folder / LOCK_NAME).exists()  # a finished owner leaves the folder as it was
    with FolderLock(folder, "cosim evaluate") as second:
        assert second.fd is not None
    assert not (folder / LOCK_NAME).exists()


HOLDER = """
import multiprocessing as mp, sys, time
from cosim.files import FolderLock
if __name__ == "__main__":
    FolderLock(sys.argv[1], "cosim train").acquire()
    worker = mp.get_context("forkserver").Process(target=time.sleep, args=(120,))
    worker.start()  # a rollout worker, started after the lock, as the trainer's are
    print(worker.pid, flush=True)
    time.sleep(120)
"""


def test_a_killed_owner_leaves_the_folder_free_though_its_workers_live_on(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    script = tmp_path / "holder.py"
    script.write_text(HOLDER)
    owner = subprocess.Popen([sys.executable, str(script), str(folder)], stdout=subprocess.PIPE, text=True)
    worker = 0
    try:
        assert owner.stdout is not None
        worker = int(owner.stdout.readline())
        with pytest.raises(CosimError, match=rf"in use by another cosim process \(pid {owner.pid}, cosim train\)"):
            FolderLock(folder, "cosim train").acquire()
        owner.kill()  # kill -9: no chance to release
        owner.wait(timeout=30)
        os.kill(worker, 0)  # the worker is still alive...
        with FolderLock(folder, "cosim train"):  # ...and holds no lock: the folder is free
            assert (folder / LOCK_NAME).read_text() == f"pid {os.getpid()}, cosim train\n"
    finally:
        owner.kill()
        if worker:
            os.kill(worker, signal.SIGKILL)
