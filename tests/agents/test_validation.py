"""Validation during training on real SUMO: greedy episodes on the validation seeds, the same rows `cosim evaluate`
gives, best.pt kept by the stated rule, and a resume that continues the curve."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from agents.checkpoint import BEST_NAME, POLICY_NAME, TrainedPolicy, find_checkpoint, load_policy
from agents.train import train
from agents.validation import (
    FIGURES,
    MOVING_SHARE,
    better,
    constant_action,
    describe,
    meets_criterion,
    moving_threshold,
    summarize,
    validation_seeds,
)
from cosim.config import EVAL_SEED_START, SEED_MAX, VALIDATION_SEED_START, load_config
from cosim.evaluation.runner import evaluate
from cosim.files import read_csv

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[2]
EPISODES = 4  # per validation


def smoke(**train_keys: object):
    keys = {"eval_every": 4, "eval_episodes": EPISODES, "episodes": 8, "checkpoint_every": 100,
            "precision": "float32", **train_keys}
    return load_config(ROOT / "configs" / "smoke.yaml", [f"train.{k}={v}" for k, v in keys.items()])


def test_validation_seeds_are_neither_training_nor_evaluation_seeds() -> None:
    seeds = validation_seeds(200)
    assert seeds == list(range(VALIDATION_SEED_START, VALIDATION_SEED_START + 200))
    # evaluation's seeds run from EVAL_SEED_START; a million evaluation episodes stay clear of validation's
    assert min(seeds) > EVAL_SEED_START + 1_000_000 and max(seeds) <= SEED_MAX


def test_best_is_the_lowest_crash_upper_bound_then_the_highest_return() -> None:
    first = {"crash_high": 10.0, "return": 5.0}
    assert better(first, None)
    assert better({"crash_high": 8.0, "return": 1.0}, first)  # fewer crashes beat a higher return
    assert not better({"crash_high": 12.0, "return": 50.0}, first)
    assert better({"crash_high": 10.0, "return": 6.0}, first) and not better({"crash_high": 10.0, "return": 4.0}, first)
    runs = {"collisions_high": 0.0, "return": 5.0}  # under demand: collisions per window, then the return
    assert better({"collisions_high": 0.0, "return": 6.0}, runs) and not better({"collisions_high": 1.0,
                                                                                  "return": 50.0}, runs)


def test_under_demand_best_asks_first_that_traffic_keeps_moving() -> None:
    moving = moving_threshold(4000.0)
    assert moving == MOVING_SHARE * 4000.0
    still = {"collisions_high": 0.0, "throughput": 950.0, "return": 90.0}  # the mainline held still, no collision
    driving = {"collisions_high": 20.0, "throughput": 3900.0, "return": 30.0}
    assert better(driving, still, moving) and not better(still, driving, moving)
    # both moving, or both not: collisions, then the return, as without the threshold
    assert better({"collisions_high": 5.0, "throughput": 3100.0, "return": 1.0}, driving, moving)
    assert not better({"collisions_high": 0.0, "throughput": 1200.0, "return": 50.0}, driving, moving)
    assert better({"collisions_high": 0.0, "throughput": 1200.0, "return": 95.0}, still, moving)
    assert better(still, driving)  # without a threshold (episodes, or a caller that has none): collisions first


def test_the_criterion_asks_safety_of_every_policy_and_merges_of_altruistic_ones() -> None:
    safe = {"crash": 1.5, "crash_high": 4.3, "merge": 90.0}  # 3 crashes in 200 episodes
    assert meets_criterion(safe, 0.0, 97.5) and meets_criterion(safe, 0.0, None)  # egoistic: the merge does not count
    with pytest.raises(ValueError, match="merge reference"):
        meets_criterion(safe, 0.7854, None)
    assert meets_criterion(safe, 0.7854, 95.0) and not meets_criterion(safe, 0.7854, 97.5)  # within 5 points?
    assert not meets_criterion({**safe, "crash_high": 5.03}, 0.0, 0.0)  # 4 of 200: 2.0%, but the bound is 5.03%
    assert not meets_criterion({**safe, "crash": 2.5}, 0.0, 0.0)


def test_summary_gives_cosim_evaluates_intervals() -> None:
    rows = [{"crashed": c, "merged": m, "conflicts": k, "merger_distance": 100.0 + k, "av_return": r}
            for c, m, k, r in [(True, False, 2, -3.0), (False, True, 0, 4.0), (False, True, 1, 5.0),
                               (False, False, 0, 6.0)]]
    fig = summarize(rows)
    assert fig["episodes_validated"] == 4
    assert fig["crash"] == pytest.approx(25.0) and fig["merge"] == pytest.approx(50.0)
    assert 0 < fig["crash_low"] < 25.0 < fig["crash_high"] < 100  # Wilson: inside [0, 100] even at n = 4
    assert fig["conflicts"] == pytest.approx(0.75) and fig["conflicts_low"] == 0.0  # a count's interval cut at 0
    assert fig["return"] == pytest.approx(3.0) and fig["return_low"] < 0  # a return may be negative: not cut


def test_a_mix_of_merging_drivers_is_also_read_per_driver() -> None:
    """Pooled, 2 crashes in 6; the impatient merging driver's episodes hold both."""
    rows = [{"crashed": c, "merged": m, "conflicts": 0, "merger_distance": 100.0, "av_return": 1.0, "merger_alt": a}
            for c, m, a in [(True, False, True), (True, True, True), (False, True, True), (False, True, False),
                            (False, True, False), (False, False, False)]]
    fig = summarize(rows)
    assert fig["crash"] == pytest.approx(100 / 3)
    assert fig["crash_merger_alt"] == pytest.approx(200 / 3) and fig["crash_merger"] == 0.0
    assert fig["merge_merger_alt"] == pytest.approx(200 / 3) and fig["merge_merger"] == pytest.approx(200 / 3)
    assert 0 < fig["crash_merger_alt_low"] < fig["crash_merger_alt"] < fig["crash_merger_alt_high"] <= 100
    assert "merger_alt: crash 66.7%" in describe(fig) and "merger: crash 0.0%" in describe(fig)
    # One driver only (every config but a mixed one): the pooled figures alone.
    assert not any("merger" in k and "distance" not in k for k in summarize(rows[3:]))


def test_validation_keeps_the_best_and_matches_an_evaluation_on_the_same_seeds(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(smoke(), run, progress=False)
    rows = read_csv(run / "validation.csv")
    assert [int(r["episodes"]) for r in rows] == [4, 8]
    assert all(float(r["episodes_validated"]) == EPISODES for r in rows)
    best = [r for r in rows if r["best"] == "1"][-1]
    _, meta = load_policy(run / BEST_NAME)
    assert meta["validation"]["update"] == int(best["update"]) == meta["counters"]["updates"]
    assert find_checkpoint(run, None) == (run / BEST_NAME).resolve()
    assert find_checkpoint(run, None, last=True) == (run / POLICY_NAME).resolve()
    assert (run / "tb").is_dir()
    shares = [float(best[f"greedy_action_{k}"]) for k in range(5)]
    assert sum(shares) == pytest.approx(100.0) and min(shares) >= 0.0

    # best.pt played by `cosim evaluate` on the validation seeds: the validation's figures, episode for episode.
    summary = evaluate(smoke(), TrainedPolicy(str(run / BEST_NAME)), tmp_path / "eval", episodes=EPISODES,
                       seed=VALIDATION_SEED_START, trajectories=0, plots=False)
    m = summary["metrics"]
    for name, label in FIGURES.items():
        assert float(best[name]) == pytest.approx(m[label]["mean"]), name


def test_a_resumed_run_continues_the_validation_curve_and_its_best(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(smoke(), run, progress=False)
    before = read_csv(run / "validation.csv")
    best_before = load_policy(run / BEST_NAME)[1]["validation"]
    train(smoke(episodes=12), run, resume=True, progress=False)
    rows = read_csv(run / "validation.csv")
    assert rows[:2] == before and [int(r["episodes"]) for r in rows] == [4, 8, 12]
    best_after = load_policy(run / BEST_NAME)[1]["validation"]
    # the third validation replaced best.pt only if it beat the best of the first two by the rule
    third = {k: float(v) for k, v in rows[2].items()}
    assert (rows[2]["best"] == "1") == better(third, best_before)
    if rows[2]["best"] == "1":
        assert best_after["episodes"] == 12
    else:
        assert best_after == best_before


def test_validation_does_not_change_what_the_run_learns(tmp_path: Path) -> None:
    """Greedy episodes draw nothing from the trainer's random streams: the same run with and without validation
    ends with the same weights (float32, bit for bit)."""
    with_it, without = tmp_path / "with", tmp_path / "without"
    train(smoke(), with_it, progress=False)
    train(smoke(eval_every=0), without, progress=False)
    assert not (without / "validation.csv").exists() and not (without / BEST_NAME).exists()
    a, b = (load_policy(run / POLICY_NAME)[0]["av_0"].state_dict() for run in (with_it, without))
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_validation_under_demand_gives_the_windows_flow_over_the_runs() -> None:
    rows = [{"throughput_total_vph": q, "collisions_window": k, "merge_rate_pct": m, "delay_mean_s": d,
             "av_return": r} for q, k, m, d, r in [(3000.0, 0, 100.0, 40.0, 20.0), (3200.0, 2, 90.0, 60.0, 10.0),
                                                    (3100.0, 1, 95.0, 50.0, 15.0)]]
    fig = summarize(rows)
    assert fig["throughput"] == pytest.approx(3100.0) and fig["throughput_low"] < 3100.0 < fig["throughput_high"]
    assert fig["collisions"] == pytest.approx(1.0) and fig["collisions_low"] == 0.0  # a count's interval cut at 0
    assert fig["merge"] == pytest.approx(95.0) and fig["delay"] == pytest.approx(50.0)
    assert "crash" not in fig and fig["return"] == pytest.approx(15.0)


def test_the_greedy_actions_are_counted_and_a_constant_policy_is_named() -> None:
    rows = [{"crashed": False, "merged": True, "conflicts": 0, "merger_distance": 100.0, "av_return": 1.0,
             "greedy_actions": counts} for counts in ([0, 150, 0, 0, 0], [0, 48, 0, 0, 2])]
    fig = summarize(rows)
    assert fig["greedy_action_1"] == pytest.approx(99.0) and fig["greedy_action_4"] == pytest.approx(1.0)
    assert sum(fig[f"greedy_action_{k}"] for k in range(5)) == pytest.approx(100.0)
    assert constant_action(fig) == 1
    rows[1]["greedy_actions"] = [0, 40, 0, 0, 10]  # 10 of 200 decisions brake: 95% idle is a policy
    assert constant_action(summarize(rows)) is None
