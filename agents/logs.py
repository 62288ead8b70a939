"""Training logs: CSV files and TensorBoard scalars for updates and episodes, recent rates, headless log lines.

Contract: `RunLogger(out_dir, updates_done, episodes_done)` appends to `out_dir/updates.csv` and
`out_dir/episodes.csv` and writes TensorBoard event files under `out_dir/tb`, all against the update
counter. A resumed run first cuts both CSV files back to the checkpoint it resumes from (rows after
`updates_done` / `episodes_done`, written by a run that died between checkpoints, would otherwise appear
twice) and purges TensorBoard events after it. `update(row)` and `episode(row)` take flat dicts of numbers;
`recent` keeps the last 100 episodes for the progress bar's and the log line's crash / merge rates.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

from torch.utils.tensorboard import SummaryWriter

from cosim.files import AppendCsv, read_csv, write_csv


def cut_csv(path: Path, key: str, last: int) -> None:
    """Drop the rows of `path` whose `key` is above `last` (and half-written ones), atomically."""
    rows = read_csv(path)
    if rows and key in rows[0]:
        write_csv(path, [r for r in rows if r[key] and float(r[key]) <= last], list(rows[0]))


class RunLogger:
    def __init__(self, out_dir: Path, updates_done: int = 0, episodes_done: int = 0, window: int = 100) -> None:
        cut_csv(out_dir / "updates.csv", "update", updates_done)
        cut_csv(out_dir / "episodes.csv", "episode", episodes_done)
        self.updates = AppendCsv(out_dir / "updates.csv")
        self.episodes = AppendCsv(out_dir / "episodes.csv")
        self.tb = SummaryWriter(str(out_dir / "tb"), purge_step=updates_done + 1)
        self.recent: deque[dict[str, Any]] = deque(maxlen=window)

    def update(self, row: dict[str, Any]) -> None:
        self.updates.write(row)
        for key, value in row.items():
            if key not in ("update", "episodes", "samples"):
                self.tb.add_scalar(f"train/{key}", value, row["update"])

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
