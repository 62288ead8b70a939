"""The top view's road (pure numpy on the dilemma net's geometry): lane markings solid along the road's sides,
dashed between its lanes, none where they would not be."""

from __future__ import annotations

import numpy as np

from cosim.environment.render import DASH, MARKING, SCENE_RES, draw_vehicles, lane_markings, road_view, top_view
from cosim.environment.velocity_map import rasterize_road
from cosim.sumo.roadnet import load_roadnet


def test_the_road_is_drawn_with_its_lane_markings() -> None:
    roadnet = load_roadnet("sumo_net/dilemma/dilemma.net.xml")
    raster = rasterize_road(roadnet.lane_shapes())
    # hw_in alone: lanes 0 and 1 of 3.2 m, centred at y = -4.8 and -1.6 m; the road from y = -6.4 to 0 m.
    bare, _ = road_view(raster, (100.0, 400.0))
    img, (_, _, _, y1) = road_view(raster, (100.0, 400.0), lane_markings(roadnet))
    paint = (img == MARKING).all(axis=-1)  # (H, W)
    assert not (bare == MARKING).all(axis=-1).any()

    def share(y: float) -> float:
        """The share of the view's columns with a marking within a pixel of `y` [m]."""
        row = int((y1 - y) / SCENE_RES)
        return float(paint[row - 1: row + 2].any(axis=0).mean())

    assert share(0.0) > 0.95 and share(-6.4) > 0.95  # solid along both sides
    assert abs(share(-3.2) - DASH[0] / sum(DASH)) < 0.05  # dashed between the lanes
    assert share(-4.8) == share(-1.6) == 0.0  # none along a lane's middle


def test_a_top_view_is_its_road_view_with_the_vehicles_drawn_on() -> None:
    roadnet = load_roadnet("sumo_net/dilemma/dilemma.net.xml")
    raster, markings = rasterize_road(roadnet.lane_shapes()), lane_markings(roadnet)
    x, y, heading = np.array([300.0]), np.array([-1.6]), np.array([0.0])
    length, width, colour = np.array([5.0]), np.array([1.8]), np.array([[40, 200, 60]], np.uint8)
    img, extent = top_view(raster, x, y, heading, length, width, colour, (250.0, 350.0), markings)
    road, same = road_view(raster, (250.0, 350.0), markings)
    draw_vehicles(road, same, x, y, heading, length, width, colour)
    assert same == extent and np.array_equal(img, road)
    # The car sits on lane 1, centred at x = 300 m, y = -1.6 m (+y up: row 0 is the top).
    rows, cols = np.nonzero((img == colour[0]).all(axis=-1))
    assert abs(extent[0] + (cols.mean() + 0.5) * SCENE_RES - 300.0) < SCENE_RES
    assert abs(extent[3] - (rows.mean() + 0.5) * SCENE_RES + 1.6) < SCENE_RES
