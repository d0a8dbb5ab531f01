"""[perception.laser] ground_min_m with stereo-novelty's ground_for_laser: a laser return
where the scan plane runs lower than ground_min_m above the ground the camera measured this
cycle is dropped where the pipelines meet (appliance/decision.py laser_on_ground); without a
camera ground every return stays."""
import numpy as np
import pytest

from appliance.config import Config, parse_config
from appliance.decision import DecisionCore
from appliance.perception import SensorInputs
from appliance.perception.base import Detections
from appliance.perception.ground import GroundModel, fit_ground
from appliance.perception.laser import LaserPipeline, LaserPipelineConfig
from hal import LaserScan
from hal.errors import ConfigError
from hal.types import VehicleState
from tests.fakes import geometry


def _rising(rise_per_m: float) -> GroundModel:
    """A fitted ground rising ``rise_per_m`` a metre ahead (from points on it)."""
    xs, ys = np.meshgrid(np.arange(2.0, 20.0, 0.25), np.arange(-4.0, 4.0, 0.25))
    pts = np.stack([xs.ravel(), ys.ravel(), rise_per_m * xs.ravel()], 1)
    g = fit_ground(pts)
    assert g.source == "fit"
    return g


def _laser(*xs):
    pts = np.array([[x, 0.0] for x in xs], np.float32)
    return Detections(points_xy=pts, points_z=np.full(len(xs), 0.7, np.float32))


def _cfg(t):
    return parse_config({"perception": {"laser": {"ground_min_m": t}}}, "<t>")


def test_a_return_where_the_plane_runs_low_above_the_cameras_ground_is_dropped():
    g = _rising(0.05)                        # 0.2 m higher at 4 m, 0.4 m at 8 m
    dets = {"laser": _laser(4.0, 8.0), "stereo-novelty": Detections(ground=g)}
    out = DecisionCore(_cfg(0.45)).laser_on_ground(dets)["laser"]
    # at 4 m the plane is 0.5 m above that ground (kept), at 8 m 0.3 m (dropped)
    assert np.allclose(out.points_xy[:, 0], [4.0], atol=1e-6)
    assert out.debug["below_ground_min"] == 1
    # the whole cycle (single-frame cells): the dropped return makes no cell, the kept one does
    cfg = parse_config({"perception": {"laser": {"ground_min_m": 0.45}},
                        "grid": {"occupied_at": 1.0}}, "<t>")
    pic = DecisionCore(cfg).perceive(dets, VehicleState(0, 0), 0)
    xs = pic.grid_cells_xy[:, 0]
    assert np.any(np.abs(xs - 4.0) < 0.2) and not np.any(np.abs(xs - 8.0) < 0.2)


@pytest.mark.parametrize("case", ["off", "no camera ground", "level ground"])
def test_without_the_rule_or_a_cameras_ground_every_return_stays(case):
    g = _rising(0.05)
    t = 0.0 if case == "off" else 0.45
    dets = {"laser": _laser(4.0, 8.0)}
    if case == "off":
        dets["stereo-novelty"] = Detections(ground=g)
    elif case == "level ground":
        dets["stereo-novelty"] = Detections(ground=GroundModel.level())
    out = DecisionCore(_cfg(t)).laser_on_ground(dets)["laser"]
    if case == "level ground":               # the level plane: 0.7 m everywhere, kept
        assert len(out.points_xy) == 2
    else:
        assert out is dets["laser"]


def test_the_laser_pipeline_says_where_its_plane_is():
    geo = geometry()
    r = np.full(geo.beams, np.nan, np.float32)
    r[268:273] = 5.0
    det = LaserPipeline(LaserPipelineConfig()).process(SensorInputs(0, laser=LaserScan(
        0, 0, r, geo)))
    assert det.points_z is not None and np.allclose(det.points_z, geo.mount.z_m)
    # with the vehicle's attitude the points are in a gravity frame: no plane heights
    det = LaserPipeline(LaserPipelineConfig(use_attitude=True)).process(SensorInputs(
        0, laser=LaserScan(0, 0, r, geo), vehicle=VehicleState(0, 0)))
    assert det.points_z is None


def test_a_bad_ground_min_is_a_clear_config_error():
    with pytest.raises(ConfigError, match=r"ground_min_m"):
        parse_config({"perception": {"laser": {"ground_min_m": -0.1}}}, "<t>")
    assert Config().perception.laser.ground_min_m == 0.0


def test_stereo_novelty_hands_its_fitted_ground_to_the_laser_only_when_asked():
    """On a simulated field whose ground rises 0.03-0.28 m over the path 3-8 m ahead, the
    pipeline's ground (ground_for_laser) is a fit, closer to the truth there than the level
    plane; off (the default) it hands none, and its own points are the same either way."""
    import dataclasses
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.sim import SimField
    f = SimField("stubble-empty", seed=6, sensors=("stereo",), stereo_scale=0.5)
    s = f.render(0, 0)
    inputs = SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle)
    out = {}
    for on in (False, True):
        o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", ground_for_laser=on)
        pipe = StereoNoveltyPipeline(o, background=False)
        try:
            out[on] = pipe.process(inputs)
        finally:
            pipe.close()
    assert out[False].ground is None
    g = out[True].ground
    assert g is not None and g.source == "fit"
    assert np.array_equal(out[False].points_xy, out[True].points_xy)
    # against the simulator's ground, in the vehicle frame (the camera's points are)
    xs, ys = np.meshgrid(np.arange(3.0, 8.01, 0.5), np.arange(-1.0, 1.01, 0.5))
    from hal import Mount
    c0, _, rb = f._sensor_pose(Mount())              # the vehicle frame in the world
    world = c0 + np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1) @ rb.T
    true_z = f.world.ground(world[:, 0].astype(np.float32), world[:, 1].astype(np.float32))
    zb = (np.asarray(true_z, float) - world[:, 2]) / rb[2, 2]   # along the body's z axis
    err = g.z(xs.ravel(), ys.ravel()) - zb
    assert zb.max() - zb.min() > 0.2                        # the ground does rise there
    assert np.median(np.abs(err)) < 0.1 and np.median(np.abs(err)) < np.median(np.abs(zb)), (
        np.percentile(err, [10, 50, 90]), np.percentile(zb, [10, 50, 90]))


def test_a_ground_that_is_not_finite_drops_no_return():
    """A camera ground that breaks (NaN or inf heights) must never blind the laser: the
    returns it cannot judge stay obstacles."""
    class Broken:
        source = "fit"

        def z(self, x, y):
            out = np.full(np.shape(x), np.nan)
            out[1::2] = np.inf
            return out
    dets = {"laser": _laser(4.0, 8.0), "stereo-novelty": Detections(ground=Broken())}
    out = DecisionCore(_cfg(0.45)).laser_on_ground(dets)["laser"]
    assert len(out.points_xy) == 2
