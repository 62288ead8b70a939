"""Writing results so that a failed or interrupted run loses nothing a user already has.

Contract: `atomic_path(path)` yields a temporary path beside `path` that replaces it only once the body
succeeded (a reader sees the old file or the new one, never half of one), with the permissions any new file
of the user gets (the umask's, not mkstemp's private 0600); a failed write (a full disk) removes the temporary file
and raises an OSError naming `path`, not the temporary; `atomic_write_text` and `atomic_copy` are its shortcuts;
`scratch_write_text` writes a file of a temporary folder, naming it on failure and leaving nothing partial;
`write_json(path, data)` writes strict JSON atomically (NaN as null, `strict_json`).
`stale_temporaries(folder, name)` lists what an interrupted atomic write of `name` left behind. `AppendCsv`
appends rows flushed one by one, keeps an existing file's header (a row with a new key widens it; a missing
key is an empty cell), and drops a half-written last line left by an interrupted run, so runs can resume.
The project's CSV tables go through here only: `read_csv(path, ints)` (complete rows as dicts of strings, gzipped
files too; none for a missing file; a `CosimError` naming the file and line for a repeated header, which two
processes writing one file leave, or a cell of an `ints` column that is no integer), `write_csv(path, rows, fields)`
(atomic), `AppendCsv`, and `column(rows, name)`, a column as floats (booleans as 0/1, empty or unparsable cells as NaN).
`FolderLock(folder, command)`: one writer per results folder (a lock the kernel drops when its owner dies).
`FolderState.capture(folder)` / `restore()`: a results folder put back as a command found it.
`file_sha256(path)`: a file's identity by content (a net's, a policy's), wherever it lies.
"""

from __future__ import annotations

import csv
import fcntl
import gzip
import hashlib
import io
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from cosim.errors import CosimError

LOCK_NAME = ".cosim.lock"
# A training run's validation curve: agents.logs writes it, the learning plots read it (cosim never imports agents).
VALIDATION_LOG = "validation.csv"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:  # it names the temporary it tried
        raise _as_write_of(exc, exc.filename, path) from None
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb") as f:  # on disk before it takes the old file's place
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _as_write_of(exc, tmp, path) from None
        raise


def _as_write_of(exc: OSError, tmp: str | None, path: Path) -> OSError:
    """A failed write of the temporary file `tmp` (a full disk: a write's error names no file) as one of `path`:
    the file the user knows. An error about another file stays as it is."""
    if exc.filename not in (None, tmp):
        return exc
    return OSError(exc.errno, exc.strerror or str(exc), str(path))


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_copy(source: Path, path: Path) -> None:
    """A copy of a small file `source` as `path`, written as `atomic_path` writes."""
    # Read whole, not shutil.copyfile: its sendfile path blames a full disk on the source file.
    data = Path(source).read_bytes()
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def scratch_write_text(path: Path, text: str) -> None:
    """`path.write_text(text)` for a file of a run's own temporary folder (no fsync: it is read once, at once);
    a failed write removes what it wrote and raises an OSError naming `path`."""
    try:
        path.write_text(text)
    except OSError as exc:
        path.unlink(missing_ok=True)
        raise _as_write_of(exc, str(path), path) from None


def strict_json(data: Any) -> Any:
    """`data` with every non-finite float (NaN: an interval of one value, a metric no episode had) as None, so that
    it is written as null: strict JSON parsers refuse the bare NaN Python's json writes by default."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, Mapping):
        return {k: strict_json(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [strict_json(v) for v in data]
    return data


def write_json(path: Path, data: Any) -> None:
    """`data` as strict JSON (`strict_json`), indented, written atomically."""
    atomic_write_text(path, json.dumps(strict_json(data), indent=2, allow_nan=False) + "\n")


def stale_temporaries(folder: Path, name: str) -> list[Path]:
    """Temporary files of `atomic_path(folder / name)` left by a write that was killed."""
    stem, suffix = Path(name).stem, Path(name).suffix
    return sorted(p for p in folder.glob(f".{stem}.*{suffix}") if p.is_file())


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes, read in blocks: what identifies a net or a policy file wherever it lies (two runs
    on nets with the same hash ran on the same net)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_csv(path: Path, ints: Sequence[str] = ()) -> list[dict[str, str]]:
    """The complete rows of a CSV file with a header (gzipped where its name ends in .gz, as the training logs
    kept in results/ are); a half-written last row (an interrupted run) is dropped. `CosimError` naming the file
    and the line for a line that repeats the header, or a cell of a column in `ints` that is no integer: damage
    that rerunning into the folder cannot repair."""
    path = Path(path)
    if not path.is_file():
        return []
    rows = []
    with (gzip.open(path, "rt", newline="") if path.suffix == ".gz" else path.open(newline="")) as f:
        reader = csv.DictReader(f)
        for row in reader:
            if None in row.values() or None in row:
                continue
            if list(row.values()) == reader.fieldnames:
                raise CosimError(f"{path}: line {reader.line_num} repeats the header: two processes wrote this file "
                                 "at once (before cosim locked its folders), so its rows cannot be trusted; move "
                                 "the folder away and run the command again into a new one")
            for key in ints:
                if key in row and not _is_int(row[key]):
                    raise CosimError(f"{path}: line {reader.line_num}: {key} {row[key]!r} is not an integer; the "
                                     "file is damaged: move the folder away and run the command again into a new one")
            rows.append(row)
    return rows


def _is_int(text: str) -> bool:
    try:
        int(text)
    except ValueError:
        return False
    return True


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], fields: Sequence[str] | None = None) -> None:
    """Write `rows` under the header `fields` (default: the keys in order of first appearance), atomically;
    gzipped where the name ends in .gz, as `read_csv` reads it."""
    fields = list(fields) if fields is not None else list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    path = Path(path)
    if path.suffix != ".gz":
        atomic_write_text(path, buf.getvalue())
        return
    with atomic_path(path) as tmp:
        tmp.write_bytes(gzip.compress(buf.getvalue().encode("utf-8"), mtime=0))  # the same rows, the same bytes


def cell_float(value: Any) -> float:
    """A CSV cell or a Python value as a float: booleans as 0/1, empty or unparsable as NaN."""
    if isinstance(value, bool | np.bool_):
        return float(value)
    if isinstance(value, str):
        v = value.strip().lower()
        if v in ("true", "false"):
            return float(v == "true")
        try:
            return float(v) if v else float("nan")
        except ValueError:
            return float("nan")
    try:
        return float("nan") if value is None else float(value)
    except (TypeError, ValueError):
        return float("nan")


def column(rows: Sequence[Mapping[str, Any]], name: str) -> np.ndarray:
    """(len(rows),) float64: one column, NaN where a row has no usable value."""
    return np.array([cell_float(r.get(name)) for r in rows], dtype=np.float64)


class AppendCsv:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.fields: list[str] | None = None
        if path.is_file() and path.stat().st_size:
            data = path.read_bytes()
            if not data.endswith(b"\n"):  # an interrupted write: drop the partial last line
                path.write_bytes(data[: data.rfind(b"\n") + 1])
            with path.open(newline="") as f:
                self.fields = next(csv.reader(f), None)

    def write(self, row: Mapping[str, Any]) -> None:
        new = self.fields is None
        if new:
            self.fields = list(row)
        extra = [k for k in row if k not in self.fields]
        if extra:  # a new column widens the file (earlier rows get empty cells): no value is dropped
            self.fields += extra
            write_csv(self.path, read_csv(self.path), self.fields)
        try:
            with self.path.open("a", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=self.fields)
                if new:
                    writer.writeheader()
                writer.writerow(dict(row))
        except OSError as exc:  # a full disk: the write's error names no file
            raise _as_write_of(exc, None, self.path) from None


class FolderLock:
    """One writer per results folder: `acquire()` takes an exclusive `flock` on `folder/.cosim.lock`, which
    records the owner's pid and command for the one line a second process gets (a `CosimError`); `release()`
    removes the file and frees the folder. The kernel drops the lock when its owner dies, so a killed run leaves
    nothing stuck; the descriptor is close-on-exec and the worker processes are exec'd (forkserver, spawn, Ray),
    so none of them holds the lock past its owner (a plain `os.fork` child would: it shares the descriptor)."""

    def __init__(self, folder: Path, command: str) -> None:
        self.folder, self.command = Path(folder), command
        self.path = self.folder / LOCK_NAME
        self.fd: int | None = None

    def acquire(self, create: bool = True) -> None:
        """Hold the lock (again: a no-op); `create=False`: only if the folder exists, so that a command refused
        for its input leaves no folder behind, while one into a live folder is refused before it reads a file."""
        if self.fd is not None or not (create or self.folder.is_dir()):
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = os.read(fd, 512).decode(errors="replace").strip() or "pid unknown"
                os.close(fd)
                raise CosimError(f"{self.folder}: in use by another cosim process ({owner}); wait for it to finish "
                                 "or choose another --out") from None
            if _same_file(fd, self.path):
                break
            os.close(fd)  # its owner removed it between our open and our lock: lock the one there now
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}, {self.command}\n".encode())
        except OSError as exc:  # a full disk: the write's error names no file
            os.close(fd)
            raise _as_write_of(exc, None, self.path) from None
        self.fd = fd

    def release(self) -> None:
        if self.fd is None:
            return
        self.path.unlink(missing_ok=True)  # before unlocking: whoever opened it meanwhile sees it gone and retries
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    return (st.st_dev, st.st_ino) == (os.fstat(fd).st_dev, os.fstat(fd).st_ino)


@dataclass
class FolderState:
    """A results folder as a command found it, to put back when the command fails on a fault of its input
    before it made anything worth keeping (a training run's checkpoint, an evaluation's episode): nothing that
    it made is left to block its rerun, nothing of the user's is lost."""

    folder: Path
    existed: bool
    files: frozenset[Path]  # every file below the folder
    texts: dict[str, bytes]  # the files a run rewrites or appends to, by name, as they were

    KEPT: ClassVar[tuple[str, ...]] = ("config.yaml", "config_changes.yaml", "updates.csv", "episodes.csv",
                                       "evaluation.json")

    @classmethod
    def capture(cls, folder: Path) -> FolderState:
        files = frozenset(p for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else frozenset()
        texts = {name: (folder / name).read_bytes() for name in cls.KEPT if (folder / name).is_file()}
        return cls(folder, folder.is_dir(), files, texts)

    def restore(self) -> None:
        if not self.existed:
            shutil.rmtree(self.folder, ignore_errors=True)
            return
        for path in sorted(self.folder.rglob("*"), reverse=True):  # files before the folders that hold them
            if path.is_file() and path not in self.files and path.name != LOCK_NAME:
                path.unlink()
            elif path.is_dir() and not any(path.iterdir()) and not any(f.is_relative_to(path) for f in self.files):
                path.rmdir()
        for name, text in self.texts.items():
            atomic_write_text(self.folder / name, text.decode("utf-8"))
