"""scripts/heldout.py: a trained run and the `courteous` rule on held-out episodes with each merging vehicle, the
run's best policy or (`--last`) its final one."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from agents.train import train
from cosim.config import load_config

pytestmark = pytest.mark.sumo

ROOT = Path(__file__).resolve().parents[1]


def _heldout(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "scripts/heldout.py", *args, "--workers", "1"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow  # 11 s
def test_a_run_meets_each_merging_vehicle_on_held_out_episodes(tmp_path: Path) -> None:
    run = tmp_path / "alt_s0"
    train(load_config("configs/smoke.yaml", ["train.episodes=4", "train.eval_every=4", "train.eval_episodes=2",
                                             "train.feature_dim=16", "train.head_hidden=16", "train.workers=1",
                                             "train.precision=float32"]), run, progress=False)
    done = _heldout(str(run), "--episodes", "3", "--impatient-episodes", "2", "--out", str(tmp_path / "best"))
    assert done.returncode == 0, done.stderr[-2000:]
    text = (tmp_path / "best" / "heldout.md").read_text()
    assert "each run plays its best.pt" in text
    polite, impatient = text.split("## Polite merging vehicle, shield none")[1].split(
        "## Impatient merging vehicle, shield none")
    assert "| courteous (n=3) | alt_s0 (n=3) |" in polite and "| courteous (n=2) | alt_s0 (n=2) |" in impatient
    # The impatient part plays configs/impatient.yaml's merging driver, and only that changed.
    played = yaml.safe_load((tmp_path / "best" / "impatient_none" / "alt_s0" / "config.yaml").read_text())
    assert played["merger"] == load_config("configs/impatient.yaml").merger.model_dump(mode="json")
    assert json.loads((tmp_path / "best" / "heldout.json").read_text())["played"][str(run)].endswith("best.pt")

    last = _heldout(str(run), "--last", "--episodes", "2", "--impatient-episodes", "0", "--out", str(tmp_path / "last"))
    assert last.returncode == 0, last.stderr[-2000:]
    assert "each run plays its policy.pt" in (tmp_path / "last" / "heldout.md").read_text()
    assert not (tmp_path / "last" / "impatient_none").exists()


def test_a_folder_that_is_no_run_is_one_line(tmp_path: Path) -> None:
    done = _heldout(str(tmp_path), "--out", str(tmp_path / "out"))
    assert done.returncode != 0 and "not a training run folder (no config.yaml)" in done.stderr
    assert "Traceback" not in done.stderr
