"""Stereo stages: matchers against ground-truth disparity on real Middlebury pairs, region
matching, reprojection, the height band, and both pipelines on the simulated field."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.perception import SensorInputs, make_pipeline
from appliance.perception.stereo import (StereoConfig, auto_disparities, disparity_regions,
                                         height_band, make_matcher, mask_boxes, merge_boxes,
                                         points_from_disparity)
from hal.types import Mount, PinholeCalibration, StereoCalibration

REAL = Path(__file__).parent / "data" / "real"


def _cones():
    d = REAL / "middlebury_cones"
    L = cv2.cvtColor(cv2.imread(str(d / "Cones_LEFT.tif"), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR)
    R = cv2.cvtColor(cv2.imread(str(d / "Cones_RIGHT.tif"), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR)
    gt = cv2.imread(str(d / "Cones_LEFT_GT.tif"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    vis = cv2.imread(str(d / "Occlusion_LEFT.png"), cv2.IMREAD_GRAYSCALE) > 0
    return L, R, gt, vis


def _aloe_half():
    d = REAL / "middlebury_aloe"
    L, R = (cv2.imread(str(d / f"aloe{s}.jpg")) for s in "LR")
    gt = cv2.imread(str(d / "aloeGT.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    half = lambda im: cv2.resize(im, (im.shape[1] // 2, im.shape[0] // 2),  # noqa: E731
                                 interpolation=cv2.INTER_AREA)
    gt_half = cv2.resize(gt, (gt.shape[1] // 2, gt.shape[0] // 2),
                         interpolation=cv2.INTER_NEAREST) / 2.0
    return half(L), half(R), gt_half, np.ones(gt_half.shape, bool)


@pytest.mark.parametrize("pair,nd", [("cones", 64), ("aloe", 144)])
@pytest.mark.parametrize("matcher", ["bm", "sgbm"])
def test_matcher_against_ground_truth_disparity(pair, nd, matcher):
    L, R, gt, vis = _cones() if pair == "cones" else _aloe_half()
    m = make_matcher(StereoConfig(matcher=matcher, num_disparities=nd), 1.0, 1.0)
    H, W = L.shape[:2]
    d, _ = disparity_regions(m, L, R, [(0, 0, W, H)])
    known = (gt > 0) & vis
    both = known & (d > 0)
    err = np.abs(d - gt)[both]
    assert both.sum() / known.sum() > 0.55          # dense enough
    assert (err > 2.0).mean() < 0.08                # >2 px errors (the Middlebury "bad 2")
    assert np.median(err) < 0.5


def test_region_matching_equals_full_frame_inside_the_box_and_nothing_outside():
    L, R, gt, _ = _cones()
    m = make_matcher(StereoConfig(matcher="bm", num_disparities=64), 1.0, 1.0)
    H, W = L.shape[:2]
    full, work_full = disparity_regions(m, L, R, [(0, 0, W, H)])
    box = (200, 120, 300, 220)
    part, work = disparity_regions(m, L, R, [box])
    x0, y0, x1, y1 = box
    np.testing.assert_array_equal(part[y0:y1, x0:x1], full[y0:y1, x0:x1])
    outside = np.ones((H, W), bool)
    outside[y0:y1, x0:x1] = False
    assert not part[outside].any()
    assert work < 0.35 * work_full                  # the point: far less matching


def test_boxes_from_a_mask_are_merged_and_grown():
    m = np.zeros((100, 200), np.uint8)
    m[10:20, 10:20] = 255
    m[15:30, 18:40] = 255            # touches the first: one region
    m[70:80, 150:160] = 255
    boxes = sorted(mask_boxes(m, 2))
    assert boxes == [(8, 8, 42, 32), (148, 68, 162, 82)]
    assert merge_boxes([(0, 0, 10, 10), (5, 5, 20, 20), (30, 30, 40, 40)]) == [
        (0, 0, 20, 20), (30, 30, 40, 40)]


def _calib(scale=0.5):
    cam = PinholeCalibration(int(1280 * scale), int(1024 * scale), 1100.0 * scale, 1100.0 * scale,
                             640.0 * scale, 512.0 * scale)
    return StereoCalibration(cam, 0.75, Mount(1.2, 0.0, 1.55, 0.0, 15.0, 0.0))


def _plane_disparity(calib, ground_h=0.0, wall_x=None):
    """Exact disparity of the ground plane z = ground_h (and a wall x = wall_x in front)."""
    cam = calib.camera
    R = calib.mount.camera_to_vehicle()
    t = calib.mount.position
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    rv = rays @ R.T                                   # vehicle-frame direction of each z=1 ray
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (ground_h - t[2]) / rv[..., 2]            # z-depth where the ray meets the plane
        s = np.where(s > 0, s, np.inf)
        if wall_x is not None:
            sw = (wall_x - t[0]) / rv[..., 0]
            s = np.minimum(s, np.where(sw > 0, sw, np.inf))
        return (cam.fx * calib.baseline_m / s).astype(np.float32)


def test_reprojection_puts_the_ground_at_zero_and_a_wall_where_it_is():
    c = _calib()
    d = _plane_disparity(c)
    pts, px = points_from_disparity(d, c, stride=4)
    assert len(pts) > 1000
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-6)
    d = _plane_disparity(c, wall_x=12.0)
    pts, px = points_from_disparity(d, c, stride=4)
    wall = pts[:, 2] > 0.05
    np.testing.assert_allclose(pts[wall, 0], 12.0, atol=1e-6)
    # u, v of each point are the pixel it came from
    assert np.all(px[:, 0] % 4 == 0) and np.all(px[:, 1] % 4 == 0)


def test_height_band():
    c = _calib()
    d = _plane_disparity(c, wall_x=12.0)
    pts, _ = points_from_disparity(d, c, stride=2)
    inband = height_band(pts, 0.5, 1.2)
    assert inband.any()
    z = pts[inband, 2]
    assert z.min() >= 0.5 and z.max() <= 1.2
    np.testing.assert_allclose(pts[inband, 0], 12.0, atol=1e-6)
    # ground (z = 0) and high wall are out; a short range limit drops the wall
    assert not height_band(pts, 0.5, 1.2, max_range_m=10.0).any()
    assert height_band(np.array([[5.0, 0, 0.49], [5.0, 0, 0.5], [5.0, 0, 1.2], [5.0, 0, 1.21],
                                 [-1.0, 0, 1.0]]), 0.5, 1.2).tolist() == [
        False, True, True, False, False]


def test_auto_disparities_cover_min_depth():
    o = StereoConfig(min_depth_m=5.0)
    nd = auto_disparities(o, 1100.0, 0.75)
    assert nd % 16 == 0 and nd >= 1100 * 0.75 / 5.0
    assert auto_disparities(StereoConfig(num_disparities=100), 1100.0, 0.75) == 96


# ---- the pipelines on the simulated field --------------------------------------------------
def _sim_frames(scene, n, start=0, scale=0.5):
    from drivers.sim.field import SimField
    from hal.types import GateState
    f = SimField(scene, seed=0, sensors=("stereo",), stereo_scale=scale)
    out = []
    for i in range(start + n):
        s = f.render(i * 100_000_000, i)
        if i >= start:
            out.append(s)
        f.step(0.1, GateState.CLEAR)
    return out


def _near(points, ob, r=0.6):
    from appliance.evaluation import footprint_distance
    return int((footprint_distance(points, ob) <= r).sum()) if len(points) else 0


def test_novelty_pipeline_learns_the_field_sees_the_person_and_drops_stubble():
    from appliance.config import parse_config
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                       "stereo-novelty": {"matcher": "sgbm",
                                                          "update_every_frames": 2}}})
    learn = _sim_frames("stubble-empty", 6)
    course = _sim_frames("stubble-day", 1, start=20)[0]
    nov = make_pipeline("stereo-novelty", cfg)
    plain = make_pipeline("stereo", parse_config({"perception": {"stereo": {"matcher": "sgbm"}}}))
    try:
        for s in learn:
            nov.process(SensorInputs(s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle))
            nov.novelty.wait_idle()
        assert nov.novelty.model.updates >= 3
        inp = SensorInputs(course.stereo.stamp_ns, stereo=course.stereo, vehicle=course.vehicle)
        dn = nov.process(inp)
        dp = plain.process(inp)
    finally:
        nov.close()
    person = next(o for o in course.truth if o["class"] == "person")
    assert _near(dn.points_xy, person) > 0                      # the person is still detected
    far = lambda pts: sum(  # noqa: E731
        1 for p in pts if all(_near(p[None], o, 0.5) == 0 for o in course.truth)
        and 2.0 <= p[0] <= 20.0)
    assert far(dn.points_xy) < far(dp.points_xy)                # fewer stubble points
    assert dn.debug["novel_fraction"] < 0.5
    assert dn.debug["stereo_px_fraction"] < 0.9
