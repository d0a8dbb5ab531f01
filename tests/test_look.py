"""Looking again at a held place (appliance/perception/look.py, [grid] hold_blind_look_frames):
does the camera see past a place nearer than its stereo search ranges?"""
import copy

import cv2
import numpy as np
import pytest

from appliance.config import parse_config
from appliance.decision import DecisionCore
from appliance.perception.base import Detections
from appliance.perception.look import StereoLook
from appliance.perception.view import CameraView
from hal import Mount
from hal.types import VehicleState

# the geometry of tests/test_hold_blind.py at the campaign's image size: a level camera 1.5 m
# up at x = 0.5, 640 x 512, fx 400; a point 0.5 m up is ranged from x = 3.5 (3 m along its
# axis); baseline 0.5 m
W, H = 640, 512
K = np.array([[400.0, 0, 320.0], [0, 400.0, 256.0], [0, 0, 1]])
MOUNT = Mount(x_m=0.5, y_m=0.0, z_m=1.5, pitch_deg=0.0)
B = 0.5
PLACE = 3.45                     # 2.95 m from the camera: an upright surface there: 68 px


def _texture(seed=0):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (H, W + 128)).astype(np.uint8)
    return cv2.GaussianBlur(img, (5, 5), 1.2)


def _pair(disparity_px: int | None, seed=0):
    """A rectified pair of one fronto-parallel textured surface at ``disparity_px`` (the whole
    image), or (None) a right image of other texture: matches nowhere."""
    t = _texture(seed)
    left = t[:, 0:W]
    if disparity_px is None:
        right = _texture(seed + 1)[:, 0:W]
    else:
        right = np.roll(t, -disparity_px, axis=1)[:, 0:W]       # x_right = x_left - d
    return np.ascontiguousarray(left), np.ascontiguousarray(right)


def _look(left, right, **kw):
    return StereoLook(left, right, K[0, 0], K[1, 1], K[0, 2], K[1, 2], B,
                      MOUNT.camera_to_vehicle(), MOUNT.position, **kw)


def test_a_surface_beyond_the_place_is_seen_past_and_one_at_it_is_not():
    at = int(round(400 * B / (PLACE - 0.5)))                  # 68 px
    far = _look(*_pair(20))                                   # a surface 10 m away
    s_at, s_else = far.scores(np.array([[PLACE, 0.0, 0.5]]))
    assert s_else[0] > 0.9 and s_at[0] < 0.5
    assert far.sees_past(np.array([[PLACE, 0.0], [PLACE, 0.3]])).tolist() == [True, True]
    near = _look(*_pair(at))                                  # a surface at the place
    s_at, s_else = near.scores(np.array([[PLACE, 0.0, 0.5]]))
    assert s_at[0] > 0.9
    assert near.sees_past(np.array([[PLACE, 0.0]])).tolist() == [False]


def test_what_cannot_be_told_is_not_seen_past():
    # no texture (a plain crate filling the view): no score, not seen past
    flat = np.full((H, W), 120, np.uint8)
    lk = _look(flat, flat)
    assert np.isnan(lk.scores(np.array([[PLACE, 0.0, 0.5]]))[0]).all()
    assert lk.sees_past(np.array([[PLACE, 0.0]])).tolist() == [False]
    # a right image that matches nowhere (noise under the strobe): not seen past
    assert _look(*_pair(None)).sees_past(np.array([[PLACE, 0.0]])).tolist() == [False]
    # a place whose block leaves the image (under it: 0.5 m up at x = 1.5 is below the view)
    assert _look(*_pair(20)).sees_past(np.array([[1.5, 0.0]])).tolist() == [False]


def _cfg(frames):
    return parse_config({"grid": {"hold_blind": True, "occupied_at": 1.0, "stop_recur": 0.0,
                                  "hold_blind_min_evidence": 0.0,
                                  "hold_blind_look_frames": frames}}, "<t>")


def _dets(xs, pair):
    view = CameraView({"novelty": np.zeros((H, W), np.uint8)}, K, MOUNT.camera_to_vehicle(),
                      MOUNT.position, 20.0, 0, min_depth_m=3.0,
                      stereo_look=None if pair is None else _look(*pair))
    pts = np.array([[x, 0.0] for x in xs], np.float32).reshape(-1, 2)
    return {"stereo-novelty": Detections(points_xy=pts, view=view)}


def _drive(frames, pair, cycles=12):
    """A cell confirmed 0.95 m ahead of the front, then (the vehicle rolling 0.1 m on) nearer
    than the stereo ranges; the verdict of every cycle after."""
    core, ns, out = DecisionCore(_cfg(frames)), 0, []
    for k in range(cycles + 2):
        speed = 1.0 if k < 2 else 0.0
        pic = core.perceive(_dets([3.55] if k == 0 else [], pair),
                            VehicleState(ns, ns, speed, 0.0), ns)
        ns += 100_000_000
        out.append("STOP" if pic.verdict.in_stop else "CLEAR")
    return out[1:], core


def test_a_held_cell_the_camera_sees_past_three_cycles_running_is_let_go():
    states, core = _drive(3, _pair(20))
    # held (out of the stereo's range), seen past in cycles 1, 2, 3 of the hold: let go in
    # the third
    assert states[:2] == ["STOP", "STOP"] and states[2:] == ["CLEAR"] * (len(states) - 2)
    assert len(core.held_xy) == 0


@pytest.mark.parametrize("pair", ["at the place", "no texture", None])
def test_a_held_cell_the_camera_cannot_see_past_stays_held(pair):
    at = int(round(400 * B / (PLACE - 0.5 - 0.1)))      # the vehicle rolled 0.1 m on
    p = {"at the place": _pair(at), "no texture": (np.full((H, W), 90, np.uint8),) * 2,
         None: None}[pair]
    states, core = _drive(3, p)
    assert set(states) == {"STOP"} and len(core.held_xy) == 1


def test_off_by_default_holds_as_before():
    assert parse_config({}, "<t>").grid.hold_blind_look_frames == 0
    states, _ = _drive(0, _pair(20))
    assert set(states) == {"STOP"}


# ---- on rendered frames: the chosen thresholds, training scenes -------------------------------
def _rendered_look(f):
    s = f.render(0, 0)
    fr, cal = s.stereo, s.stereo.calib
    c = cal.camera
    return StereoLook(fr.left, fr.right, c.fx, c.fy, c.cx, c.cy, cal.baseline_m,
                      cal.mount.camera_to_vehicle(), cal.mount.position)


def test_on_the_rendered_field_obstacles_are_never_seen_past_and_empty_places_are():
    """Training seed 13 of stubble-boot by day (the campaign's 640 x 512): the field's places
    1.2-1.9 m ahead of the front (2.2 m) with nothing there, and real obstacles of
    stubble-day seed 13 (a person, a crate, a dog...) set there one at a time."""
    from drivers.sim import SimField
    f = SimField("stubble-boot", seed=13, sensors=("stereo",), stereo_scale=0.5)
    pool = copy.deepcopy(SimField("stubble-day", seed=13, sensors=("stereo",),
                                  stereo_scale=0.5).world.obstacles)
    f.set_obstacles([])
    lk = _rendered_look(f)
    places = np.array([[2.2 + a, y] for a in (1.2, 1.5, 1.75, 1.9) for y in (-0.6, -0.2, 0.2, 0.6)])
    past = lk.sees_past(places)
    assert past.sum() >= 2, past                  # it does see past the empty field
    released = []
    for k, o in enumerate([o for o in pool if not o.moving][:8]):
        o.x, o.y = 2.2 + (1.2, 1.5, 1.75)[k % 3], (0.0, 0.3)[k % 2]
        f.set_obstacles([o])
        if _rendered_look(f).sees_past(np.array([[o.x - 0.3 * o.length_m, o.y], [o.x, o.y]])).any():
            released.append((o.cls, o.x))
    assert released == []
