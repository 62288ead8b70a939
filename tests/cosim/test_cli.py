"""The `cosim` command's env-side subcommands run end to end on real SUMO."""

from __future__ import annotations

from pathlib import Path

import pytest

from cosim.cli import main

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

def test_build_net_then_run_scenario_on_it(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    caplog.set_level("INFO")
    monkeypatch.chdir(tmp_path)  # a user's own folder: the default config is found from anywhere
    out = tmp_path / "my_merge"
    assert main(["build-net", "--lanes", "2", "--accel-length", "80", "--out", str(out)]) == 0
    assert (out / "merge.net.xml").is_file() and (out / "merge.yaml").is_file()
    assert main(["run-scenario", "--episodes", "1", "--policy", "random", "--save-routes", str(tmp_path / "routes"),
                 "--net", str(out / "merge.net.xml")]) == 0
    assert "random   seed 0" in caplog.text and "WARNING" not in caplog.text  # the default fits this net
    routes = (tmp_path / "routes" / "episode_0.rou.xml").read_text()
    # The default scene: 4 AVs in the stream, 3 HVs beside it (16 per km on its 200 m), the merging vehicle, and
    # the stream's HVs.
    assert routes.count('type="av"') == 4 and routes.count('id="merger"') == 1
    assert routes.count("<vehicle ") > 4 + 3 + 1 and 'carFollowModel="IDM"' in routes


def test_bench_prints_ratios(capsys: pytest.CaptureFixture[str]) -> None:
    # Two episodes: the env resets after the bare loops have replayed its first one in the same libsumo.
    assert main(["bench", "--episodes", "2", "--resets", "2", "--set", "scenario.n_hvs=4"]) == 0
    out = capsys.readouterr().out
    for needle in ("(a) bare libsumo", "b/a =", "c/a =", "(d) reset", "KiB per observation"):
        assert needle in out
