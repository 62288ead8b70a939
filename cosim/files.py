"""Writing results so that a failed or interrupted run loses nothing a user already has.

Contract: `atomic_path(path)` yields a temporary path beside `path` that replaces it only once the body
succeeded (a reader sees the old file or the new one, never half of one), with the permissions any new file
of the user gets (the umask's, not mkstemp's private 0600); `atomic_write_text` is its text shortcut;
`stale_temporaries(folder, name)` lists what an interrupted atomic write of `name` left behind. `AppendCsv`
appends rows flushed one by one, keeps an existing file's header (a row with a new key widens it; a missing
key is an empty cell), and drops a half-written last line left by an interrupted run, so runs can resume.
The project's CSV tables go through here only: `read_csv(path)` (complete rows as dicts of strings; none for a
missing file), `write_csv(path, rows, fields)` (atomic), `AppendCsv`, and `column(rows, name)`, a column as
floats (booleans as 0/1, empty or unparsable cells as NaN).
"""

from __future__ import annotations

import csv
import io
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb") as f:  # on disk before it takes the old file's place
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def stale_temporaries(folder: Path, name: str) -> list[Path]:
    """Temporary files of `atomic_path(folder / name)` left by a write that was killed."""
    stem, suffix = Path(name).stem, Path(name).suffix
    return sorted(p for p in folder.glob(f".{stem}.*{suffix}") if p.is_file())


def read_csv(path: Path) -> list[dict[str, str]]:
    """The complete rows of a CSV file with a header; a half-written last row (an interrupted run) is dropped."""
    if not Path(path).is_file():
        return []
    with Path(path).open(newline="") as f:
        return [r for r in csv.DictReader(f) if None not in r.values() and None not in r]


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], fields: Sequence[str] | None = None) -> None:
    """Write `rows` under the header `fields` (default: the keys in order of first appearance), atomically."""
    fields = list(fields) if fields is not None else list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(Path(path), buf.getvalue())


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
        with self.path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields)
            if new:
                writer.writeheader()
            writer.writerow(dict(row))
