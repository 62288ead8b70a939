"""Training logs: CSV files and TensorBoard scalars for updates and episodes, and recent-episode rates.

Contract: `RunLogger(out_dir)` appends to `out_dir/updates.csv` and `out_dir/episodes.csv` (a header is
written when a file is new, so a resumed run continues the same files) and writes TensorBoard event files
under `out_dir/tb`. `update(step, row)` and `episode(step, row)` take flat dicts of numbers; rows of one
file must keep the same keys (episode rows take the union of reward terms seen first, missing ones are
left empty). `recent` keeps the last 100 episodes for the progress bar's crash / merge rates.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

from torch.utils.tensorboard import SummaryWriter

from cosim.files import AppendCsv


class RunLogger:
    def __init__(self, out_dir: Path, window: int = 100) -> None:
        self.updates = AppendCsv(out_dir / "updates.csv")
        self.episodes = AppendCsv(out_dir / "episodes.csv")
        self.tb = SummaryWriter(str(out_dir / "tb"))
        self.recent: deque[dict[str, Any]] = deque(maxlen=window)

    def update(self, step: int, row: dict[str, Any]) -> None:
        self.updates.write(row)
        for key, value in row.items():
            if key not in ("update", "episodes", "samples"):
                self.tb.add_scalar(f"train/{key}", value, step)

    def episode(self, step: int, row: dict[str, Any]) -> None:
        self.recent.append(row)
        self.episodes.write(row)
        for key, value in row.items():
            if key != "episode":
                self.tb.add_scalar(f"episode/{key}", value, step)

    def rate(self, key: str) -> float:
        """Mean of `key` over the recent episodes (e.g. crashed -> crash rate), NaN before the first."""
        return sum(float(r[key]) for r in self.recent) / len(self.recent) if self.recent else float("nan")

    def close(self) -> None:
        self.tb.close()
