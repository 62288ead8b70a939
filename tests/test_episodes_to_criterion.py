"""scripts/episodes_to_criterion.py: which settings set a run apart from the other seeds in its table and plot."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from cosim.config import DEFAULT_CONFIG, load_config
from cosim.evaluation.store import config_hash

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


def test_a_fine_tune_is_set_apart_by_where_it_started(tmp_path: Path) -> None:
    start = tmp_path / "start.pt"
    tuned = load_config(DEFAULT_CONFIG, [f"train.init_from={start}"])
    assert criterion._differs(tuned, load_config(DEFAULT_CONFIG)) == f"train.init_from={start}"
    # Started by `cosim train --init-from`: the config keeps the key null and the run's net.json names the policy.
    cli = load_config(DEFAULT_CONFIG)
    assert criterion._differs(cli, load_config(DEFAULT_CONFIG), str(start)) == f"train.init_from={start}"
    assert criterion._differs(tuned, load_config(DEFAULT_CONFIG), "elsewhere.pt") == f"train.init_from={start}"


def test_a_run_on_both_merging_drivers_is_set_apart_by_its_scenario() -> None:
    # The mixed-merger runs were listed as differing in "nothing" from the polite-only default.
    mixed = load_config(ROOT / "configs" / "mixed_merger.yaml")
    assert criterion._differs(mixed, load_config(DEFAULT_CONFIG)) == "scenario.merger_alt_share=0.5"


def test_a_run_with_another_observation_driver_or_social_reward_is_set_apart() -> None:
    # A run on a 16 m VelocityMap was listed as differing in "nothing" from the default's 32 m.
    default = load_config(DEFAULT_CONFIG)
    narrow = load_config(DEFAULT_CONFIG, ["observation.height_px=16", "observation.width_m=16", "av.shield=sumo",
                                          "reward.social=mean", "sim.seed=7", "sim.outputs=true"])
    assert (criterion._differs(narrow, default)
            == "reward.social=mean av.shield=sumo observation.height_px=16 observation.width_m=16.0")
    assert criterion._differs(load_config(ROOT / "configs" / "impatient.yaml"), default).startswith("merger.")


def test_runs_share_a_merge_reference_only_where_the_courteous_rules_episodes_would_be_the_same() -> None:
    # Runs under the safety layer were held to the courteous rule played without it, the first run's setting.
    default = load_config(DEFAULT_CONFIG)
    bookkeeping = load_config(DEFAULT_CONFIG, ["train.seed=7", "train.lr=0.0005", "reward.phi=0.7854",
                                               "observation.frames=3", "sim.seed=7", "sim.outputs=true"])
    assert criterion._setting(bookkeeping) == criterion._setting(default)
    for other in (load_config(DEFAULT_CONFIG, ["av.shield=sumo"]), load_config(ROOT / "configs" / "mixed_merger.yaml"),
                  load_config(DEFAULT_CONFIG, [f"net.file={ROOT / 'sumo_net' / 'merge' / 'merge.net.xml'}"])):
        assert criterion._setting(other) != criterion._setting(default)
    # ... and one evaluation of the rule, whose config is the setting's alone: a later table whose first run of the
    # setting was trained with another reward resumed it, and was refused as a different evaluation.
    shielded = load_config(DEFAULT_CONFIG, ["av.shield=sumo", "reward.phi=0.7854"])
    assert (config_hash(criterion._reference_config(bookkeeping, default).to_dict())
            == config_hash(criterion._reference_config(default, default).to_dict())
            != config_hash(criterion._reference_config(shielded, default).to_dict()))
    assert criterion._reference_config(shielded, default).av.shield == "sumo"
    rows = [{"run": "runs/a", "merge_reference": 98.0}, {"run": "runs/b", "merge_reference": 98.0}]
    assert criterion._references(rows) == "98.0%"
    rows.append({"run": "runs/shielded", "merge_reference": 96.5})
    assert criterion._references(rows) == "98.0% for a, b; 96.5% for shielded"
    # An egoistic run's criterion has no merge in it, so it has no reference and none is evaluated for it.
    egoistic = [{"run": "runs/phi0", "merge_reference": None}]
    assert criterion._references(rows[:2] + egoistic) == "98.0%"
    assert criterion._references(egoistic) == "no run at phi > 0 here"


def test_a_setting_is_summed_up_over_its_seeds_and_a_run_cut_short_unmet_counts_as_unmet() -> None:
    def run(met: float | None, last: float, differs: str = "") -> dict:
        return {"phi": 0.7854, "differs": differs, "met_at_episodes": met, "last_validated": last}

    rows = [run(1008, 2004), run(1500, 2004), run(None, 2004), run(1008, 1644), run(None, 1500),
            run(None, 2004, "train.lr=0.0005")]
    header, rule, default, lever = criterion._summary(rows)
    assert header.startswith("| phi |") and rule.startswith("|---")
    # By the longest budget, 2,004: three of five met (two at 1,008, one at 1,500), so half of the five by 1,500; the
    # run stopped at 1,500 unmet might have met it later, so the share is a lower bound.
    assert default == "| 0.7854 | nothing | 5 (1 stopped short unmet: at least) | 2,004 | 3 of 5: 60 [23, 88] | 1,500 |"
    assert lever == "| 0.7854 | train.lr=0.0005 | 1 | 2,004 | 0 of 1: 0 [0, 79] | not by 2,004 |"
    # By a shorter budget: a run met later counts as unmet, and no run stopped short of it.
    by_1008 = criterion._summary(rows, by=1008)[2]
    assert by_1008 == "| 0.7854 | nothing | 5 | 1,008 | 2 of 5: 40 [12, 77] | not by 1,008 |"


def test_egoistic_runs_are_tabled_without_an_evaluation_of_the_courteous_rule(tmp_path: Path, monkeypatch) -> None:
    # Their criterion has no merge in it; each table of them played the rule's 200 validation episodes for nothing.
    runs = [ROOT / "results" / "learner" / f"base_phi0_s{s}" for s in (1, 2)]
    monkeypatch.setattr(sys, "argv", ["episodes_to_criterion.py", *map(str, runs), "--out", str(tmp_path)])
    criterion.main()
    assert not list(tmp_path.glob("courteous_validation_*"))
    table = (tmp_path / "criterion.md").read_text()
    assert "(no run at phi > 0 here)" in table and "| 0.0000 | train.obs_norm=False" in table
