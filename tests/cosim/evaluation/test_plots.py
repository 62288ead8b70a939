"""Figures of a real recorded episode: labelled, with a legend and a title, and continuous through junctions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

import cosim
from cosim.environment.policies import POLICIES
from cosim.environment.render import COLOURS as TOP_VIEW_COLOURS
from cosim.environment.velocity_map import rasterize_road
from cosim.evaluation import plots
from cosim.sumo.roadnet import load_roadnet
from cosim.sumo.snapshot import KIND_MERGER

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

@pytest.fixture(scope="module")
def merged_episode() -> dict[str, np.ndarray]:
    """A courteous episode of the default scenario in which the merging vehicle gets in (through the junction)."""
    env = cosim.parallel_env("configs/default.yaml")
    try:
        for seed in range(10_000_000, 10_000_010):
            act = POLICIES["courteous"](seed)
            env.reset(seed=seed)
            recorder = env.new_tracker(record=True)
            recorder.observe(env.snapshot)
            while env.agents:
                actions = act(env)
                env.step(actions)
                recorder.observe(env.snapshot, actions)
            traj = recorder.trajectory()
            if np.isfinite(float(traj["merge_time"])):
                return traj
    finally:
        env.close()
    pytest.fail("no courteous episode of ten merged")


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    drawn: list[Figure] = []
    monkeypatch.setattr(plots, "save", lambda fig, path: drawn.append(fig) or path)
    return drawn


def test_top_views_have_axis_labels_a_legend_and_a_title(merged_episode, figures, tmp_path: Path) -> None:
    lanes = load_roadnet("sumo_net/dilemma/dilemma.net.xml").lane_shapes()
    plots.top_views(merged_episode, rasterize_road(lanes), tmp_path / "top.png", title="courteous: episode seed 1")
    (fig,) = figures
    axes = fig.axes
    assert fig.get_suptitle().startswith("courteous: episode seed 1: top views around the merge (merge at ")
    assert all(ax.get_ylabel() == "y [m]" for ax in axes) and axes[-1].get_xlabel().startswith("x [m]")
    legend = axes[0].get_legend()
    assert legend is not None and [t.get_text() for t in legend.get_texts()] == ["AV", "HV", "merging vehicle",
                                                                                  "guide AV", "crashed"]
    # Each view is the renderer's image, in network coordinates, with the merging vehicle drawn in its colour.
    merger_rgb = np.asarray(TOP_VIEW_COLOURS[KIND_MERGER], dtype=np.uint8)
    for ax in axes:
        (image,) = ax.get_images()
        assert (np.asarray(image.get_array())[..., :3] == merger_rgb).all(axis=-1).any()
        x0, x1, _, _ = image.get_extent()
        assert x1 - x0 == pytest.approx(220.0, abs=2.0)  # the 2 x 110 m window


def test_time_space_lines_are_continuous_through_the_junction(merged_episode, figures, tmp_path: Path) -> None:
    plots.time_space(merged_episode, tmp_path / "ts.png")
    (fig,) = figures
    merger = [line for line in fig.axes[0].lines
              if line.get_linewidth() > 2 and line.get_color() == plots.COLORS[KIND_MERGER]]
    (line,) = merger
    t, s = (np.asarray(a, float) for a in line.get_data())
    # The merging vehicle goes from the ramp through the junction onto the highway: no gap, no jump back.
    assert np.isfinite(s).all() and len(s) == len(t) > 10
    assert np.all(np.diff(s) >= -1e-6) and np.max(np.diff(s)) < 40.0 * np.max(np.diff(t))
    assert merged_episode["kind"].tolist().count(KIND_MERGER) == len(s)
