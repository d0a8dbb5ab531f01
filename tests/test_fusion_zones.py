import numpy as np

from appliance.config import ExclusionZone, GridConfig, LaserPipelineConfig, ZonesConfig
from appliance.fusion import GridFusion
from appliance.perception import SensorInputs
from appliance.perception.laser import LaserPipeline
from appliance.zones import assess, sectors, stop_length
from hal import LaserScan, VehicleState
from tests.fakes import geometry

S = 10**9


def vs(speed=0.0, yaw_rate=0.0, pitch=0.0):
    return VehicleState(0, 0, speed_mps=speed, yaw_rate_radps=yaw_rate, pitch_rad=pitch)


def test_single_hit_is_not_enough_two_are():
    g = GridFusion(GridConfig(decay=0.5, occupied_at=1.4))
    pt = np.array([[5.05, 0.05]])
    assert len(g.update(pt, vs(), 0)) == 0
    occ = g.update(pt, vs(), S // 10)
    assert len(occ) == 1 and np.allclose(occ[0], [5.05, 0.05])
    # gone for two cycles: evidence 1.5 -> 0.75 -> 0.375: not occupied
    assert len(g.update(np.zeros((0, 2)), vs(), 2 * S // 10)) == 0


def test_single_frame_mode():
    g = GridFusion(GridConfig(occupied_at=1.0))
    assert len(g.update(np.array([[5.0, 0.0]]), vs(), 0)) == 1


def test_ego_motion_moves_world_points_back():
    g = GridFusion(GridConfig(decay=0.9, occupied_at=0.5))
    g.update(np.array([[10.05, 2.05]]), vs(), 0)
    occ = g.update(np.zeros((0, 2)), vs(speed=5.0), S)          # drove 5 m straight
    assert len(occ) == 1 and np.allclose(occ[0], [5.05, 2.05], atol=0.11)
    # turning left 90 deg/s for 1 s at standstill: a point ahead ends up on the right
    g.reset()
    g.update(np.array([[10.05, 0.05]]), vs(), 0)
    occ = g.update(np.zeros((0, 2)), vs(yaw_rate=np.pi / 2), S)
    assert len(occ) == 1 and np.allclose(occ[0], [0.05, -10.05], atol=0.15)


def test_stop_length_follows_speed():
    z = ZonesConfig(reaction_time_s=0.5, decel_mps2=2.0, margin_m=1.0, min_stop_m=2.0)
    assert stop_length(0.0, z) == 2.0
    assert abs(stop_length(4.0, z) - (2.0 + 4.0 + 1.0)) < 1e-9


def test_assess_zones_and_exclusion():
    z = ZonesConfig(front_x_m=2.0, half_width_m=1.0, min_stop_m=2.0, margin_m=0.0,
                    slow_extra_m=5.0,
                    exclusion=(ExclusionZone(2.0, 3.0, -0.5, 0.5),))
    cells = np.array([[2.5, 0.0],      # inside the exclusion box: the implement
                      [3.5, 0.3],      # stop zone (1.5 m from the front)
                      [6.0, -0.9],     # slow zone
                      [3.5, 3.0]])     # beside the path
    v = assess(cells, 0.0, z)
    assert (v.in_stop, v.in_slow) == (1, 1)
    assert abs(v.nearest_m - 1.5) < 1e-9
    v2 = assess(cells[[2, 3]], 0.0, z)
    assert v2.in_stop == 0 and v2.in_slow == 1


def test_a_cell_is_in_a_zone_when_any_part_of_it_is():
    """A 0.1 m cell centred 4 cm beyond the stop zone's end holds a hit that may be inside it
    (stubble-night 4 frame 27: the person's footprint met the stop zone by 2 cm, its nearest
    cell's centre was 4 cm beyond; the box slowed instead of stopping for one cycle)."""
    z = ZonesConfig(front_x_m=2.6, half_width_m=1.25, min_stop_m=2.0, margin_m=0.0,
                    slow_extra_m=5.0)                       # at standstill: stop zone 2.6-4.6
    beyond = np.array([[4.64, 0.0]])
    assert assess(beyond, 0.0, z).in_stop == 0              # the centre test (cell_m 0)
    v = assess(beyond, 0.0, z, cell_m=0.1)
    assert (v.in_stop, v.in_slow) == (1, 0)
    assert assess(np.array([[4.66, 0.0]]), 0.0, z, cell_m=0.1).in_stop == 0   # wholly beyond
    side = np.array([[3.5, 1.29]])                          # half a cell over the side edge
    assert assess(side, 0.0, z).in_stop == 0 and assess(side, 0.0, z, cell_m=0.1).in_stop == 1
    far = np.array([[9.64, 0.0]])                           # the slow zone ends at 9.6
    assert assess(far, 0.0, z).in_slow == 0 and assess(far, 0.0, z, cell_m=0.1).in_slow == 1


def test_sectors_body_frd():
    sec = sectors(np.array([[5.0, -1.0], [3.0, 0.01]]), n=72, fov_deg=180)
    assert len(sec) == 72
    right = [s for s in sec if s.distance_m is not None and s.angle_min_deg > 0]
    assert right and abs(right[0].distance_m - np.hypot(5, 1)) < 1e-6   # FRD: right positive


def test_laser_pipeline_geometry():
    geo = geometry()
    r = np.full(geo.beams, np.nan, np.float32)
    r[270] = 5.0            # straight ahead
    r[270 + 180] = 2.0      # +90 deg: to the left
    r[0] = 0.1              # closer than min range: dropped
    scan = LaserScan(0, 0, r, geo)
    # one beam each: the paper's pipeline keeps them (the default's min_width_m drops them)
    det = LaserPipeline(LaserPipelineConfig(min_width_m=0.0)).process(SensorInputs(0, laser=scan))
    pts = det.points_xy[np.argsort(det.points_xy[:, 0])]
    assert len(pts) == 2
    assert np.allclose(pts[1], [1.3 + 5.0, 0.0], atol=1e-4)
    assert np.allclose(pts[0], [1.3, 2.0], atol=1e-4)


def test_laser_pipeline_attitude_drops_ground_hits():
    geo = geometry()
    r = np.full(geo.beams, np.nan, np.float32)
    # pitched 5 deg nose down the beam at 0.7 m meets flat ground at 0.7/tan(5deg) = 8.0 m
    r[270] = 0.7 / np.tan(np.radians(5.0))
    scan = LaserScan(0, 0, r, geo)
    faithful = LaserPipeline(LaserPipelineConfig()).process(
        SensorInputs(0, laser=scan, vehicle=vs(pitch=np.radians(5.0))))
    assert len(faithful.points_xy) == 1          # the paper's laser calls the ground an obstacle
    better = LaserPipeline(LaserPipelineConfig(use_attitude=True, min_height_m=0.2)).process(
        SensorInputs(0, laser=scan, vehicle=vs(pitch=np.radians(5.0))))
    assert len(better.points_xy) == 0


# --- the one zone test (appliance/zones.py footprints_meet, #14) ------------------------------
STOP = {"x_min_m": 2.6, "x_max_m": 4.6, "half_width_m": 1.25}    # the stop zone at standstill


def meets(x, y, length, width, yaw_deg=0.0):
    from appliance.zones import footprint_meets
    return footprint_meets(x, y, length, width, STOP, np.radians(yaw_deg))


def test_a_footprint_meets_a_zone_when_any_part_of_it_is_inside():
    assert meets(3.5, 0.0, 0.4, 0.4)                          # wholly inside
    assert meets(4.64, 0.0, 0.1, 0.1)                         # a cell 4 cm beyond the far end
    assert meets(4.7, 0.0, 0.3, 0.3)                          # centre 10 cm beyond, edge 5 cm in
    assert not meets(4.66, 0.0, 0.1, 0.1)                     # wholly beyond: 1 cm out
    assert meets(2.57, 0.0, 0.1, 0.1)                         # centre behind the front, edge in
    assert not meets(2.54, 0.0, 0.1, 0.1)                     # behind the front
    assert meets(3.5, 1.29, 0.1, 0.1) and meets(3.5, -1.29, 0.1, 0.1)   # over the side edges
    assert not meets(3.5, 1.31, 0.1, 0.1) and not meets(3.5, -1.31, 0.1, 0.1)
    assert meets(3.5, 0.0, 0.0, 0.0) and not meets(4.61, 0.0, 0.0, 0.0)  # a point: inside or not
    big = meets(3.5, 0.0, 20.0, 20.0)                         # larger than the zone: covers it
    assert big


def test_a_footprint_that_only_touches_an_edge_does_not_meet_it():
    """The grid's cells share their edges with a zone whose ends fall on the grid (the 2.0 m
    standstill stop zone from a 2.6 m front, 0.1 m cells): a cell from 4.6 to 4.7 m holds hits
    at x >= 4.6 only; whether it counted must not depend on rounding (4.65 - 0.05 is
    4.6000000000000005)."""
    x = -2.0 + 66.5 * 0.1                                     # the grid's cell centre, 4.65
    assert not meets(x, 0.0, 0.1, 0.1)
    assert not meets(-2.0 + 45.5 * 0.1, 0.0, 0.1, 0.1)        # 2.5 .. 2.6: behind the front
    assert meets(x - 1e-6, 0.0, 0.1, 0.1)                     # a micrometre in is in


def test_a_thing_beside_the_zone_does_not_meet_it():
    assert not meets(3.5, 1.6, 0.5, 0.5)                      # its near side 1.35 m out
    assert not meets(3.5, -1.6, 0.5, 0.5)
    assert not meets(3.5, 1.6, 0.5, 0.6)                      # 1.30: 5 cm beside
    assert meets(3.5, 1.6, 0.5, 0.8)                          # 1.20: 5 cm in


def test_a_turned_footprint_meets_by_its_turned_corners_and_sides():
    # a 2.0 x 0.2 m bar beside the zone (centre 2.0 m out): along x it stays out; turned
    # across the path it reaches 1.0 m from the centre line
    assert not meets(3.5, 2.0, 2.0, 0.2, yaw_deg=0.0)
    assert meets(3.5, 2.0, 2.0, 0.2, yaw_deg=90.0)
    assert meets(3.5, 2.0, 2.0, 0.2, yaw_deg=-90.0)
    # 180 degrees is the same footprint as 0
    assert meets(4.7, 0.0, 0.3, 0.3, yaw_deg=180.0) and not meets(3.5, 2.0, 2.0, 0.2, yaw_deg=180)
    # off the zone's corner (4.6, 1.25): a thin bar along the corner's diagonal reaches in; the
    # same bar turned square to it does not, though its axis-aligned box still overlaps the
    # zone (only the footprint's own axes separate them)
    cx, cy = 4.6 + 0.4, 1.25 + 0.4
    assert meets(cx, cy, 2.0, 0.1, yaw_deg=45.0)
    assert not meets(cx, cy, 2.0, 0.1, yaw_deg=135.0)
    # a 1.0 x 1.0 m box centred 0.65 m beyond the far end: square, its edge is 0.15 m out;
    # turned 45 degrees, its corner is 0.06 m in; 0.75 m beyond and turned, 0.04 m out
    assert not meets(5.25, 0.0, 1.0, 1.0) and meets(5.25, 0.0, 1.0, 1.0, yaw_deg=45.0)
    assert not meets(5.35, 0.0, 1.0, 1.0, yaw_deg=45.0)


def test_footprints_meet_takes_one_size_and_yaw_per_footprint():
    from appliance.zones import footprints_meet
    xy = np.array([[4.7, 0.0], [4.7, 0.0], [3.5, 2.0], [3.5, 2.0]])
    got = footprints_meet(xy, [0.3, 0.1, 2.0, 2.0], [0.3, 0.1, 0.2, 0.2], STOP,
                          np.radians([0.0, 0.0, 0.0, 90.0]))
    assert got.tolist() == [True, False, False, True]
    assert footprints_meet(np.zeros((0, 2)), 0.1, 0.1, STOP).shape == (0,)


def test_the_cells_the_tracks_and_the_truth_use_the_same_zone_test():
    """The zone test was written three times (cells, tracks, truth) and they disagreed:
    the same footprints through each, against the one function."""
    from appliance.config import Config
    from appliance.decision import assess_tracks
    from appliance.evaluation import _rect_intersects
    from appliance.tracking import TrackView
    from appliance.zones import footprints_meet, zone_rects
    z = ZonesConfig()
    stop_rect, slow_rect = zone_rects(0.0, z)
    rng = np.random.default_rng(14)
    xy = np.column_stack([rng.uniform(1.5, 11.0, 400), rng.uniform(-2.0, 2.0, 400)])
    cell = GridConfig().cell_m
    want_stop = footprints_meet(xy, cell, cell, stop_rect)
    want_slow = ~want_stop & footprints_meet(xy, cell, cell, slow_rect)
    assert 20 < want_stop.sum() and 20 < want_slow.sum()
    # the cell decision, one cell at a time
    got = [(assess(p[None], 0.0, z, cell_m=cell).in_stop, assess(p[None], 0.0, z,
            cell_m=cell).in_slow) for p in xy]
    assert [a for a, _ in got] == want_stop.astype(int).tolist()
    assert [b for _, b in got] == want_slow.astype(int).tolist()
    # the track decision, footprint and cells
    cfg = Config()
    for p, s, w in zip(xy, want_stop, want_slow):
        t = TrackView(id=1, x_m=p[0], y_m=p[1], length_m=cell, width_m=cell, height_m=1.0,
                      vx_mps=0.0, vy_mps=0.0, confidence=0.9, sources=("geometry",),
                      confirmed=True, coasting=False, hits=5, age_s=1.0)
        v = assess_tracks([t], np.zeros((0, 2)), 0.0, cfg)
        assert (v.in_stop, v.in_slow) == (int(s), int(w))
        v = assess_tracks([t], p[None], 0.0, cfg, {1: p[None]})
        assert (v.in_stop, v.in_slow) == (int(s), int(w))
    # the truth side of eval
    truth = [{"x_m": p[0], "y_m": p[1], "length_m": cell, "width_m": cell} for p in xy]
    assert [_rect_intersects(o, stop_rect) for o in truth] == want_stop.tolist()


def test_grid_cells_helper_is_nonzero():
    """The grid's fast cell listing gives np.nonzero's indices in np.nonzero's order."""
    from appliance.fusion import _cells
    rng = np.random.default_rng(5)
    for frac in (0.0, 0.01, 0.5, 1.0):
        m = rng.random((320, 300)) < frac
        ix, iy = _cells(m)
        rx, ry = np.nonzero(m)
        assert np.array_equal(ix, rx) and np.array_equal(iy, ry)


def test_grid_move_equals_the_max_of_every_cell_landing_there():
    """_move's plain assignment (used when no two cells land together) and its maximum.at
    fallback give, for shifts and turns, exactly the reference: every cell with evidence goes
    to the cell its centre moves to, the larger value where two land together."""
    from appliance.config import default_config
    from appliance.fusion import GridFusion
    g = GridFusion(default_config().grid)
    rng = np.random.default_rng(11)

    def reference(grid, a, b):
        ix, iy = np.nonzero(grid)
        nij = a @ np.stack([ix, iy]).astype(np.float64) + b[:, None]
        ni, nj = np.floor(nij[0] + 0.5), np.floor(nij[1] + 0.5)
        ok = (ni >= 0) & (ni < g.nx) & (nj >= 0) & (nj < g.ny)
        out = np.zeros_like(grid)
        np.maximum.at(out, (ni[ok].astype(np.int64), nj[ok].astype(np.int64)),
                      grid[ix, iy][ok])
        return out

    for th in (0.0, 0.0, 0.02, -0.3, 1.0):
        for shift in ((-2.5, 0.0), (-0.5, 0.5), (3.0, -7.2)):
            grid = np.zeros((g.nx, g.ny), np.float32)
            m = rng.random(grid.shape) < 0.05
            grid[m] = rng.random(int(m.sum())).astype(np.float32)
            a = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
            b = np.asarray(shift, float)
            assert np.array_equal(g._move(grid, a, b), reference(grid, a, b))
