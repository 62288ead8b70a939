"""scripts/probe_features.py: how much a network's features vary across real scenes, fresh and standardised."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.sumo

ROOT = Path(__file__).resolve().parents[1]


def test_standardising_the_input_spreads_a_fresh_encoders_features_across_scenes() -> None:
    done = subprocess.run([sys.executable, "scripts/probe_features.py", "--episodes", "2", "--init-seeds", "0"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(r"non-zero input values: [\d.]+%, of which per channel: road \d+%", done.stdout)
    spread = {norm: float(re.search(rf"obs_norm {norm}: dead [\d.]+%, spread / size ([\d.]+)", done.stdout)[1])
              for norm in ("false", "true")}
    # The default map is mostly empty road: without the standardisation a fresh encoder's features move across
    # scenes by about a third of their size, with it by about as much as their size (docs/results.md).
    assert spread["true"] > 2 * spread["false"]
