"""Result files: atomic writes with the user's permissions, CSV logs that resume and never drop a value."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from cosim.files import AppendCsv, atomic_write_text, stale_temporaries


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
