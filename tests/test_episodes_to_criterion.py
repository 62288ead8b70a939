"""scripts/episodes_to_criterion.py: which settings set a run apart in its table and plot, and a joined run's seeds."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

from cosim.config import DEFAULT_CONFIG, load_config

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("episodes_to_criterion", ROOT / "scripts" / "episodes_to_criterion.py")
criterion = sys.modules["episodes_to_criterion"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(criterion)


def test_how_long_a_run_ran_does_not_set_it_apart_from_its_seeds_but_what_it_learns_with_does() -> None:
    # A run resumed with --budget-min was drawn as a setting of its own, apart from the other seeds of its angle.
    default = load_config(DEFAULT_CONFIG)
    resumed = load_config(DEFAULT_CONFIG, ["train.budget_min=174", "train.episodes=30000", "train.seed=15"])
    assert criterion._differs(resumed, default) == ""
    tuned = load_config(DEFAULT_CONFIG, ["train.lr=0.0005", "reward.weights.collision=40"])
    assert criterion._differs(tuned, default) == "train.lr=0.0005 reward.weights.collision=40.0"


def test_a_joined_run_names_both_its_seeds(tmp_path: Path) -> None:
    cfg = load_config(DEFAULT_CONFIG, ["train.seed=1016"])
    assert criterion._seeds(tmp_path, cfg) == "1016"  # no net.json: one run
    (tmp_path / "net.json").write_text(json.dumps({"continues": {"train_seed": 16}}))
    assert criterion._seeds(tmp_path, cfg) == "16, then 1016"
