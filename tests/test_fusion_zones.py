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
    det = LaserPipeline(LaserPipelineConfig()).process(SensorInputs(0, laser=scan))
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
