"""The README's main job: `cosim train` on configs/smoke.yaml (real SUMO, worker processes), then
`cosim evaluate` of the trained run, through the CLI."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from cosim.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_smoke_train_then_evaluate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    run = tmp_path / "runs" / "smoke"
    assert main(["train", "--config", "configs/smoke.yaml", "--out", str(run)]) == 0
    assert (run / "checkpoint.pt").is_file() and (run / "config.yaml").is_file()
    with open(run / "episodes.csv") as f:
        episodes = list(csv.DictReader(f))
    assert len(episodes) >= 16
    assert main(["evaluate", "--run", str(run), "--episodes", "3"]) == 0
    summary = json.loads((run / "eval" / "summary.json").read_text())
    assert summary["episodes"] == 3 and summary["policy"] == "checkpoint"
    assert 0.0 <= summary["metrics"]["crash [%]"]["mean"] <= 100.0
    with open(run / "eval" / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    assert all(int(r["seed"]) >= 10_000_000 for r in rows)  # evaluation seeds never meet training seeds
