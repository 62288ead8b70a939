"""Figures a reader takes in at a glance: a title, axis labels with units, legends that cover no data, the net,
config and policy in a caption; the distance histogram marks the acceleration lane, the bars hold the flow
metrics, the training curves are one smoothed line per group with a band and the crash target marked; and the
figures of a real recorded episode are labelled and continuous through junctions."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import PolyCollection

import cosim
from cosim.config import load_config
from cosim.environment.policies import POLICIES
from cosim.environment.render import COLOURS as TOP_VIEW_COLOURS
from cosim.environment.velocity_map import rasterize_road
from cosim.evaluation import plots
from cosim.sumo.roadnet import load_roadnet
from cosim.sumo.setting import Setting
from cosim.sumo.snapshot import KIND_MERGER

CAPTION = plots.caption_text("sumo_net/dilemma/dilemma.net.xml", "configs/default.yaml", "courteous")


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


@pytest.mark.sumo  # runs SUMO (libsumo or netconvert)
def test_top_views_have_axis_labels_a_legend_and_a_title(merged_episode, figures, readable, tmp_path: Path) -> None:
    lanes = load_roadnet("sumo_net/dilemma/dilemma.net.xml").lane_shapes()
    plots.top_views(merged_episode, rasterize_road(lanes), tmp_path / "top.png", title="courteous: episode seed 1",
                    caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
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


@pytest.mark.sumo
def test_time_space_lines_are_continuous_through_the_junction(merged_episode, figures, readable,
                                                               tmp_path: Path) -> None:
    plots.time_space(merged_episode, tmp_path / "ts.png", title="courteous: episode seed 1", caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    # Both ends of the acceleration lane are drawn and named.
    lines = {round(line.get_ydata()[0], 3) for line in fig.axes[0].lines if line.get_linestyle() == "--"}
    assert lines == {round(float(merged_episode[k]), 3) for k in ("merge_start", "merge_end")}
    assert [t.get_text() for t in fig.axes[0].texts] == ["acceleration lane starts", "acceleration lane ends"]
    merger = [line for line in fig.axes[0].lines
              if line.get_linewidth() > 2 and line.get_color() == plots.COLORS[KIND_MERGER]]
    (line,) = merger
    t, s = (np.asarray(a, float) for a in line.get_data())
    # The merging vehicle goes from the ramp through the junction onto the highway: no gap, no jump back.
    assert np.isfinite(s).all() and len(s) == len(t) > 10
    assert np.all(np.diff(s) >= -1e-6) and np.max(np.diff(s)) < 40.0 * np.max(np.diff(t))
    assert merged_episode["kind"].tolist().count(KIND_MERGER) == len(s)


def test_time_space_marks_a_crash_and_names_crashed_only_then(figures, readable, tmp_path: Path) -> None:
    # Three vehicles over three steps; the guide AV runs into the HV ahead at the last one (its rows flagged).
    vehicle, step = np.tile([0, 1, 2], 3), np.repeat([0, 1, 2], 3)
    s = np.array([400.0, 420.0, 380.0])[vehicle] + 10.0 * step
    traj = {"guide": np.asarray("av_0"), "merge_time": np.asarray(np.nan), "merge_start": np.asarray(500.0),
            "merge_end": np.asarray(620.0), "ids": np.array(["av_0", "hv_0", "merger_0"]), "vehicle": vehicle,
            "step": step, "kind": np.array([0, 1, KIND_MERGER])[vehicle], "s": s, "speed": np.full(9, 20.0),
            "crashed": (step == 2) & (vehicle < 2), "time": np.array([0.0, 0.5, 1.0]),
            "guide_actions": np.array([0, 1])}
    legends = []
    for crashed in (traj["crashed"], np.zeros(9, bool)):
        plots.time_space({**traj, "crashed": crashed}, tmp_path / "ts.png", title="by hand", caption=CAPTION)
        ax = figures[-1].axes[0]
        readable(figures[-1], CAPTION)
        legends.append([t.get_text() for t in ax.get_legend().get_texts()])
        points = [c.get_offsets().tolist() for c in ax.collections]
        assert points == ([[[1.0, 420.0], [1.0, 440.0]]] if crashed.any() else [])
    assert legends == [["AV", "HV", "merging vehicle", "guide AV", "crashed"], ["AV", "HV", "merging vehicle",
                                                                               "guide AV"]]


def test_bars_hold_the_flow_metrics(figures, readable, tmp_path: Path) -> None:
    stats = {m: {"mean": 10.0, "ci_low": 8.0, "ci_high": 12.0} for m in plots.BAR_METRICS}
    plots.bars({"courteous": stats, "scripted": stats}, tmp_path / "bars.png", caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION, runs_on_x=True)
    assert [ax.get_ylabel() for ax in fig.axes] == ["crash [%]", "merge success [%]", "mean distance [m]",
                                                    "throughput [veh/h]", "time loss [s]"]
    assert all([t.get_text() for t in ax.get_xticklabels()] == ["courteous", "scripted"] for ax in fig.axes)


def test_distance_histogram_marks_the_acceleration_lane(figures, readable, tmp_path: Path) -> None:
    cfg = load_config("configs/default.yaml")
    marks = plots.accel_lane_marks(Setting.of(cfg))
    # dilemma: the merging vehicle starts 3.6-5.4 s before the acceleration lane at 0.8-1.0 x the ramp's 22.22
    # m/s (64-120 m), its end one merge edge (118.8 m between the junctions) further.
    (s0, s1), (e0, e1) = marks.values()
    assert (s0, s1) == pytest.approx((3.6 * 0.8 * 22.22, 5.4 * 22.22))
    merge_edge = load_roadnet(cfg.net.file).edge_length("hw_merge")
    assert e0 - s0 == pytest.approx(merge_edge) and e1 - s1 == pytest.approx(merge_edge)
    distances = {"egoistic": [210.0, 212.0, 215.0, 430.0], "altruistic": [420.0, 440.0, 211.0]}
    plots.distance_histogram(distances, tmp_path / "h.png", marks=marks, caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    (ax,) = fig.axes
    drawn = sorted(line.get_xdata()[0] for line in ax.lines if len(line.get_xdata()) == 2)
    assert drawn == pytest.approx(sorted([s0, s1, e0, e1]))
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["egoistic (n=4)", "altruistic (n=3)", f"acceleration lane starts: {s0:.0f}-{s1:.0f} m",
                      f"acceleration lane ends: {e0:.0f}-{e1:.0f} m"]
    ticks = [t for t in ax.get_yticks() if ax.get_ylim()[0] <= t <= ax.get_ylim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)  # no half episodes


def _log(path: Path, crash: np.ndarray) -> Path:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "return_mean", "crashed", "merged", "mean_distance"])
        w.writerows([i + 1, 1.0, c, 0, 100.0] for i, c in enumerate(crash))
    return path


def test_training_curves_one_line_per_group_with_its_band_and_the_crash_target(figures, readable,
                                                                                tmp_path: Path) -> None:
    # Two angles: one with three seeds whose crash rate falls from 100% to 0% at episodes 300, 400, 500, one
    # with a single seed that never gets below 50%.
    fall = {seed: _log(tmp_path / f"a{seed}.csv", (np.arange(600 + 10 * seed) < 300 + 100 * seed).astype(int))
            for seed in range(3)}
    stay = _log(tmp_path / "b.csv", np.arange(650) % 2)
    plots.training_curves({"phi=0.785": list(fall.values()), "phi=0.000": [stay]}, tmp_path / "t.png", window=100,
                          caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    crash = next(ax for ax in fig.axes if ax.get_ylabel().startswith("crash rate"))
    curves = [line for line in crash.lines if line.get_linewidth() == 1.6]
    assert len(curves) == 2  # one smoothed line per group, no raw per-episode lines:
    assert len(crash.lines) == 4  # besides them only the crash marker and the target's dotted line
    x, y = (np.asarray(a, float) for a in curves[0].get_data())
    assert len(x) == 600 - 100 + 1  # up to the shortest seed's episodes
    assert y[0] == 100.0 and y[-1] == 0.0
    bands = [c for c in crash.collections if isinstance(c, PolyCollection)]
    assert len(bands) == 1  # a band for the group with several seeds only
    # The mean of the three seeds' 100-episode means first reaches 2% where the last seed's reaches 6%
    # (1/3 of 6%): 94 of its 100 episodes after its fall at 500, i.e. at the window ending at episode 594.
    (marker,) = [line for line in crash.lines if line.get_marker() == "v"]
    assert marker.get_xdata()[0] == 594 and marker.get_ydata()[0] == pytest.approx(2.0)


def _validations(folder: Path, crash: list[float], merge: list[float]) -> None:
    with (folder / "validation.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["update", "episodes", "crash", "crash_high", "merge"])
        w.writerows([10 * (i + 1), 500 * (i + 1), c, c + 3.0, m]
                    for i, (c, m) in enumerate(zip(crash, merge, strict=True)))


def test_training_curves_draw_the_validations_beside_training_and_star_where_the_criterion_held(
        figures, readable, tmp_path: Path) -> None:
    # Two seeds of one angle, each run in its folder with its validations (every 500 episodes; the second stopped
    # one validation earlier), and a run without validations: the dashed curve is the mean of the two at the
    # episodes both validated at, and the criterion's star sits on the run's own validation at the episodes given.
    logs = []
    for seed, (crash, merge) in enumerate([([40.0, 10.0, 1.5], [50.0, 90.0, 97.0]), ([60.0, 4.0], [70.0, 80.0])]):
        (tmp_path / f"s{seed}").mkdir()
        logs.append(_log(tmp_path / f"s{seed}" / "episodes.csv", np.zeros(1600, int)))
        _validations(tmp_path / f"s{seed}", crash, merge)
    (tmp_path / "other").mkdir()
    other = _log(tmp_path / "other" / "episodes.csv", np.zeros(1600, int))
    plots.training_curves({"phi=0.785": logs, "phi=0.000": [other]}, tmp_path / "t.png", caption=CAPTION,
                          criterion_met={logs[0]: 1500.0})
    (fig,) = figures
    readable(fig, CAPTION)
    panel = {ax.get_ylabel(): ax for ax in fig.axes if ax.get_visible()}
    for label, expected in (("crash rate [% of episodes]", [50.0, 7.0]), ("merge rate [% of episodes]", [60.0, 85.0])):
        (dashed,) = [line for line in panel[label].lines if line.get_linestyle() == "--"]  # none for the other run
        assert list(dashed.get_xdata()) == [500, 1000] and list(dashed.get_ydata()) == pytest.approx(expected)
        assert dashed.get_color() == "C0"
    stars = [line for line in panel["crash rate [% of episodes]"].lines if line.get_marker() == "*"]
    assert [(s.get_xdata()[0], s.get_ydata()[0]) for s in stars] == [(1500.0, 1.5)]
    (star,) = [line for line in panel["merge rate [% of episodes]"].lines if line.get_marker() == "*"]
    assert star.get_ydata()[0] == 97.0
    legends = [leg for leg in [*fig.legends, *(ax.get_legend() for ax in fig.axes)] if leg is not None]
    labels = [t.get_text() for leg in legends for t in leg.get_texts()]
    assert "a run's validation first meeting the criterion" in labels


def test_over_phi_puts_each_angle_with_its_interval_and_the_references_across(figures, readable,
                                                                              tmp_path: Path) -> None:
    def stat(mean: float, half: float) -> dict[str, float]:
        return {"mean": mean, "ci_low": mean - half, "ci_high": mean + half}

    tables = {0.7854: {"crash [%]": stat(3.0, 1.0), "merge success [%]": stat(94.0, 2.0)},
              0.0: {"crash [%]": stat(3.2, 1.2), "merge success [%]": stat(55.0, 3.0)},
              1.5708: {"crash [%]": stat(6.0, 2.0), "merge success [%]": stat(99.0, 1.0)}}
    plots.over_phi(tables, ["crash [%]", "merge success [%]"], tmp_path / "p.png",
                   {"courteous": {"merge success [%]": stat(97.3, 1.0)}}, caption=CAPTION)
    (fig,) = figures
    readable(fig, CAPTION)
    crash, merge = (ax for ax in fig.axes if ax.get_visible())
    (line,) = merge.lines[:1]
    assert list(line.get_xdata()) == [0.0, 0.7854, 1.5708]  # in angle order, whatever the mapping's
    assert list(line.get_ydata()) == [55.0, 94.0, 99.0]
    (bars,) = [c for c in merge.collections if c.get_segments()]
    assert [tuple(seg[:, 1]) for seg in bars.get_segments()] == [(52.0, 58.0), (92.0, 96.0), (98.0, 100.0)]
    assert [ln.get_ydata()[0] for ln in merge.lines if ln.get_linestyle() == "--"] == [97.3]  # the rule across
    assert not [ln for ln in crash.lines if ln.get_linestyle() == "--"]  # no reference for this metric
