"""VelocityMap rendering and stacking on hand-built snapshots (pure numpy, no SUMO).

The default preset is used throughout: a 128 m x 32 m window of 128 x 32 pixels, so a pixel is 1 m x 1 m,
the ego (at the window's middle) sits on the boundary between w = 63 and w = 64 and between h = 15 and 16.
A vehicle centre at (u ahead, lat to the left) [m] is in pixel (h, w) = (floor(16 - lat), floor(64 + u)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.config import ObservationConfig
from cosim.environment.velocity_map import RoadRaster, VelocityMapper, rasterize_road
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot

CH = {name: i for i, name in enumerate(("road", "avs", "hvs", "ego_merger"))}  # default channel order


def no_road() -> RoadRaster:
    return RoadRaster(grid=np.zeros((4, 4), dtype=bool), origin=(-1.0, -1.0), resolution=0.5)


def straight_road(width: float = 3.6) -> RoadRaster:
    """One lane along the x axis, centred on y = 0, from x = -200 to 200 m."""
    return rasterize_road([(np.array([[-200.0, 0.0], [200.0, 0.0]]), width)])


def scene(turn: float = 0.0, hv_x: float = 20.0) -> Snapshot:
    """Ego at the origin heading +x at 20 m/s; an HV ahead in its lane at 20 m/s; an AV behind in the lane
    to the right at 35 m/s; the merging vehicle ahead-right at 15 m/s. `turn` [rad] rotates the whole scene
    about the origin."""
    x = np.array([0.0, hv_x, -30.0, 10.0])
    y = np.array([0.0, 0.0, -3.2, -6.4])
    c, s = math.cos(turn), math.sin(turn)
    return Snapshot.build(
        ids=["ego", "hv", "av", "merger"],
        kind=[KIND_AV, KIND_HV, KIND_AV, KIND_MERGER],
        x=c * x - s * y,
        y=s * x + c * y,
        heading=np.array([0.0, 0.0, 0.0, 0.0]) + turn,
        speed=[20.0, 20.0, 35.0, 15.0],
    )


def mapper(road: RoadRaster | None = None, n_agents: int = 1, **obs) -> VelocityMapper:
    # speed_scale in m/s, as an env resolves it on its net (cosim.sumo.resolve)
    return VelocityMapper(ObservationConfig(**{"speed_scale": 15.0, **obs}), road if road is not None else no_road(),
                          n_agents)


def frame(snap: Snapshot, rows: list[int], agent: int = 0, road: RoadRaster | None = None,
          **obs) -> np.ndarray:
    """The newest (C, H, W) frame of `agent` after one update of a fresh mapper."""
    m = mapper(road, len(rows), **obs)
    m.update(snap, np.array(rows))
    return np.array(m.observation(agent)[-1])


def box(h0: int, h1: int, w0: int, w1: int, shape: tuple[int, int] = (32, 128)) -> np.ndarray:
    out = np.zeros(shape, dtype=bool)
    out[h0 : h1 + 1, w0 : w1 + 1] = True
    return out


def test_hand_placed_scene_has_the_expected_pixels() -> None:
    f = frame(scene(), [0])
    assert f.shape == (4, 32, 128) and f.dtype == np.float32
    # HV: u in [17.5, 22.5] -> w 81..86; lat in [-0.9, 0.9] -> h 15..16; same speed -> 0.5.
    hvs = f[CH["hvs"]]
    np.testing.assert_array_equal(hvs != 0, box(15, 16, 81, 86))
    np.testing.assert_array_equal(hvs[hvs != 0], 0.5)
    # AV behind, right lane: u in [-32.5, -27.5] -> w 31..36; lat in [-4.1, -2.3] -> h 18..20;
    # 15 m/s faster with speed_scale 15 -> 1.0. The ego (also an AV) is not in avs.
    avs = f[CH["avs"]]
    np.testing.assert_array_equal(avs != 0, box(18, 20, 31, 36))
    np.testing.assert_array_equal(avs[avs != 0], 1.0)
    # ego_merger: the ego at 1.0 around the centre, the merger (u 7.5..12.5, lat -7.3..-5.5) at
    # 0.5 + 0.5 * (15 - 20) / 15.
    em = f[CH["ego_merger"]]
    np.testing.assert_array_equal(em != 0, box(15, 16, 61, 66) | box(21, 23, 71, 76))
    np.testing.assert_array_equal(em[box(15, 16, 61, 66)], 1.0)
    np.testing.assert_allclose(em[box(21, 23, 71, 76)], 0.5 + 0.5 * -5 / 15, rtol=1e-6)
    assert em[15, 63] == em[16, 64] == 1.0
    # The merger is not a human vehicle; with no road raster the road channel is empty.
    assert not hvs[21:24, 71:77].any()
    assert not f[CH["road"]].any()


def test_relative_speed_is_clipped_and_never_zero() -> None:
    snap = Snapshot.build(ids=["ego", "slow", "fast"], kind=[KIND_AV, KIND_HV, KIND_HV],
                          x=[0.0, 20.0, -20.0], speed=[30.0, 0.0, 60.0])
    hvs = frame(snap, [0])[CH["hvs"]]
    assert np.isclose(hvs[15, 84], 1 / 255)  # 30 m/s slower: 0.5 - 1.0, clipped up to the smallest non-zero
    assert hvs[15, 44] == 1.0


def test_heading_alignment_rotated_scene_gives_the_same_frame() -> None:
    base = frame(scene(), [0])
    for turn in (math.pi / 2, -math.pi / 2, math.pi, 0.3):
        np.testing.assert_array_equal(frame(scene(turn), [0]), base, err_msg=f"turn {turn}")


def test_vehicle_to_the_left_appears_at_smaller_h() -> None:
    snap = Snapshot.build(ids=["ego", "left", "right"], kind=[KIND_AV, KIND_HV, KIND_HV],
                          x=[0.0, 10.0, 10.0], y=[0.0, 3.2, -3.2], speed=[20.0] * 3)
    hvs = frame(snap, [0])[CH["hvs"]]
    np.testing.assert_array_equal(hvs != 0, box(11, 13, 71, 76) | box(18, 20, 71, 76))
    # The same for an ego heading +y: "left" is then -x.
    turned = Snapshot.build(ids=["ego", "left", "right"], kind=[KIND_AV, KIND_HV, KIND_HV],
                            x=[0.0, -3.2, 3.2], y=[0.0, 10.0, 10.0], heading=[math.pi / 2] * 3,
                            speed=[20.0] * 3)
    np.testing.assert_array_equal(frame(turned, [0])[CH["hvs"]], hvs)


def test_rotated_footprint_covers_its_pixels() -> None:
    # A ramp vehicle at 30 degrees: every pixel whose centre lies inside its rectangle is drawn, and every
    # drawn pixel touches the rectangle (its centre is within half a pixel diagonal of it).
    cx, cy, th, ln, wd = 12.3, -5.1, math.radians(30), 5.0, 1.8
    snap = Snapshot.build(ids=["ego", "ramp"], kind=[KIND_AV, KIND_MERGER], x=[0.0, cx], y=[0.0, cy],
                          heading=[0.0, th], length=[5.0, ln], width=[1.8, wd], speed=[20.0, 20.0])
    em = frame(snap, [0])[CH["ego_merger"]]
    h, w = np.mgrid[0:32, 0:128]
    px, py = w + 0.5 - 64.0, 16.0 - (h + 0.5)  # pixel centres in the ego frame [m]
    along = (px - cx) * math.cos(th) + (py - cy) * math.sin(th)
    across = -(px - cx) * math.sin(th) + (py - cy) * math.cos(th)
    inside = (np.abs(along) <= ln / 2) & (np.abs(across) <= wd / 2)
    gap = np.hypot(np.maximum(np.abs(along) - ln / 2, 0), np.maximum(np.abs(across) - wd / 2, 0))
    drawn = em > 0
    drawn[14:18, 60:68] = False  # the ego
    assert inside.sum() > 5
    assert drawn[inside].all()
    assert (gap[drawn] <= math.sqrt(0.5) + 1e-9).all()


def test_vehicles_outside_the_window_are_not_drawn_nor_observed() -> None:
    snap = Snapshot.build(
        ids=["ego", "far_ahead", "far_left", "behind", "edge_in", "edge_out"],
        kind=[KIND_AV, KIND_HV, KIND_HV, KIND_AV, KIND_HV, KIND_HV],
        x=[0.0, 100.0, 0.0, -80.0, 63.0, 66.0], y=[0.0, 0.0, 20.0, 0.0, 0.0, 0.0], speed=[20.0] * 6,
    )
    f = frame(snap, [0])
    drawn_w = np.flatnonzero(f[CH["hvs"]].any(axis=0))
    # edge_in (centre at w = 127) covers w 124..127; edge_out's centre is outside but its rear reaches w 127.
    np.testing.assert_array_equal(drawn_w, [124, 125, 126, 127])
    assert not f[CH["avs"]].any()
    m = mapper()
    np.testing.assert_array_equal(m.observed(snap, np.array([0])),
                                  [[False, False, False, False, True, False]])


def test_observed_excludes_ego_and_absent_agents() -> None:
    snap = scene()
    m = mapper(n_agents=3)
    seen = m.observed(snap, np.array([0, -1, 2]))
    assert seen.shape == (3, 4)
    np.testing.assert_array_equal(seen[0], [False, True, True, True])
    assert not seen[1].any()
    np.testing.assert_array_equal(seen[2], [True, True, False, True])  # the AV behind sees everyone


def test_observed_after_an_update_answers_for_the_rows_asked_not_the_rows_drawn() -> None:
    # The env asks `observed` right after `update` on the same snapshot: the frames made there are reused, and
    # only for those rows.
    snap = scene()
    m = mapper(n_agents=3)
    m.update(snap, np.array([0, -1, 2]))
    np.testing.assert_array_equal(m.observed(snap, np.array([0, -1, 2])),
                                  mapper(n_agents=3).observed(snap, np.array([0, -1, 2])))
    np.testing.assert_array_equal(m.observed(snap, np.array([2, 0, -1])),
                                  mapper(n_agents=3).observed(snap, np.array([2, 0, -1])))
    moved = scene(hv_x=200.0)  # the HV out of every window
    m.update(moved, np.array([0, -1, 2]))
    assert not m.observed(moved, np.array([0, -1, 2]))[:, 1].any()


def test_other_agents_see_each_other_in_avs() -> None:
    m = mapper(n_agents=2)
    m.update(scene(), np.array([0, 2]))
    behind = m.observation(1)[-1]
    # From the AV 30 m behind and 3.2 m right: the ego agent is 30 m ahead, 3.2 m left, 15 m/s slower.
    avs = behind[CH["avs"]]
    np.testing.assert_array_equal(avs != 0, box(11, 13, 91, 96))
    np.testing.assert_allclose(avs[avs != 0], 1 / 255, rtol=1e-6)  # 0.5 - 0.5, clipped to non-zero
    np.testing.assert_array_equal(behind[CH["ego_merger"]][15:17, 61:67], 1.0)


def moving_snaps(n: int) -> list[Snapshot]:
    """An HV 10 m further ahead at each step, and a second agent that leaves at step 4."""
    snaps = []
    for k in range(n):
        ids = ["ego", "hv"] + (["av2"] if k < 4 else [])
        snaps.append(Snapshot.build(ids=ids, kind=[KIND_AV, KIND_HV, KIND_AV][: len(ids)],
                                    x=[0.0, 5.0 + 10 * k, -20.0][: len(ids)], y=[0.0, 0.0, 3.2][: len(ids)],
                                    speed=[20.0, 22.0, 18.0][: len(ids)]))
    return snaps


def test_stack_is_oldest_to_newest_and_matches_each_frame_written() -> None:
    road = straight_road()
    m = mapper(road, n_agents=2)
    snaps = moving_snaps(3)
    for snap in snaps:
        m.update(snap, snap.rows_of(["ego", "av2"]))
    stack = m.observation(0)
    assert stack.shape == (5, 4, 32, 128)
    assert not stack[:2].any()  # only 3 frames so far
    hv_w = [np.flatnonzero(stack[i, CH["hvs"]].any(axis=0)).min() for i in (2, 3, 4)]
    assert hv_w == [66, 76, 86]  # oldest -> newest: the HV moves ahead
    for i, snap in enumerate(snaps):
        for agent in (0, 1):
            expected = frame(snap, list(snap.rows_of(["ego", "av2"])), agent=agent, road=road)
            np.testing.assert_array_equal(m.observation(agent)[2 + i], expected)


def test_ring_wraps_and_clears_old_pixels() -> None:
    # More updates than frames: every stacked frame equals a fresh render of its snapshot, so the cleared
    # slots hold nothing stale; agent 1 leaves the simulation at step 4 and gets zero frames after.
    road = straight_road()
    m = mapper(road, n_agents=2)
    snaps = moving_snaps(12)
    fresh = []
    for snap in snaps:
        rows = snap.rows_of(["ego", "av2"])
        m.update(snap, rows)
        fresh.append([frame(snap, list(rows), agent=a, road=road) for a in (0, 1)])
        k = len(fresh)
        for agent in (0, 1):
            stack = m.observation(agent)
            for i in range(5):
                j = k - 5 + i
                expected = fresh[j][agent] if j >= 0 else np.zeros((4, 32, 128), np.float32)
                np.testing.assert_array_equal(stack[i], expected, err_msg=f"step {k} agent {agent} frame {i}")
    assert not m.observation(1).any()  # absent for the last 8 steps, road included


def test_observation_is_a_read_only_view() -> None:
    m = mapper(n_agents=1)
    m.update(scene(), np.array([0]))
    obs = m.observation(0)
    assert not obs.flags.writeable and not obs.flags.owndata
    with pytest.raises(ValueError):
        obs[0, 0, 0, 0] = 1.0


def test_reset_zeros_every_stack() -> None:
    m = mapper(straight_road(), n_agents=2)
    for snap in moving_snaps(3):
        m.update(snap, snap.rows_of(["ego", "av2"]))
    assert m.observation(0).any()
    m.reset()
    assert not m.observation(0).any() and not m.observation(1).any()
    snap = moving_snaps(1)[0]
    m.update(snap, snap.rows_of(["ego", "av2"]))
    assert not m.observation(0)[:-1].any() and m.observation(0)[-1].any()


def test_absent_agent_gets_a_zero_frame() -> None:
    m = mapper(straight_road(), n_agents=2)
    m.update(scene(), np.array([0, -1]))
    assert m.observation(0)[-1].any()
    assert not m.observation(1).any()


def test_wrong_number_of_rows_is_an_error() -> None:
    with pytest.raises(ValueError, match="ego_rows"):
        mapper(n_agents=2).update(scene(), np.array([0]))


def test_road_channel_marks_the_lane() -> None:
    # Lane half-width 1.8 m: pixel centres at lat +-0.5 and +-1.5 m (h 14..17) are on it, +-2.5 m are not.
    ego = Snapshot.build(ids=["ego"], kind=[KIND_AV], x=[0.0], y=[0.0], speed=[20.0])
    road = frame(ego, [0], road=straight_road())[CH["road"]]
    np.testing.assert_array_equal(road, box(14, 17, 0, 127))
    # An ego heading +y on a lane along y sees the same; one heading +x across it sees a band along w.
    along_y = rasterize_road([(np.array([[0.0, -200.0], [0.0, 200.0]]), 3.6)])
    turned = Snapshot.build(ids=["ego"], kind=[KIND_AV], heading=[math.pi / 2])
    np.testing.assert_array_equal(frame(turned, [0], road=along_y)[CH["road"]], road)
    across = frame(ego, [0], road=along_y)[CH["road"]]
    np.testing.assert_array_equal(across, box(0, 31, 62, 65))


def test_road_channel_off_the_raster_is_off_road() -> None:
    # The window reaches past the raster's edge (and the ego itself is off it): nothing wraps around.
    short = rasterize_road([(np.array([[0.0, 0.0], [20.0, 0.0]]), 3.6)], margin=2.0)
    for x in (0.0, 60.0, -200.0, 5000.0):
        ego = Snapshot.build(ids=["ego"], kind=[KIND_AV], x=[x])
        road = frame(ego, [0], road=short)[CH["road"]]
        w = np.arange(128) + 0.5 - 64.0 + x  # pixel-centre world x
        expected = box(14, 17, 0, 127) & ((w >= -1.8) & (w <= 21.8))[None, :]
        on = (w > -1.5) & (w < 21.5)  # clear of the rounded ends
        np.testing.assert_array_equal(road[:, on], expected[:, on], err_msg=f"ego x {x}")
        assert not road[:14].any() and not road[18:].any()


def test_uint8_stores_255_scaled_values() -> None:
    f32 = frame(scene(), [0], road=straight_road())
    u8 = frame(scene(), [0], road=straight_road(), dtype="uint8")
    assert u8.dtype == np.uint8
    np.testing.assert_array_equal(u8, np.round(f32.astype(np.float64) * 255).astype(np.uint8))
    assert u8[CH["hvs"], 15, 84] == 128 and u8[CH["avs"], 19, 33] == 255 and u8[CH["road"], 15, 0] == 255
    m = mapper(dtype="uint8")
    assert m.high == 255 and m.dtype == np.uint8
    assert mapper(dtype="float16").high == 1.0


def test_channel_subset_and_order_follow_the_config() -> None:
    full = frame(scene(), [0], road=straight_road())
    sub = frame(scene(), [0], road=straight_road(), channels=("ego_merger", "road", "hvs"))
    assert sub.shape == (3, 32, 128)
    for i, name in enumerate(("ego_merger", "road", "hvs")):
        np.testing.assert_array_equal(sub[i], full[CH[name]], err_msg=name)
    # Without ego_merger neither the ego nor the merger is drawn anywhere (the ego is never an "other AV").
    only = frame(scene(), [0], channels=("avs", "hvs"))
    np.testing.assert_array_equal(only[0], full[CH["avs"]])
    np.testing.assert_array_equal(only[1], full[CH["hvs"]])


def test_paper_preset_shape_and_pixel_size() -> None:
    m = mapper(preset="paper")
    assert m.shape == (10, 4, 64, 512)
    m.update(scene(hv_x=19.9), np.array([0]))
    hvs = np.array(m.observation(0)[-1, CH["hvs"]])
    # 0.5 m pixels, ego at w 256 / h 32: the HV spans u 17.4..22.4 -> w 290..300, lat +-0.9 -> h 30..33.
    np.testing.assert_array_equal(hvs != 0, box(30, 33, 290, 300, shape=(64, 512)))


def test_rasterize_curved_polyline_marks_cells_within_half_width() -> None:
    # A quarter circle of radius 50 m as a 40-point polyline, lane width 4 m.
    ang = np.linspace(0.0, math.pi / 2, 40)
    poly = np.stack([50 * np.cos(ang), 50 * np.sin(ang)], axis=1)
    r = rasterize_road([(poly, 4.0)], resolution=0.5, margin=5.0)
    ny, nx = r.grid.shape
    cx = r.origin[0] + (np.arange(nx) + 0.5) * r.resolution
    cy = r.origin[1] + (np.arange(ny) + 0.5) * r.resolution
    px, py = np.meshgrid(cx, cy)  # (Ny, Nx) cell centres
    # Brute-force distance from every cell centre to every segment.
    a, b = poly[:-1], poly[1:]
    d = b - a
    rel = np.stack([px, py], axis=-1)[..., None, :] - a  # (Ny, Nx, S, 2)
    t = np.clip((rel * d).sum(-1) / (d * d).sum(-1), 0, 1)
    dist = np.linalg.norm(rel - t[..., None] * d, axis=-1).min(axis=-1)
    np.testing.assert_array_equal(r.grid, dist <= 2.0)
    # And against the true arc: well inside the band is road, well outside is not.
    radius = np.hypot(px, py)
    in_quadrant = (px > 0) & (py > 0)
    assert r.grid[in_quadrant & (np.abs(radius - 50) < 1.8)].all()
    assert not r.grid[np.abs(radius - 50) > 2.2].any()
    assert r.sample(np.array([50.0, 0.0, 35.36]), np.array([0.0, 0.0, 35.36])).tolist() == [True, False, True]


# --- randomized reference: the vectorised renderer against a slow per-pixel one ------------------------------


def _pixel_centres(cfg: ObservationConfig) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) ego-frame coordinates of every pixel centre [m]: along the heading, to the left."""
    h, w = cfg.height_px, cfg.width_px
    px_l, px_w = cfg.length_m / w, cfg.width_m / h
    along = (np.arange(w) + 0.5) * px_l - cfg.ego_at * cfg.length_m
    left = cfg.width_m / 2 - (np.arange(h) + 0.5) * px_w
    return np.broadcast_to(along[None, :], (h, w)), np.broadcast_to(left[:, None], (h, w))


def _in_rect(px: float, py: float, cx: float, cy: float, heading: float, length: float, width: float,
             grow: float = 0.0) -> bool:
    """Whether point (px, py) lies in the rectangle (centre, heading, length x width), grown by `grow` [m]."""
    dx, dy = px - cx, py - cy
    a = dx * math.cos(heading) + dy * math.sin(heading)
    b = -dx * math.sin(heading) + dy * math.cos(heading)
    return abs(a) <= length / 2 + grow and abs(b) <= width / 2 + grow


@pytest.mark.parametrize("seed", range(6))
def test_renderer_matches_a_per_pixel_reference_on_random_scenes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cfg = ObservationConfig(preset="default", width_px=64, length_m=100.0, ego_at=float(rng.uniform(0.3, 0.7)),
                            speed_scale=15.0)
    road = rasterize_road([(np.array([[-300.0, 3.0 * k], [300.0, 3.0 * k + rng.uniform(-20, 20)]]), 3.4)
                           for k in range(-2, 3)])
    n = 14
    snap = Snapshot.build(ids=[f"v{i}" for i in range(n)], kind=rng.integers(0, 3, n),
                          x=rng.uniform(-60, 60, n), y=rng.uniform(-14, 14, n), heading=rng.uniform(-0.6, 0.6, n),
                          speed=rng.uniform(0, 40, n), length=rng.uniform(3, 16, n), width=rng.uniform(1.5, 2.6, n))
    egos = [0, 1, 2]
    m = VelocityMapper(cfg, road, len(egos))
    m.update(snap, np.array(egos))
    along, left = _pixel_centres(cfg)
    px_l, px_w = cfg.length_m / cfg.width_px, cfg.width_m / cfg.height_px
    half_diag = 0.5 * math.hypot(px_l, px_w)
    channel_of_kind = {KIND_AV: CH["avs"], KIND_HV: CH["hvs"], KIND_MERGER: CH["ego_merger"]}
    for agent, e in enumerate(egos):
        got = np.array(m.observation(agent)[-1])
        c, s = math.cos(snap.heading[e]), math.sin(snap.heading[e])
        wx = snap.x[e] + along * c - left * s  # (H, W) world position of every pixel centre
        wy = snap.y[e] + along * s + left * c
        # Road: the raster's nearest cell under each pixel centre, except within float32 rounding of a cell edge.
        want_road = road.sample(wx, wy)
        fx = (wx - road.origin[0]) / road.resolution
        fy = (wy - road.origin[1]) / road.resolution
        on_edge = (np.abs(fx - np.round(fx)) < 1e-2) | (np.abs(fy - np.round(fy)) < 1e-2)
        assert np.array_equal((got[CH["road"]] > 0)[~on_edge], want_road[~on_edge])
        # Vehicles: a pixel whose centre lies inside a footprint shows that vehicle in its channel with its
        # relative-speed value, unless another vehicle of that channel touches the pixel too (which of them is
        # drawn is not specified); a lit pixel must touch some footprint of its channel.
        chan = [CH["ego_merger"] if v == e else channel_of_kind[int(snap.kind[v])] for v in range(n)]
        rects = [(snap.x[v], snap.y[v], snap.heading[v], snap.length[v], snap.width[v]) for v in range(n)]
        for h in range(cfg.height_px):
            for w in range(cfg.width_px):
                inside = [v for v in range(n) if _in_rect(wx[h, w], wy[h, w], *rects[v])]
                near = [v for v in range(n) if _in_rect(wx[h, w], wy[h, w], *rects[v], grow=half_diag)]
                for v in inside:
                    if any(o != v and chan[o] == chan[v] for o in near):
                        continue
                    value = 1.0 if v == e else float(np.clip(0.5 + 0.5 * (snap.speed[v] - snap.speed[e]) /
                                                             cfg.speed_scale, 1 / 255, 1.0))
                    assert got[chan[v], h, w] == pytest.approx(value, abs=1e-6), (agent, v, h, w)
                for ch in (CH["avs"], CH["hvs"], CH["ego_merger"]):
                    if got[ch, h, w] > 0:
                        assert any(chan[v] == ch for v in near), (agent, ch, h, w)
