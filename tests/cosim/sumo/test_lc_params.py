"""Lane-change parameters: the names each model reads hold for the installed SUMO; a name no model reads is
refused, one the chosen model ignores is warned about."""

from __future__ import annotations

import logging
from pathlib import Path

import libsumo
import pytest

import cosim
from cosim.config import DEFAULT_NET, LC_PARAMS, load_config
from cosim.errors import ConfigError

pytestmark = pytest.mark.sumo

VALUE = 0.37  # valid for every parameter (non-negative, lcAccelLat > 0), and no model's default


def _read_back(tmp_path: Path, model: str, names: list[str]) -> dict[str, float | None]:
    """Each name set to VALUE on one vType of `model`; what its vehicle's model reports (None: not a parameter
    of the model)."""
    attrs = " ".join(f'{n}="{VALUE}"' for n in names)
    routes = tmp_path / "r.rou.xml"
    routes.write_text(f'<routes><vType id="t" laneChangeModel="{model}" {attrs}/>'
                      '<route id="r" edges="hw_in hw_merge hw_out"/><vehicle id="v" type="t" route="r" depart="0"/>'
                      '</routes>')
    sublane = ["--lateral-resolution", "0.8"] if model == "SL2015" else []
    libsumo.start(["sumo", "-n", str(DEFAULT_NET), "-r", str(routes), "--no-step-log", *sublane])
    try:
        libsumo.simulationStep()
        got: dict[str, float | None] = {}
        for name in names:
            try:
                got[name] = float(libsumo.vehicle.getParameter("v", f"laneChangeModel.{name}"))
            except libsumo.TraCIException:
                got[name] = None
        return got
    finally:
        libsumo.close()


def test_lc2013_takes_its_parameters_and_ignores_sl2015s(tmp_path: Path) -> None:
    sl2015_only = sorted(LC_PARAMS["SL2015"] - LC_PARAMS["LC2013"])
    got = _read_back(tmp_path, "LC2013", sorted(LC_PARAMS["LC2013"]) + sl2015_only)
    assert {n: got[n] for n in LC_PARAMS["LC2013"]} == dict.fromkeys(LC_PARAMS["LC2013"], pytest.approx(VALUE))
    assert {n: got[n] for n in sl2015_only} == dict.fromkeys(sl2015_only)


def test_sl2015_takes_its_own_parameters(tmp_path: Path) -> None:
    # lcPushyGap and lcTurnAlignmentDistance are read from the vType but not reported back by the model.
    own = sorted(LC_PARAMS["SL2015"] - LC_PARAMS["LC2013"] - {"lcPushyGap", "lcTurnAlignmentDistance"})
    assert _read_back(tmp_path, "SL2015", own) == dict.fromkeys(own, pytest.approx(VALUE))


@pytest.mark.parametrize("key", ["hv", "merger"])
def test_a_name_no_model_reads_is_refused_with_the_models_list(key: str) -> None:
    with pytest.raises(ConfigError, match=rf"{key}\.lc_params.*'lcFoo' is no lane-change parameter.*lcAssertive"):
        load_config("configs/default.yaml", {f"{key}.lc_params": {"lcFoo": 1.0}})


@pytest.mark.parametrize(("overrides", "warned"), [
    ({"hv.lc_params": {"lcImpatience": 0.5}}, True),
    ({"hv.lane_change_model": "SL2015", "hv.lc_params": {"lcImpatience": 0.5}}, False),
])
def test_a_name_the_model_ignores_is_warned_about(overrides: dict, warned: bool,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        cosim.parallel_env("configs/default.yaml", overrides).close()
    assert ("hv.lc_params: LC2013 ignores lcImpatience" in caplog.text) is warned
