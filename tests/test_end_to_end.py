"""The README's main job, as the README writes it: `cosim train` on configs/smoke.yaml (real SUMO, worker
processes), then `cosim evaluate` of the trained run, through the CLI."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from agents.checkpoint import read_checkpoint
from cosim.cli import main
from cosim.config import EVAL_SEED_START, VALIDATION_SEED_START
from cosim.files import read_csv

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[1]


def readme_main_job() -> list[list[str]]:
    """The `cosim` commands of the README's main-job line, as argument lists."""
    line = next(ln for ln in (ROOT / "README.md").read_text().splitlines() if "&& cosim train" in ln)
    return [shlex.split(cmd)[1:] for cmd in re.split(r"\s*&&\s*", line) if cmd.strip().startswith("cosim ")]


def test_readme_main_job_trains_then_evaluates_the_trained_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    train_args, eval_args = readme_main_job()
    assert train_args[:3] == ["train", "--config", "configs/smoke.yaml"] and eval_args[0] == "evaluate"
    run = tmp_path / "runs" / "smoke"
    train_args[train_args.index("--out") + 1] = str(run)
    eval_args[eval_args.index("--run") + 1] = str(run)
    eval_args[eval_args.index("--episodes") + 1] = "3"  # the README's 10, cut for time
    monkeypatch.chdir(ROOT)

    assert main(train_args) == 0
    trained = read_csv(run / "episodes.csv")
    assert len(trained) == 16  # train.episodes of the smoke config, no more
    assert all(int(r["seed"]) < EVAL_SEED_START for r in trained)
    assert read_checkpoint(run / "checkpoint.pt")["counters"]["updates"] == 8
    assert (run / "policy.pt").is_file() and (run / "config.yaml").is_file()
    validations = read_csv(run / "validation.csv")  # the smoke config validates every 8 episodes
    assert [int(r["episodes"]) for r in validations] == [8, 16]
    best = [r for r in validations if r["best"] == "1"][-1]

    assert main(eval_args) == 0
    summary = json.loads((run / "eval" / "summary.json").read_text())
    # The run's best policy by validation is the one evaluated, and the report says so.
    assert summary["policy"] == "checkpoint" and summary["checkpoint"] == str((run / "best.pt").resolve())
    assert summary["trained_updates"] == int(best["update"])
    assert str((run / "best.pt").resolve()) in (run / "eval" / "report.md").read_text()
    evaluated = read_csv(run / "eval" / "episodes.csv")
    assert [int(r["seed"]) for r in evaluated] == [EVAL_SEED_START + i for i in range(3)]
    crashed = [r["crashed"] == "True" for r in evaluated]
    assert summary["episodes"] == 3
    assert summary["metrics"]["crash [%]"]["mean"] == pytest.approx(100 * sum(crashed) / 3)

    # Its figures on the seeds best.pt was chosen on are said not to be held out; on evaluation's own they are.
    assert "not held out" not in caplog.text
    assert main(["evaluate", "--run", str(run), "--episodes", "1", "--seed", str(VALIDATION_SEED_START),
                 "--no-plots", "--out", str(tmp_path / "on_validation")]) == 0
    assert (f"evaluation seeds {VALIDATION_SEED_START}..{VALIDATION_SEED_START}: 1 from 2,000,000,000, the "
            "validation seeds best.pt is chosen on; a trained policy's figures there are not held out") in caplog.text
