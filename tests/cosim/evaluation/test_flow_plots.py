"""The demand run's figures (pure, on records written by hand): the time-space diagram marks the window's
collisions, and names them in its legend only where it draws one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from cosim.evaluation import flow_plots
from cosim.evaluation.plots import CRASH_COLOR

CAPTION = "policy: courteous; demand: by hand; net: dilemma.net.xml"


def _record(times: list[float], chainage: list[float]) -> dict[str, np.ndarray]:
    # Two vehicles' points in the window, and the collisions of the whole run (warm-up included).
    return {"points": np.array([[130.0, 400.0, 30.0, 1.0], [131.0, 430.0, 29.0, 2.0]], dtype=np.float32),
            "window": np.array([120.0, 720.0]), "merge_start": np.array(501.0), "merge_end": np.array(620.0),
            "collision_times": np.array(times), "collision_chainage": np.array(chainage)}


def _drawn(monkeypatch: pytest.MonkeyPatch, rec: dict[str, np.ndarray], tmp_path: Path) -> Figure:
    figures: list[Figure] = []
    monkeypatch.setattr(flow_plots, "save", lambda fig, path: figures.append(fig) or path)
    flow_plots.merge_time_space(rec, tmp_path / "ts.png", "courteous, seed 1", CAPTION)
    (fig,) = figures
    return fig


def test_the_time_space_diagram_marks_the_windows_collisions(monkeypatch: pytest.MonkeyPatch,
                                                             tmp_path: Path) -> None:
    # One in the warm-up (not in the diagram's window), one in it, one off the highway's axis (no place on it).
    ax = _drawn(monkeypatch, _record([100.0, 300.0, 310.0], [480.0, 610.0, np.nan]), tmp_path).axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["acceleration lane starts (501 m)", "acceleration lane ends (620 m)", "collision (1)"]
    (crashes,) = [c for c in ax.collections if np.allclose(c.get_facecolor()[:, :3], CRASH_COLOR)]
    assert crashes.get_offsets().tolist() == [[300.0, 610.0]]


def test_without_a_collision_the_legend_names_none(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    for rec in (_record([], []), {k: v for k, v in _record([], []).items() if k != "collision_chainage"}):
        ax = _drawn(monkeypatch, rec, tmp_path).axes[0]  # the second: a record from before places were kept
        assert [t.get_text() for t in ax.get_legend().get_texts()] == ["acceleration lane starts (501 m)",
                                                                       "acceleration lane ends (620 m)"]
        assert len(ax.collections) == 1  # the vehicles' points alone


def test_the_penetration_curves_draw_each_players_means_and_band_per_level(monkeypatch: pytest.MonkeyPatch,
                                                                            tmp_path: Path) -> None:
    def stat(mean: float) -> dict[str, float]:
        return {"mean": mean, "ci_low": mean - 1.0, "ci_high": mean + 1.0}

    cells = {level: {share: {player: {"delay per vehicle [s]": stat(10 * share + k),
                                      "throughput, total [veh/h]": stat(3000 + k)}
                             for k, player in enumerate(("all-human", "phi0"))}
                     for share in (0.6, 0.1)}  # out of order: drawn by penetration
             for level in ("near capacity", "over capacity")}
    figures: list[Figure] = []
    monkeypatch.setattr(flow_plots, "save", lambda fig, path: figures.append(fig) or path)
    flow_plots.penetration_curves(cells, tmp_path / "p.png", caption=CAPTION)
    (fig,) = figures
    axes = fig.axes
    assert [ax.get_title() for ax in axes] == ["near capacity: delay per vehicle", "over capacity: delay per vehicle",
                                               "near capacity: throughput, total", "over capacity: throughput, total"]
    line = axes[0].get_lines()[1]  # phi0's delay, near capacity
    assert line.get_label() == "phi0"
    np.testing.assert_allclose(line.get_xdata(), [10.0, 60.0])
    np.testing.assert_allclose(line.get_ydata(), [2.0, 7.0])
    assert len(axes[0].collections) == 2  # a band per player
