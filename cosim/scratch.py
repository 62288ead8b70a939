"""Temporary files that carry their owner, so that none outlives a run, whatever ended it.

Contract: each process that needs a temporary folder (an env, a pool of workers, a Ray actor) has one,
TMPDIR/cosim_<pid>-<start> (`run_folder()`; <start>: the process's start time from /proc, which tells it from a
later process with the same pid; `owner()` is that name), removed when the process exits; multiprocessing's own
folder (pymp-*, the forkserver's socket) is made in it, or, where the socket's path would be too long for
AF_UNIX, beside it and named in its `pymp` file. Shared arrays are /dev/shm/<owner>_*. `remove_leftovers()` removes
such folders and files whose owner no longer runs (a kill -9): never a live process's, nor names not of this form;
`run_folder` calls it at its first call in a process, and so does every pool start.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from multiprocessing import util as mp_util
from pathlib import Path

from cosim.files import scratch_write_text

log = logging.getLogger(__name__)

SHM = Path("/dev/shm")
_OWNED = re.compile(r"cosim_(\d+)-(\d+)(_|$)")  # cosim_<pid>-<start>, alone or followed by _...
# multiprocessing's folder and its forkserver's socket within it, as long as their random names make them
_SOCKET_TAIL = len("/pymp-12345678/listener-12345678")
_SOCKET_PATH_MAX = 107  # bytes of an AF_UNIX socket path on Linux (108 with the closing NUL)
_RUN_FOLDERS: dict[int, Path] = {}  # by pid: a forked child makes its own


def _started(pid: int) -> int | None:
    """When process `pid` started [clock ticks after boot]; None if no such process runs (a zombie is dead)."""
    try:
        state, *fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None if state in ("Z", "X") else int(fields[18])  # stat's 22nd field; its 2nd, the name, may hold ")"


def _runs(pid: int, start: int) -> bool:
    """Whether process `pid` runs and is the one that started at `start`, not a later one with its pid."""
    try:
        return _started(pid) == start
    except PermissionError:  # another user's, hidden by /proc's hidepid: leave its files alone
        return True


def owner() -> str:
    """This process's name for what it owns: cosim_<pid>-<start>."""
    return f"cosim_{os.getpid()}-{_started(os.getpid()) or 0}"


def remove_leftovers() -> list[Path]:
    """Remove the temporary folders and shared-memory files of processes that no longer run (module doc);
    returns what was removed. Without /proc (not Linux) a dead owner cannot be told from a live one: none is."""
    if _started(os.getpid()) is None:
        return []
    removed = []
    for base in dict.fromkeys((Path(tempfile.gettempdir()), SHM)):
        try:
            entries = list(base.iterdir())
        except OSError:  # no /dev/shm
            continue
        for path in entries:
            owner = _OWNED.match(path.name)
            if owner is None or _runs(int(owner[1]), int(owner[2])):
                continue
            try:
                if path.is_dir() and not path.is_symlink():
                    beside = path / "pymp"
                    if beside.is_file():  # multiprocessing's folder where it could not be nested (_nest_mp)
                        pymp = Path(beside.read_text().strip())
                        if pymp.name.startswith("pymp-") and pymp.parent == base:
                            shutil.rmtree(pymp, ignore_errors=True)
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
            except OSError:  # another user's (sticky /tmp, /dev/shm): theirs to remove
                continue
            removed.append(path)
    if removed:
        log.info("removed what stopped processes left: %s", ", ".join(str(p) for p in removed))
    return removed


def run_folder() -> Path:
    """This process's temporary folder, made at the first call and removed when the process exits;
    multiprocessing's folder is made in it (module doc)."""
    pid = os.getpid()
    if pid not in _RUN_FOLDERS:
        remove_leftovers()  # a run without a pool (one env in this process) cleans up after killed ones too
        folder = Path(tempfile.gettempdir()) / owner()
        folder.mkdir(exist_ok=True)
        # After multiprocessing removes its folder within (exitpriority -100): removed first, it would
        # print a traceback at exit.
        mp_util.Finalize(None, shutil.rmtree, args=(str(folder),), kwargs={"ignore_errors": True},
                         exitpriority=-200)
        _RUN_FOLDERS[pid] = folder
        _nest_mp(folder)
    return _RUN_FOLDERS[pid]


def _nest_mp(folder: Path) -> None:
    """Make multiprocessing's folder now, in `folder`: it makes it once per process, at its first need (the
    forkserver's start), in the temp dir of that moment. Where the socket's path would be too long (a deep
    TMPDIR), or where it exists already, it stays where it is and `folder/pymp` names it."""
    before = tempfile.tempdir
    if len(os.fsencode(folder)) + _SOCKET_TAIL <= _SOCKET_PATH_MAX:
        tempfile.tempdir = str(folder)
    try:
        pymp = Path(mp_util.get_temp_dir())
    finally:
        tempfile.tempdir = before
    if pymp.parent != folder:
        scratch_write_text(folder / "pymp", f"{pymp}\n")
