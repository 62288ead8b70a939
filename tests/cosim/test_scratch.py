"""Temporary files named after their owner: what killed processes left is removed, nothing else."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import cosim.scratch
from cosim.scratch import remove_leftovers


def _owned(pid: int, start: int, rest: str = "") -> str:
    return f"cosim_{pid}-{start}{rest}"


def test_leftovers_of_dead_owners_are_removed_and_no_others(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tmp, shm = tmp_path / "tmp", tmp_path / "shm"
    tmp.mkdir(), shm.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    monkeypatch.setattr(cosim.scratch, "SHM", shm)
    gone = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.3)"])
    gone_start = int(Path(f"/proc/{gone.pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    gone.wait()
    me, my_start = os.getpid(), int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
    dead = [tmp / _owned(gone.pid, gone_start), shm / _owned(gone.pid, gone_start, "_obs_ab12"),
            tmp / _owned(me, my_start + 1),  # this pid, but another process's: pid reuse
            tmp / "pymp-dead1234"]  # multiprocessing's folder of a dead owner, named in its record
    live = [tmp / _owned(me, my_start), shm / _owned(me, my_start, "_obs_cd34")]
    others = [tmp / "pymp-other123", tmp / "cosim_obs_xyz", shm / "cosim_obs_xyz", tmp / "cosim_bench_q1",
              tmp / "cosim_12x-34", tmp / "ray"]
    for path in dead + live + others:
        if "_obs_" in path.name:
            path.write_bytes(b"0")
        else:
            path.mkdir()
            (path / "file").write_text("x")
    (dead[0] / "pymp").write_text(f"{dead[3]}\n")
    (dead[2] / "pymp").write_text(f"{others[0]}x\n")  # not a folder beside it: nothing else is touched
    assert sorted(remove_leftovers()) == sorted(dead[:3])
    assert not any(p.exists() for p in dead) and all(p.exists() for p in live + others)
