"""`cosim sweep` end to end on real SUMO (the smoke config, 2 angles, 1 seed, seconds of training) and its resume."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow  # 31 s; the default tier has the sweep's own checks (tests/faults: live folders, kill -9)
def test_tiny_sweep_runs_end_to_end_and_resumes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    out = tmp_path / "sweep"
    args = ["sweep", "--config", "configs/smoke.yaml", "--phi", "0", "0.7854", "--seeds", "0", "--budget-min", "0.05",
            "--eval-episodes", "4", "--eval-workers", "1", "--baselines", "idle", "courteous", "--out", str(out),
            # each run and baseline under traffic demand too: one seed of a 30 s window after 30 s
            "--demand", "configs/demand.yaml", "--set", "demand.warmup=30", "--set", "demand.window=30",
            "--set", "demand.seeds=1"]
    assert main(args) == 0
    report = (out / "report.md").read_text()
    assert "## Traffic flow under demand" in report and "flow_demand.png" in report
    assert "| throughput, total [veh/h] |" in report and (out / "flow_demand.png").stat().st_size > 1000
    for r in (out / "runs").iterdir():
        assert json.loads((r / "eval_demand" / "summary.json").read_text())["demand"]["level_of_service"]
    for needle in ("## The paper's claims", "(2) altruistic AVs", "rates_vs_phi.png", "merger_distance.png",
                   "flow_vs_phi.png", "training_curves.png", "phi=0.000 (egoistic)", "phi=0.785 (altruistic)", "idle"):
        assert needle in report, needle
    for figure in ("rates_vs_phi.png", "merger_distance.png", "flow_vs_phi.png", "training_curves.png"):
        assert (out / figure).stat().st_size > 1000
    data = json.loads((out / "sweep.json").read_text())
    assert data["episodes"] == {"idle": 4, "courteous": 4, "phi=0.000 (egoistic)": 4, "phi=0.785 (altruistic)": 4}
    holds = [(c["claim"][:3], c["holds"]) for c in data["claims"]]
    # Scripted was not evaluated (nothing to hold (1) against), 4 episodes are not the 300 that (2) needs, and
    # (4) is a figure, not a test.
    assert holds == [("(1)", False), ("(1)", False), ("(2)", False), ("(3)", holds[3][1]), ("(4)", None)]
    runs = sorted((out / "runs").iterdir())
    assert [r.name for r in runs] == ["phi_0.0000_seed_0", "phi_0.7854_seed_0"]
    for r in runs:  # trained within the budget, with its angle, evaluated on the evaluation seeds
        summary = json.loads((r / "eval" / "summary.json").read_text())
        assert summary["episodes"] == 4 and summary["first_seed"] == 10_000_000
    checkpoints = {r: (r / "checkpoint.pt").stat().st_mtime_ns for r in runs}

    # An interrupted sweep (here: one evaluation and the report gone) continues without training again.
    (runs[1] / "eval" / "summary.json").unlink()
    (out / "report.md").unlink()
    assert main(args) == 0
    assert (out / "report.md").is_file() and (runs[1] / "eval" / "summary.json").is_file()
    assert {r: (r / "checkpoint.pt").stat().st_mtime_ns for r in runs} == checkpoints


def test_claim_3_needs_a_significant_shift_downstream() -> None:
    from cosim.evaluation.report import shift_p_value

    rng = np.random.default_rng(0)
    stuck = 225 + rng.normal(0, 5, 150)  # egoistic: the merging vehicle waits at the lane's end
    assert shift_p_value(stuck, 225 + rng.normal(0, 5, 150)) > 0.05  # the same distribution: no claim
    assert shift_p_value(stuck, stuck + 0.4) > 0.05  # a sub-metre nudge of every sample is not a shift
    released = np.concatenate([225 + rng.normal(0, 5, 100), 450 + rng.normal(0, 20, 50)])  # a third got in
    assert shift_p_value(stuck, released) < 1e-3
    assert shift_p_value(released, stuck) > 0.5  # one-sided: downstream only
    assert shift_p_value(stuck, np.array([])) == 1.0
