"""scripts/demand_headline.py's checks: with several training seeds, each altruistic run is weighed against the
egoistic run of its own seed, not against whichever egoistic run came first."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("demand_headline", ROOT / "scripts" / "demand_headline.py")
headline = sys.modules["demand_headline"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(headline)


def _measure(mean: float) -> dict[str, float]:
    return {"mean": mean, "ci_low": mean - 1, "ci_high": mean + 1}


def test_an_altruistic_run_is_weighed_against_the_egoistic_run_of_its_training_seed() -> None:
    throughput = {"all-human": 4000, "scripted": 4000, "ego_s1": 3000, "ego_s2": 4500, "alt_s1": 4100,
                  "alt_s2": 4200}
    table = {p: {headline.THROUGHPUT: _measure(v), headline.CRASH: _measure(1)} for p, v in throughput.items()}
    phis = {"ego_s1": 0.0, "ego_s2": 0.0, "alt_s1": 0.7854, "alt_s2": 0.7854}
    seeds = {"ego_s1": 1, "ego_s2": 2, "alt_s2": 2, "alt_s1": 1}
    checks = [c for c in headline.cell_checks(table, phis, seeds) if headline.THROUGHPUT in c and "against ego" in c]
    assert checks == [
        "alt_s1 against ego_s1, throughput, total [veh/h]: 4100 [4099, 4101] vs 3000 [2999, 3001]: "
        "altruism better (intervals apart)",
        "alt_s2 against ego_s2, throughput, total [veh/h]: 4200 [4199, 4201] vs 4500 [4499, 4501]: "
        "altruism worse (intervals apart)"]
    # An altruistic run whose seed no egoistic run shares is weighed against the first egoistic one.
    seeds["alt_s2"] = 3
    assert any(c.startswith("alt_s2 against ego_s1, throughput") for c in headline.cell_checks(table, phis, seeds))


def test_each_player_gets_the_level_of_service_of_its_density_and_of_its_interval() -> None:
    # 16 / 20 / 24 veh/km/ln are 25.7 / 32.2 / 38.6 pc/mi/ln: HCM's C, D and E; 4 / 5 / 7 are A, A and B.
    table = {"all-human": {headline.DENSITY: {"mean": 20.0, "ci_low": 16.0, "ci_high": 24.0}},
             "ego_s1": {headline.DENSITY: {"mean": 5.0, "ci_low": 4.0, "ci_high": 7.0}}}
    assert headline.service_levels(table, over_capacity=False).endswith("all-human D [C, E]; ego_s1 A [A, B]")
    # Demand over the capacity is F whatever the density.
    assert headline.service_levels(table, over_capacity=True).endswith("all-human F [F, F]; ego_s1 F [F, F]")
