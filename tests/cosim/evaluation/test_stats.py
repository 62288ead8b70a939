"""Confidence intervals and summaries against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.evaluation.stats import format_table, mean_ci, rate_ci, summarize


def test_mean_ci_known_values() -> None:
    ci = mean_ci([1, 2, 3, 4, 5])
    half = 2.7764 * math.sqrt(2.5) / math.sqrt(5)
    assert (ci.mean, ci.n) == (3.0, 5)
    assert ci.low == pytest.approx(3 - half, abs=1e-3) and ci.high == pytest.approx(3 + half, abs=1e-3)
    one = mean_ci([7.0])
    assert one.mean == 7.0 and math.isnan(one.low) and math.isnan(one.high) and one.n == 1
    assert math.isnan(mean_ci([]).mean) and mean_ci([math.nan, 2.0]).n == 1  # NaNs are left out
    same = mean_ci([4.0, 4.0, 4.0])
    assert (same.low, same.high) == (4.0, 4.0)


def test_summarize_hand_built_records() -> None:
    # CSV-style cells as read back from episodes.csv: strings, booleans as "True"/"False", empty = missing.
    rows = [
        {"crashed": "True", "merged": "False", "time_to_merge": "", "mean_distance": "100"},
        {"crashed": "False", "merged": "True", "time_to_merge": "6.0", "mean_distance": "200"},
        {"crashed": "False", "merged": "True", "time_to_merge": "8.0", "mean_distance": "300"},
        {"crashed": "False", "merged": "True", "time_to_merge": "7.0", "mean_distance": "400"},
    ]
    s = summarize(rows)
    assert s["crash [%]"]["mean"] == 25.0 and s["merge success [%]"]["mean"] == 75.0
    # Rates get Wilson score intervals: 1 of 4 -> [4.56, 69.94] % (a t-interval would be clipped to [0, 100])
    assert s["crash [%]"]["ci_low"] == pytest.approx(4.56, abs=0.01)
    assert s["crash [%]"]["ci_high"] == pytest.approx(69.94, abs=0.01)
    assert s["merge success [%]"]["ci_low"] == pytest.approx(100 - 69.94, abs=0.01)
    d = s["mean distance [m]"]
    half = 3.1824 * np.std([100, 200, 300, 400], ddof=1) / 2
    assert d["mean"] == 250.0 and d["ci_high"] == pytest.approx(250 + half, abs=1e-2)
    assert s["time to merge [s]"]["n"] == 3 and s["time to merge [s]"]["mean"] == pytest.approx(7.0)
    assert "throughput [veh/h]" not in s  # not in the rows: left out
    one = summarize([{"crashed": True, "merged": True, "mean_distance": 5.0}])
    # One episode: a rate still has a Wilson interval, a continuous metric has none.
    assert one["crash [%]"]["mean"] == 100.0 and one["crash [%]"]["ci_low"] == pytest.approx(20.65, abs=0.01)
    assert math.isnan(one["mean distance [m]"]["ci_low"])
    table = format_table({"A": s, "B": one}, {"A": 4, "B": 1})
    assert "crash [%]" in table and "A (n=4)" in table and "B (n=1)" in table
    assert format_table({"A": s}, {"A": 4}, markdown=True).startswith("| metric")


@pytest.mark.parametrize(("k", "n", "low", "high"), [(0, 10, 0.0, 0.2775), (10, 10, 0.7225, 1.0),
                                                   (1, 4, 0.0456, 0.6994), (50, 100, 0.4038, 0.5962)])
def test_rate_ci_is_the_wilson_score_interval(k: int, n: int, low: float, high: float) -> None:
    ci = rate_ci([1] * k + [0] * (n - k))
    assert ci.mean == k / n and ci.n == n
    assert ci.low == pytest.approx(low, abs=1e-4) and ci.high == pytest.approx(high, abs=1e-4)
    assert rate_ci([1, 0, 1], confidence=0.99).high > rate_ci([1, 0, 1], confidence=0.9).high
    assert math.isnan(rate_ci([]).mean) and rate_ci([math.nan, 1.0]).n == 1
    with pytest.raises(ValueError, match="0/1"):
        rate_ci([0.5, 1.0])


def test_rates_of_none_or_all_episodes_keep_a_width() -> None:
    # No crash in 20 episodes is not "0 % for sure": the t-interval would be [0, 0].
    s = summarize([{"crashed": "False", "merged": "True", "mean_distance": "100"}] * 20)
    assert s["crash [%]"]["mean"] == 0.0 and s["crash [%]"]["ci_low"] == 0.0
    assert s["crash [%]"]["ci_high"] == pytest.approx(16.11, abs=0.01)
    assert s["merge success [%]"]["ci_high"] == 100.0
    assert s["merge success [%]"]["ci_low"] == pytest.approx(100 - 16.11, abs=0.01)
    assert (s["mean distance [m]"]["ci_low"], s["mean distance [m]"]["ci_high"]) == (100.0, 100.0)  # t-interval


def test_t_intervals_stop_at_what_the_quantity_can_take() -> None:
    # One hard-braking event in 5 episodes: the t-interval 0.2 +- 0.56 would reach below zero events.
    s = summarize([{"hard_brakes": v} for v in (0, 0, 0, 1, 0)])
    got = s["hard braking [events per episode]"]
    assert got["mean"] == pytest.approx(0.2) and got["ci_low"] == 0.0
    assert got["ci_high"] == pytest.approx(0.2 + 2.7764 * math.sqrt(0.2) / math.sqrt(5), abs=1e-3)
    # A share over a demand run's seeds stops at 100%.
    share = summarize([{"merge_rate_pct": v} for v in (100.0, 100.0, 90.0)])["merge success, per merging vehicle [%]"]
    assert share["ci_high"] == 100.0 and 0.0 < share["ci_low"] < share["mean"]


def test_a_mix_of_merging_drivers_gets_each_drivers_rates_beside_the_pooled_ones() -> None:
    rows = [{"crashed": c, "merged": True, "merger_alt": a} for c, a in [(1, True), (0, True), (0, False), (0, False)]]
    got = summarize(rows)
    assert got["crash [%]"]["mean"] == 25.0
    assert got["crash [%], merger_alt"]["mean"] == 50.0 and got["crash [%], merger_alt"]["n"] == 2
    assert got["crash [%], merger"]["mean"] == 0.0 < got["crash [%], merger"]["ci_high"]  # Wilson, as pooled
    table = format_table({"run": got}, {"run": 4}).splitlines()
    names = [line.split("  ")[0] for line in table[2:]]
    assert names.index("crash [%], merger") == names.index("crash [%]") + 1
    # One driver: nothing split.
    assert not [k for k in summarize(rows[2:]) if ", merger" in k]
