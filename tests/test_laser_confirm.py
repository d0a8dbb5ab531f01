"""[grid] laser_confirm_by: a laser return inside a camera pipeline's view makes a STOP only
where that camera confirms it (its novelty / learned / depth masks at the return's pixel, or
its own obstacle points near it); an unconfirmed one makes a SLOW. Outside every camera's
view, or without a camera this cycle, a return counts as before (appliance/decision.py,
appliance/perception/view.py)."""
import numpy as np
import pytest

from appliance.config import parse_config
from appliance.decision import DecisionCore, near_squares
from appliance.perception.base import Detections
from appliance.perception.view import CameraView
from hal import Mount
from hal.errors import ConfigError
from hal.types import VehicleState

W, H = 160, 128
K = np.array([[100.0, 0, 80.0], [0, 100.0, 64.0], [0, 0, 1]])
MOUNT = Mount(x_m=0.5, y_m=0.0, z_m=1.5, pitch_deg=0.0)


def _view(raise_at=None, name="novelty", slack=0):
    """A camera 1.5 m up, 0.5 m behind the vehicle origin, looking straight ahead; its mask
    raised in one 16-px cell round ``raise_at`` (u, v) (or nowhere)."""
    m = np.zeros((H, W), np.uint8)
    if raise_at is not None:
        u, v = raise_at
        m[max(0, v - 8):v + 8, max(0, u - 8):u + 8] = 255
    return CameraView({name: m}, K, MOUNT.camera_to_vehicle(), MOUNT.position, 20.0, slack)


def _pixel(x, y, z):
    """Where a vehicle-frame point lands in that camera, by hand: optical x = -y, y = -(z - 1.5),
    depth = x - 0.5."""
    d = x - 0.5
    return 80.0 + 100.0 * (-y) / d, 64.0 + 100.0 * (1.5 - z) / d


def test_the_view_projects_a_vehicle_frame_point_where_the_pinhole_says():
    v = _view()
    pts = np.array([[4.5, 0.0, 1.5], [4.5, 1.0, 0.7], [10.5, -2.0, 0.0]])
    u, vv, inside = v.project(pts)
    want = np.array([_pixel(*p) for p in pts])
    assert np.allclose(u, want[:, 0]) and np.allclose(vv, want[:, 1])
    assert inside.all()
    # behind the camera, beyond its range, out of the image: not in its view
    u, vv, inside = v.project(np.array([[0.0, 0.0, 0.7], [30.0, 0.0, 0.7], [2.0, 5.0, 0.7]]))
    assert not inside.any()


def test_look_reads_the_named_masks_at_the_points_pixel_with_its_slack():
    p = np.array([[4.5, 0.0, 0.7]])                 # at (80, 84)
    u, v = _pixel(*p[0])
    assert _view((int(u), int(v))).look(p, ["novelty"]) == (np.array([True]), np.array([True]))
    # another mask is not read
    ins, raised = _view((int(u), int(v)), name="depth").look(p, ["novelty", "learned"])
    assert ins[0] and not raised[0]
    # raised 20 px above: only with a slack that reaches it
    above = (int(u), int(v) - 20)
    assert not _view(above).look(p, ["novelty"])[1][0]
    assert _view(above, slack=14).look(p, ["novelty"])[1][0]


def test_masks_of_different_sizes_are_refused():
    with pytest.raises(ValueError, match="different sizes"):
        CameraView({"novelty": np.zeros((10, 10), np.uint8),
                    "learned": np.zeros((10, 12), np.uint8)}, K, np.eye(3), np.zeros(3), 10.0)


def _cfg(by=("novelty",), **grid):
    return parse_config({"grid": {"laser_confirm_by": list(by), "occupied_at": 1.0,
                                  "stop_recur": 0.0, **grid}}, "<t>")


def _laser(x, y=0.0):
    return Detections(points_xy=np.array([[x, y]], np.float32),
                      points_z=np.array([0.7], np.float32))


def _state(cfg, dets):
    core = DecisionCore(cfg)
    pic = core.perceive(dets, VehicleState(0, 0), 0)
    v = pic.verdict
    return ("STOP" if v.in_stop else "SLOW" if v.in_slow or v.slow_reason else "CLEAR"), core


def test_an_unconfirmed_laser_return_in_the_stop_zone_is_a_slow_and_a_confirmed_one_a_stop():
    x = 3.5                                          # 0.9 m beyond the front (2.6 m)
    u, v = _pixel(x, 0.0, 0.7)
    blind = {"laser": _laser(x), "stereo-novelty": Detections(view=_view())}
    seen = {"laser": _laser(x), "stereo-novelty": Detections(view=_view((int(u), int(v))))}
    state, core = _state(_cfg(), blind)
    assert state == "SLOW" and core.laser_unconfirmed == 1
    assert _state(_cfg(), seen)[0] == "STOP"
    # the rule off: the same return stops
    assert _state(_cfg(by=()), blind)[0] == "STOP"


@pytest.mark.parametrize("case", ["no camera", "camera without a view", "out of view",
                                  "beyond its range", "camera point near", "camera's own cell",
                                  "no plane heights"])
def test_returns_the_camera_cannot_judge_or_confirms_by_its_points_still_stop(case):
    x, y = 3.5, 0.0
    cam = Detections(view=_view())
    cfg = _cfg()
    laser = _laser(x, y)
    if case == "no camera":
        cam = None
    elif case == "camera without a view":
        cam = Detections()
    elif case == "out of view":                      # the camera looks the other way
        R = Mount(x_m=0.5, z_m=1.5, yaw_deg=180.0).camera_to_vehicle()
        cam = Detections(view=CameraView({"novelty": np.zeros((H, W), np.uint8)}, K, R,
                                         MOUNT.position, 20.0))
    elif case == "beyond its range":
        cam = Detections(view=CameraView({"novelty": np.zeros((H, W), np.uint8)}, K,
                                         MOUNT.camera_to_vehicle(), MOUNT.position, 2.5))
    elif case == "camera point near":                # 0.25 m aside, within a 0.3 m square's
        cfg = _cfg(by=("novelty", "points"))         # neighbours
        cam = Detections(points_xy=np.array([[x, y + 0.25]], np.float32), view=_view())
    elif case == "camera's own cell":                # the camera's point in the same cell
        cam = Detections(points_xy=np.array([[x + 0.01, y]], np.float32), view=_view())
    elif case == "no plane heights":                 # use_attitude: a gravity frame
        laser = Detections(points_xy=laser.points_xy)
    dets = {"laser": laser}
    if cam is not None:
        dets["stereo-novelty"] = cam
    state, core = _state(cfg, dets)
    assert state == "STOP", case
    assert core.laser_unconfirmed == 0 or case == "camera's own cell"


def test_a_camera_point_far_from_the_return_does_not_confirm_it():
    x = 3.5
    cam = Detections(points_xy=np.array([[x, 2.0]], np.float32), view=_view())   # beside the zone
    assert _state(_cfg(by=("points",)), {"laser": _laser(x), "stereo-novelty": cam})[0] == "SLOW"


def test_near_squares():
    a = np.array([[0.05, 0.05], [1.0, 1.0], [-0.31, 0.0]])
    b = np.array([[0.35, 0.29], [-0.05, 0.01]])
    assert near_squares(a, b, 0.3).tolist() == [True, False, True]
    assert not near_squares(a, np.zeros((0, 2)), 0.3).any()


def test_bad_settings_are_clear_config_errors():
    with pytest.raises(ConfigError, match=r"grid.laser_confirm_by.*unknown camera evidence"):
        parse_config({"grid": {"laser_confirm_by": ["colour"]}}, "<t>")
    with pytest.raises(ConfigError, match=r"cell decision only"):
        parse_config({"grid": {"laser_confirm_by": ["novelty"]},
                      "tracking": {"enabled": True}}, "<t>")
    assert parse_config({}, "<t>").grid.laser_confirm_by == ()


def test_stereo_novelty_hands_a_view_whose_masks_are_its_own():
    """On a simulated stubble frame with an obstacle, the pipeline's view holds its novelty
    mask at the descriptor resolution and projects the pipeline's own obstacle points into
    the image it saw."""
    import dataclasses
    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.sim import SimField
    f = SimField("stubble-day", seed=1, sensors=("stereo",), stereo_scale=0.5)
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="off")
    pipe = StereoNoveltyPipeline(o, background=False)
    try:
        for i in range(4):
            s = f.render(i, i * 100_000_000)
            d = pipe.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo,
                                          vehicle=s.vehicle))
    finally:
        pipe.close()
    v = d.view
    assert v is not None and "novelty" in v.masks
    assert v.masks["novelty"].shape == pipe._source_masks["novelty"].shape
    pts, px, h, keep, k = pipe.last_points
    assert keep.any()
    kd = d.debug["descriptor_factor"]
    u, vv, inside = v.project(pts[keep])
    # the pipeline's own points land on the pixels they came from (matching px -> descriptor)
    assert inside.mean() > 0.95
    err = np.hypot(u[inside] - px[keep][inside, 0] * k / kd,
                   vv[inside] - px[keep][inside, 1] * k / kd)
    assert np.median(err) < 1.0, np.percentile(err, [50, 90])


def test_a_box_set_to_confirm_its_laser_without_a_camera_still_stops_for_it():
    """The laser alone (the shipped pipelines) with laser_confirm_by set: no camera can
    confirm or refuse, so a post in the path stops the loop as before; status says how many
    returns went unconfirmed (none)."""
    from appliance.config import Config, GateConfig, GridConfig
    from hal.types import GateState
    from tests.test_decision import DT, make_loop
    cfg = Config(gate=GateConfig(hold_off_s=0.3), grid=GridConfig(laser_confirm_by=("novelty",)))
    clock, loop, laser, link = make_loop(cfg)
    for _ in range(6):
        loop.cycle()
        clock.advance(DT)
    assert loop.gate.state is GateState.CLEAR
    assert loop.status()["obstacles"]["laser_unconfirmed"] == 0
    laser.put_obstacle(4.0, 0.0)
    states = []
    for _ in range(8):
        states.append(loop.cycle().output.state)
        clock.advance(DT)
    assert states[-1] is GateState.STOP and link.sent[-1].state is GateState.STOP
    assert loop.status()["obstacles"]["laser_unconfirmed"] == 0
    # off: the key says so
    clock, loop, laser, link = make_loop(Config())
    loop.cycle()
    assert loop.status()["obstacles"]["laser_unconfirmed"] is None
