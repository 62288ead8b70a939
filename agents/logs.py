"""Training logs: CSV files and TensorBoard scalars for updates and episodes, recent rates, headless log lines.

Contract: `RunLogger(out_dir, updates_done, episodes_done)` appends to `out_dir/updates.csv`,
`out_dir/episodes.csv` and `out_dir/validation.csv` (`validation(row)`) and writes TensorBoard event files under
`out_dir/tb`, all against the update counter. A resumed run first cuts the CSV files back to the checkpoint it
resumes from (`cut_logs`: rows after `updates_done` / `episodes_done`, written by a run that died between
checkpoints, would otherwise appear twice) and purges TensorBoard events after it. `update(row)` and
`episode(row)` take flat dicts of numbers; `recent` keeps the last 100 episodes for the progress bar's and the log
line's crash / merge rates.
`log_gaps(out_dir, updates_done, episodes_done, log_every)` checks the two files against a checkpoint's
counters before a resume: one line per file that lacks rows (deleted or cut), naming both counts; a
`CosimError` naming the file and row where two processes wrote into it (an episode twice, a repeated header).
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

from torch.utils.tensorboard import SummaryWriter

from cosim.errors import CosimError
from cosim.files import VALIDATION_LOG, AppendCsv, read_csv, write_csv


def cut_csv(path: Path, key: str, last: int) -> None:
    """Drop the rows of `path` whose `key` is above `last` (and half-written ones), atomically."""
    rows = read_csv(path, ints=(key,))
    if rows and key in rows[0]:
        write_csv(path, [r for r in rows if int(r[key]) <= last], list(rows[0]))


def cut_logs(out_dir: Path, updates_done: int, episodes_done: int) -> None:
    """Both CSV logs back to a checkpoint's counters."""
    cut_csv(out_dir / "updates.csv", "update", updates_done)
    cut_csv(out_dir / "episodes.csv", "episode", episodes_done)
    cut_csv(out_dir / VALIDATION_LOG, "update", updates_done)


def log_gaps(out_dir: Path, updates_done: int, episodes_done: int, log_every: int) -> list[str]:
    """What the CSV logs lack of the rows up to a checkpoint (`updates_done`, `episodes_done`; `log_every`: its
    updates.csv row interval), one line per file; `CosimError` for a log that two processes wrote."""
    gaps = []
    path = out_dir / "episodes.csv"
    seen: dict[int, int] = {}  # episode -> its row
    for i, row in enumerate(read_csv(path, ints=("episode",)), start=1):
        episode = int(row.get("episode", 0))
        if 0 < episode <= episodes_done and seen.setdefault(episode, i) != i:
            raise CosimError(f"{path}: rows {seen[episode]} and {i} are both episode {episode}: two processes wrote "
                             "this run at once (before cosim locked its folders), so its log and checkpoint cannot "
                             "be trusted; train again into a new --out")
    if len(seen) < episodes_done:
        held = f"holds {len(seen)} of the {episodes_done} episodes" if path.is_file() else \
            f"is missing; it held the {episodes_done} episodes"
        gaps.append(f"{path} {held} that the checkpoint counts (deleted or cut?): the run goes on, its log without "
                    "the missing rows")
    path = out_dir / "updates.csv"
    logged = [int(r["update"]) for r in read_csv(path, ints=("update",)) if "update" in r]
    last = max((u for u in logged if u <= updates_done), default=0)
    due = updates_done // log_every * log_every  # the checkpoint's update, as a row is written every log_every
    if last < due:
        held = f"ends at update {last}" if path.is_file() else "is missing"
        gaps.append(f"{path} {held}, but the checkpoint is at update {updates_done} (a row every {log_every}; "
                    "deleted or cut?): the run goes on, its log without the missing rows")
    return gaps


class RunLogger:
    def __init__(self, out_dir: Path, updates_done: int = 0, episodes_done: int = 0, window: int = 100) -> None:
        cut_logs(out_dir, updates_done, episodes_done)
        self.updates = AppendCsv(out_dir / "updates.csv")
        self.episodes = AppendCsv(out_dir / "episodes.csv")
        self.validations = AppendCsv(out_dir / VALIDATION_LOG)
        self.tb = SummaryWriter(str(out_dir / "tb"), purge_step=updates_done + 1)
        self.recent: deque[dict[str, Any]] = deque(maxlen=window)

    def update(self, row: dict[str, Any]) -> None:
        self.updates.write(row)
        for key, value in row.items():
            if key not in ("update", "episodes", "samples"):
                self.tb.add_scalar(f"train/{key}", value, row["update"])

    def validation(self, row: dict[str, Any]) -> None:
        """One validation's row (`agents.validation.summarize` and the counters), against the update counter."""
        self.validations.write(row)
        for key, value in row.items():
            if key not in ("update", "best"):
                self.tb.add_scalar(f"validation/{key}", value, row["update"])

    def episode(self, row: dict[str, Any]) -> None:
        self.recent.append(row)
        self.episodes.write(row)

    def episodes_to_tb(self, update: int, rows: list[dict[str, Any]]) -> None:
        """The mean of each episode column over this update's episodes."""
        for key in rows[0] if rows else ():
            if key != "episode":
                self.tb.add_scalar(f"episode/{key}", sum(float(r[key]) for r in rows) / len(rows), update)

    def rate(self, key: str) -> float:
        """Mean of `key` over the recent episodes (e.g. crashed -> crash rate), NaN before the first."""
        return sum(float(r[key]) for r in self.recent) / len(self.recent) if self.recent else float("nan")

    def close(self) -> None:
        self.tb.close()
