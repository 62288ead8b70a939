"""Two merging drivers in one run (`scenario.merger_alt_share`): each episode's merging vehicle, or under demand
each ramp vehicle, is drawn to drive `merger` or `merger_alt`, and SUMO drives the one drawn."""

from __future__ import annotations

from pathlib import Path

import libsumo
import pytest

import cosim
from cosim.config import load_config
from cosim.errors import ConfigError
from cosim.sumo.demand import plan_demand, write_demand
from cosim.sumo.scenario import MERGER_ID, plan_episode
from cosim.sumo.setting import Setting
from cosim.sumo.snapshot import KIND_MERGER

MIXED = "configs/mixed_merger.yaml"


def _drawn(config: str, overrides: dict | None = None, seeds: range = range(200)) -> list[bool]:
    setting = Setting.of(load_config(config, overrides))
    return [next(s for s in plan_episode(setting.config, setting.net, seed).vehicles if s.vid == MERGER_ID).alt
            for seed in seeds]


def test_a_share_without_a_second_type_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"scenario\.merger_alt_share.*add a merger_alt section"):
        load_config("configs/default.yaml", {"scenario.merger_alt_share": 0.5})


def test_the_mixed_config_restates_the_impatient_merger() -> None:
    assert load_config(MIXED).merger_alt == load_config("configs/impatient.yaml").merger


def test_each_episode_draws_its_merging_driver_by_its_seed() -> None:
    drawn = _drawn(MIXED)
    assert 70 <= sum(drawn) <= 130  # Binomial(200, 0.5): outside in 1 of 10^4 draws
    assert _drawn(MIXED, seeds=range(20)) == drawn[:20]
    assert not any(_drawn(MIXED, {"scenario.merger_alt_share": 0.0}))
    assert all(_drawn(MIXED, {"scenario.merger_alt_share": 1.0}))


def test_no_share_keeps_every_episode_as_it_was() -> None:
    """The draw is made only where a share asks for it: the default scenario's episodes stay the same."""
    plain, given = (Setting.of(load_config(c)) for c in ("configs/default.yaml", MIXED))
    given_off = Setting.of(given.config.model_copy(update={"scenario": given.config.scenario.model_copy(
        update={"merger_alt_share": 0.0})}))
    for seed in range(5):
        assert plan_episode(plain.config, plain.net, seed) == plan_episode(given_off.config, given_off.net, seed)


@pytest.mark.sumo
def test_sumo_drives_the_merging_vehicle_drawn() -> None:
    """The impatient type asks for half the default gap (lcAssertive 2); the polite one keeps SUMO's 1."""
    drawn = _drawn(MIXED, seeds=range(6))
    assert len(set(drawn)) == 2
    env = cosim.parallel_env(MIXED, {"sim.horizon": 2.0})
    try:
        for seed, alt in enumerate(drawn):
            env.reset(seed=seed)
            assert float(libsumo.vehicle.getParameter(MERGER_ID, "laneChangeModel.lcAssertive")) == (
                2.0 if alt else 1.0)
            while env.agents:
                env.step(dict.fromkeys(env.agents, 0))
            # The episode's row says which driver it met, so that a mixed run's figures are read per driver.
            assert env.last_summary["merger_alt"] is alt
    finally:
        env.close()


def test_under_demand_each_ramp_vehicle_draws_its_driver(tmp_path: Path) -> None:
    setting = Setting.of(load_config("configs/demand.yaml", {"scenario.merger_alt_share": 0.3, **{
        f"merger_alt.{k}": v for k, v in {"lane_change_model": "SL2015", "lc_params": {"lcAssertive": 2.0}}.items()}}))
    ramp = [a for a in plan_demand(setting.config, setting.net, setting.demand, 7) if a.kind == KIND_MERGER]
    alt = [a for a in ramp if a.alt]
    assert 0.15 * len(ramp) <= len(alt) <= 0.45 * len(ramp), (len(alt), len(ramp))
    write_demand(ramp, setting.config, setting.net.desc, tmp_path / "d.rou.xml")
    text = (tmp_path / "d.rou.xml").read_text()
    assert text.count('laneChangeModel="SL2015"') == len(alt)
