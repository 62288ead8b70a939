"""Demand's vehicles on real SUMO: they enter as traffic arriving from upstream does, at speed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.config import load_config
from cosim.evaluation.runner import Baseline, evaluate

pytestmark = pytest.mark.sumo


def test_vehicles_enter_the_highway_at_speed_not_at_a_crawl(tmp_path: Path) -> None:
    """Inserted at the speed safe behind the last vehicle in (departSpeed "max"), they crawled in and the highway's
    first 100 m were a permanent slow band (22 m/s over this window, 16 m/s in its first 25 m) below the 30 m/s
    downstream, where nothing slows them."""
    cfg = load_config("configs/demand.yaml", ["demand.warmup=30", "demand.window=60"])
    evaluate(cfg, Baseline("sumo"), tmp_path / "ev", episodes=1, plots=False)
    with np.load(next((tmp_path / "ev" / "sumo").glob("run_*/record.npz"))) as rec:
        heat, (dt, ds), window = rec["heatmap"], rec["heat_bins"], rec["window"]
    # (S,) [m/s] over the window per chainage cell, up to 300 m (the cells past the road's end stay empty)
    speed = np.nanmean(heat[int(window[0] // dt):, : int(300 / ds)], axis=0)
    first, downstream = np.nanmean(speed[: int(100 / ds)]), np.nanmean(speed[int(250 / ds): int(300 / ds)])
    assert first > downstream - 1.0, (first, downstream)
