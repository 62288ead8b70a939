"""scripts/bench_frames.py: the network with each frame through its first two layers once, timed against it whole."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_it_times_acting_and_an_update_pass_both_ways_and_counts_the_distinct_frames() -> None:
    done = subprocess.run([sys.executable, "scripts/bench_frames.py", "--acting", "3", "--update", "10", "--run",
                           "4", "--reps", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    acting, update = done.stdout.strip().splitlines()
    assert re.fullmatch(r"acting, 3 observations \(5, 4, 32, 128\), 1 thread: whole [\d.]+ ms, through FrameMemory "
                        r"[\d.]+ ms: [\d.]+", acting)
    # Runs of 4 decisions of 5 frames: 3 runs, 8 frames each, of which the 10 samples use 8 + 8 + 6.
    assert re.fullmatch(r"update pass, 10 samples from 22 distinct frames \(2\.20 per sample\), \d+ threads: whole "
                        r"[\d.]+ ms per sample, from distinct frames [\d.]+: [\d.]+", update)
