"""`render_mode="rgb_array"`: a top view of the scene above the first live agent's newest VelocityMap frame.

Contract: `render_scene(road, snap, mapper, cfg, agent)` returns an (H, W, 3) uint8 image; it reads only the
snapshot, the road raster and the mapper's stacks. `top_view` draws the road and the vehicles; the evaluation's
top-view figures (`cosim.evaluation.plots.top_views`) and videos (`cosim.evaluation.video`) draw through it
too, in two steps where the road stays put: `road_view` once (the road, with the lane markings of
`lane_markings` where given: solid along each edge's outer sides, dashed between its lanes), then
`draw_vehicles` on a copy per picture.
"""

from __future__ import annotations

import numpy as np

from cosim.config import ObservationConfig
from cosim.environment.velocity_map import RoadRaster, VelocityMapper
from cosim.sumo.roadnet import RoadNet
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot

BACKGROUND = (30, 30, 30)
ROAD = (110, 110, 110)
COLOURS = {KIND_AV: (40, 200, 60), KIND_HV: (60, 120, 230), KIND_MERGER: (190, 60, 200)}
CHANNEL_COLOURS = {"road": ROAD, "avs": COLOURS[KIND_AV], "hvs": COLOURS[KIND_HV], "ego_merger": (230, 80, 80)}
MARKING = (235, 235, 235)
SCENE_RES = 0.5  # [m/px]
DASH = (3.0, 9.0)  # [m] painted, then blank, along a line between two lanes (a motorway's broken line)


def render_scene(road: RoadRaster, snap: Snapshot, mapper: VelocityMapper, cfg: ObservationConfig,
                 agent: int = 0, width_px: int = 1024) -> np.ndarray:
    top = _top_view(road, snap)
    panel = _velocity_map_panel(mapper, cfg, agent)
    scale_top = width_px / top.shape[1]
    scale_vm = width_px / panel.shape[1]
    top = _resize(top, max(1, round(top.shape[0] * scale_top)), width_px)
    panel = _resize(panel, max(1, round(panel.shape[0] * scale_vm)), width_px)
    gap = np.full((4, width_px, 3), 255, dtype=np.uint8)
    return np.concatenate([top, gap, panel], axis=0)


def _top_view(road: RoadRaster, snap: Snapshot, margin: float = 25.0, min_length: float = 250.0) -> np.ndarray:
    """The road around the vehicles (at least `min_length` [m] long)."""
    x_range = None
    if len(snap):  # crop to the vehicles, so that they are not specks on a kilometre of road
        x0, x1 = snap.x.min() - margin, snap.x.max() + margin
        pad = max(0.0, min_length - (x1 - x0)) / 2
        x_range = (x0 - pad, x1 + pad)
    colours = np.array([COLOURS.get(int(k), COLOURS[KIND_HV]) for k in snap.kind], dtype=np.uint8).reshape(-1, 3)
    return top_view(road, snap.x, snap.y, snap.heading, snap.length, snap.width, colours, x_range)[0]


def top_view(road: RoadRaster, x: np.ndarray, y: np.ndarray, heading: np.ndarray, length: np.ndarray,
             width: np.ndarray, colours: np.ndarray, x_range: tuple[float, float] | None = None,
             markings: np.ndarray | None = None) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The one top-view renderer (the env's `render`, the evaluation's top-view figures and videos): the road at
    SCENE_RES between `x_range` [m] (all of it by default), cropped to the road's rows there, with `markings`
    (`lane_markings`) where given, vehicles (V,) as footprint rectangles of their `colours` (V, 3) uint8.
    Returns the (H, W, 3) uint8 image, +y up, and its extent (x0, x1, y0, y1) [m] in network coordinates."""
    img, extent = road_view(road, x_range, markings)
    draw_vehicles(img, extent, x, y, heading, length, width, colours)
    return img, extent


def road_view(road: RoadRaster, x_range: tuple[float, float] | None = None, markings: np.ndarray | None = None
              ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """`top_view` without vehicles: the (H, W, 3) uint8 road image, +y up, and its extent [m]."""
    step = max(1, round(SCENE_RES / road.resolution))
    grid = road.grid[::step, ::step] != 0
    res = road.resolution * step
    ox, oy = road.origin
    if x_range is not None:
        j0 = max(0, int((x_range[0] - ox) / res))
        j1 = min(grid.shape[1], int((x_range[1] - ox) / res) + 1)
        rows = np.flatnonzero(grid[:, j0:j1].any(axis=1))
        i0, i1 = (max(0, rows[0] - 4), rows[-1] + 5) if rows.size else (0, grid.shape[0])
        grid = grid[i0:i1, j0:j1]
        ox, oy = ox + j0 * res, oy + i0 * res
    img = np.empty(grid.shape + (3,), dtype=np.uint8)
    img[:] = BACKGROUND
    img[grid] = ROAD
    ny, nx = grid.shape
    if markings is not None and len(markings):
        j, i = np.floor((markings - (ox, oy)) / res).astype(np.int64).T
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        img[i[ok], j[ok]] = MARKING
    return img[::-1], (ox, ox + nx * res, oy, oy + ny * res)


def draw_vehicles(img: np.ndarray, extent: tuple[float, float, float, float], x: np.ndarray, y: np.ndarray,
                  heading: np.ndarray, length: np.ndarray, width: np.ndarray, colours: np.ndarray) -> None:
    """Draw vehicles (V,) into `road_view`'s `img` of `extent`, in place, as `top_view` says."""
    ox, x1, oy, _ = extent
    ny, nx = img.shape[:2]
    res = (x1 - ox) / nx
    for k in range(len(x)):
        c, s = np.cos(heading[k]), np.sin(heading[k])
        along = np.arange(-length[k] / 2, length[k] / 2 + 1e-9, res / 2)
        across = np.arange(-width[k] / 2, width[k] / 2 + 1e-9, res / 2)
        a, b = np.meshgrid(along, across)
        j = ((x[k] + a * c - b * s - ox) / res).astype(int)
        i = ((y[k] + a * s + b * c - oy) / res).astype(int)
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        img[ny - 1 - i[ok], j[ok]] = colours[k]  # row 0 is the top: +y up


def lane_markings(road: RoadNet, spacing: float = SCENE_RES / 2) -> np.ndarray:
    """(P, 2) [m] points, `spacing` apart, of every edge's lane markings: a solid line along its outer sides (the
    right side of lane 0, the left of its last lane), a dashed one (`DASH`) between neighbouring lanes; each
    line is its lane's centre line offset by half the lane's width. Compute it once per net and pass it to
    `road_view` or `top_view`."""
    points = []
    for edge in road.edges.values():
        last = len(edge.lanes) - 1
        for lane in edge.lanes:
            if lane.index == 0:
                points.append(_sample(_offset(lane.shape, -lane.width / 2), spacing, dashed=False))
            points.append(_sample(_offset(lane.shape, lane.width / 2), spacing, dashed=lane.index < last))
    return np.concatenate(points) if points else np.zeros((0, 2))


def _offset(line: np.ndarray, d: float) -> np.ndarray:
    """(K, 2) `line` moved `d` [m] to its left (negative: right), each point along its segments' mean normal."""
    seg = np.diff(line, axis=0)  # (K-1, 2)
    normal = np.stack([-seg[:, 1], seg[:, 0]], axis=1) / np.maximum(np.hypot(*seg.T), 1e-9)[:, None]
    at = np.concatenate([normal[:1], normal[:-1] + normal[1:], normal[-1:]])  # (K, 2) per point
    return line + d * at / np.maximum(np.hypot(*at.T), 1e-9)[:, None]


def _sample(line: np.ndarray, spacing: float, dashed: bool) -> np.ndarray:
    """Points along `line`, `spacing` [m] apart; where `dashed`, only those on the painted part of each dash."""
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])  # (K,) [m]
    at = np.arange(0.0, arc[-1], spacing)
    if dashed:
        at = at[at % sum(DASH) < DASH[0]]
    return np.stack([np.interp(at, arc, line[:, 0]), np.interp(at, arc, line[:, 1])], axis=1)


def _velocity_map_panel(mapper: VelocityMapper, cfg: ObservationConfig, agent: int) -> np.ndarray:
    """The newest frame of the agent's stack, channels blended by colour."""
    frame = mapper.observation(agent)[-1].astype(np.float32) / mapper.high  # (C, H, W)
    img = np.zeros(frame.shape[1:] + (3,), dtype=np.float32)
    img[:] = BACKGROUND
    for ch, name in enumerate(cfg.channels):
        on = frame[ch] > 0
        colour = np.asarray(CHANNEL_COLOURS[name], dtype=np.float32)
        weight = np.clip(frame[ch], 0.3, 1.0)[..., None] if name != "road" else 1.0
        img[on] = (colour * weight)[on] if name != "road" else colour
    return img.astype(np.uint8)


def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize (no imaging dependency)."""
    rows = np.minimum((np.arange(h) * img.shape[0] / h).astype(int), img.shape[0] - 1)
    cols = np.minimum((np.arange(w) * img.shape[1] / w).astype(int), img.shape[1] - 1)
    return img[rows][:, cols]
