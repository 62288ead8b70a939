"""Bad input reaches the user as one clear error naming the file or key, never a libsumo traceback."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest

import cosim
from cosim.cli import main
from cosim.errors import ConfigError, NetError, SimulationError, run_script

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[2]
NET_DIR = ROOT / "sumo_net" / "merge"


def test_missing_net_file(tmp_path: Path) -> None:
    with pytest.raises(NetError, match=r"net file .*nope\.net\.xml.*not found"):
        cosim.parallel_env("configs/default.yaml", {"net.file": str(tmp_path / "nope.net.xml")})


def test_malformed_net_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.net.xml"
    bad.write_text((NET_DIR / "merge.net.xml").read_text()[:500])
    with pytest.raises(NetError, match="broken.net.xml"):
        cosim.parallel_env("configs/default.yaml", {"net.file": str(bad)})


def test_description_naming_a_missing_edge(tmp_path: Path) -> None:
    shutil.copy(NET_DIR / "merge.net.xml", tmp_path / "merge.net.xml")
    (tmp_path / "merge.yaml").write_text(
        "highway: [hw_in, hw_merge, hw_gone]\nramp: [ramp]\nmerge_edge: hw_merge\naccel_lanes: [0]\n")
    with pytest.raises(NetError, match="hw_gone"):
        cosim.parallel_env("configs/default.yaml", {"net.file": str(tmp_path / "merge.net.xml")})


def test_sumo_that_fails_to_start() -> None:
    env = cosim.parallel_env("configs/default.yaml", {"sim.sumo_args": ["--no-such-option", "1"]})
    try:
        with pytest.raises(SimulationError, match="SUMO failed to start"):
            env.reset(seed=0)
    finally:
        env.close()
    # The process is usable again afterwards.
    env = cosim.parallel_env("configs/default.yaml", {"scenario.n_hvs": 2})
    try:
        env.reset(seed=0)
        assert env.agents
    finally:
        env.close()


def test_unknown_key_through_the_env_factory() -> None:
    with pytest.raises(ConfigError, match="scenario.n_av: unknown"):
        cosim.parallel_env("configs/default.yaml", {"scenario.n_av": 3})


def test_every_config_problem_names_its_key_and_the_file_only_for_the_files_values() -> None:
    with pytest.raises(ConfigError) as caught:
        cosim.parallel_env("configs/default.yaml", {"scenario.n_avs": 0, "train.algo": "dqn"})
    assert str(caught.value).splitlines() == [  # the caller's own values: not the file's
        "scenario.n_avs: must be > 0, got 0",
        "train.algo: expected 'a2c' or 'ppo', got 'dqn'",
    ]


def test_cli_prints_one_line_and_exits_2(capsys: pytest.CaptureFixture[str], caplog) -> None:
    assert main(["run-scenario", "--episodes", "1", "--set", "scenario.n_avs=-2"]) == 2
    assert caplog.messages == ["--set scenario.n_avs=-2: must be > 0, got -2"]
    assert "Traceback" not in capsys.readouterr().err


def test_scripts_end_bad_input_in_one_line(caplog: pytest.LogCaptureFixture) -> None:
    def bad() -> None:
        raise NetError("--net x.net.xml: not found (expected a SUMO .net.xml)")

    with pytest.raises(SystemExit) as stop:
        run_script(bad, logging.getLogger("script"))
    assert stop.value.code == 2
    assert [r.getMessage() for r in caplog.records] == ["--net x.net.xml: not found (expected a SUMO .net.xml)"]
    with pytest.raises(ZeroDivisionError):  # a defect is not bad input: its traceback stays
        run_script(lambda: 1 / 0, logging.getLogger("script"))
