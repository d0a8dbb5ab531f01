"""Stereo stages: matchers against ground-truth disparity on real Middlebury pairs, region
matching, reprojection, the height band, and both pipelines on the simulated field."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.perception import SensorInputs, make_pipeline
from appliance.perception.stereo import (StereoConfig, auto_disparities, dedupe_cells,
                                         disparity_regions, downscale, ground_search_range,
                                         height_band, make_matcher, mask_boxes, match_factor,
                                         merge_boxes, merge_strips, points_from_disparity, scaled_calibration,
                                         strip_boxes)
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


try:
    import elas  # noqa: F401  (optional, GPLv3: tools/install_elas.sh)
    HAVE_ELAS = True
except ImportError:
    HAVE_ELAS = False
ELAS = pytest.param("elas", marks=pytest.mark.skipif(
    not HAVE_ELAS, reason="pyelas (optional, GPLv3) not installed: tools/install_elas.sh"))


@pytest.mark.parametrize("pair,nd", [("cones", 64), ("aloe", 144)])
@pytest.mark.parametrize("matcher", ["bm", "sgbm", ELAS])
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


def _cones_full_and_box(matcher: str, box=(200, 120, 300, 220)):
    """Cones matched over the whole frame and over ``box`` alone: (full, work_full), (part,
    work), box."""
    L, R, _, _ = _cones()
    m = make_matcher(StereoConfig(matcher=matcher, num_disparities=64), 1.0, 1.0)
    H, W = L.shape[:2]
    return disparity_regions(m, L, R, [(0, 0, W, H)]), disparity_regions(m, L, R, [box]), box


def test_region_matching_equals_full_frame_inside_the_box_and_nothing_outside():
    (full, work_full), (part, work), box = _cones_full_and_box("bm")
    H, W = full.shape
    x0, y0, x1, y1 = box
    np.testing.assert_array_equal(part[y0:y1, x0:x1], full[y0:y1, x0:x1])
    outside = np.ones((H, W), bool)
    outside[y0:y1, x0:x1] = False
    assert not part[outside].any()
    assert work < 0.35 * work_full                  # the point: far less matching


def test_region_matching_with_a_shifted_range_agrees_with_ground_truth_and_full_range():
    L, R, gt, vis = _cones()
    m = make_matcher(StereoConfig(matcher="bm", num_disparities=64), 1.0, 1.0)
    H, W = L.shape[:2]
    full, _ = disparity_regions(m, L, R, [(0, 0, W, H)])
    box = (200, 120, 300, 220)
    x0, y0, x1, y1 = box
    g = gt[y0:y1, x0:x1]
    lo, hi = g[g > 0].min(), g[g > 0].max()
    dmin = int(lo) - 3
    n = int(np.ceil((hi + 3 - dmin) / 16.0)) * 16
    assert dmin > 0 and n < 64
    part, work = disparity_regions(m, L, R, [box], [(dmin, n)])
    _, work_full = disparity_regions(m, L, R, [box])
    p, f = part[y0:y1, x0:x1], full[y0:y1, x0:x1]
    known = (g > 0) & vis[y0:y1, x0:x1]
    both = known & (p > 0)
    assert both.sum() > 0.5 * known.sum()
    assert np.median(np.abs(p - g)[both]) < 0.5 and (np.abs(p - g)[both] > 2).mean() < 0.08
    agree = (p > 0) & (f > 0)
    assert (np.abs(p - f)[agree] <= 1.0).mean() > 0.9
    assert p[p > 0].min() >= dmin + 1                # nothing at (or below) the range's end
    outside = np.ones((H, W), bool)
    outside[y0:y1, x0:x1] = False
    assert not part[outside].any()
    assert work <= work_full
    # an empty range is skipped
    none, w0 = disparity_regions(m, L, R, [box], [(dmin, 0)])
    assert w0 == 0 and not none.any()


def test_merge_strips_joins_touching_bands_with_overlapping_rows_when_cheaper():
    # three 32-px bands of one region, the middle one's rows shifted, each searching from the
    # horizon (d_min 0) to a near foot: matched apart each pays its own 128 extension columns
    boxes = [(100, 40, 132, 168), (132, 48, 164, 176), (164, 40, 196, 168)]
    ranges = [(0, 128), (0, 128), (0, 112)]
    b, r, p = merge_strips(boxes, ranges, 3)
    assert b == [(100, 40, 196, 176)] and r == [(0, 128)]
    assert p == [[(100, 132, 0, 128, 40, 168), (132, 164, 0, 128, 48, 176),
                  (164, 196, 0, 112, 40, 168)]]
    # no wider than max_width; bands that do not touch, or whose rows do not overlap, and
    # empty ranges are never joined
    b, _, p = merge_strips(boxes, ranges, 3, max_width=64)
    assert b == [(100, 40, 164, 176), (164, 40, 196, 168)] and len(p[0]) == 2
    apart = [(100, 40, 132, 168), (140, 40, 172, 168), (172, 200, 204, 260), (204, 200, 236, 260)]
    b, _, _ = merge_strips(apart, [(0, 128), (0, 128), (0, 0), (0, 128)], 3)
    assert sorted(b) == sorted(apart)
    b, _, _ = merge_strips([(100, 40, 132, 100), (132, 100, 164, 160)], [(0, 128)] * 2, 3)
    assert len(b) == 2
    # narrow ranges far apart: the union would search more than it saves
    b, r, _ = merge_strips([(100, 200, 132, 264), (132, 200, 164, 264)], [(0, 16), (96, 16)], 3)
    assert len(b) == 2 and r == [(0, 16), (96, 16)]


def test_merged_boxes_write_each_member_with_its_own_range_only():
    L, R, gt, vis = _cones()
    m = make_matcher(StereoConfig(matcher="sgbm", num_disparities=64), 1.0, 1.0)
    H, W = L.shape[:2]
    members = [(200, 120, 232, 200), (232, 130, 264, 210)]
    rng = [(0, 64), (16, 48)]
    boxes, ranges, parts = merge_strips(members, rng, m.margin)
    assert len(boxes) == 1
    d, _ = disparity_regions(m, L, R, boxes, ranges, parts)
    alone, _ = disparity_regions(m, L, R, members, rng)
    inside = np.zeros((H, W), bool)
    for (x0, y0, x1, y1), (dmin, n) in zip(members, rng):
        inside[y0:y1, x0:x1] = True
        seg = d[y0:y1, x0:x1]
        lo = dmin + 1.0 if dmin > 0 else 0.0
        assert seg.any() and np.all((seg == 0) | ((seg >= lo) & (seg < dmin + n)))
    assert not d[~inside].any()      # the union's rows and columns outside the members: nothing
    # the same surfaces as matching each member alone (SGBM sees more context in the union)
    both = (d > 0) & (alone > 0)
    assert both.sum() > 0.5 * (alone > 0).sum()
    assert (np.abs(d - alone)[both] <= 1.0).mean() > 0.9
    known = both & (gt > 0) & vis
    assert np.median(np.abs(d - gt)[known]) < 0.5


def test_ground_search_range_keeps_every_point_above_the_ground_and_narrows_the_search():
    c = _calib(0.5)                                   # 640x512, horizon near row 108
    nd = auto_disparities(StereoConfig(), c.camera.fx, c.baseline_m)
    ground = _plane_disparity(c)                      # exact, level vehicle, flat field
    # a strip well below the horizon: the far end is the ground (with slack), not 0
    box = (0, 300, 640, 340)
    dmin, n = ground_search_range(c, box, nd)
    assert n % 16 == 0 and dmin + n >= nd
    assert 0 < dmin <= ground[300:340].min()          # every ground pixel can still be matched
    assert n < nd                                     # and the search is narrower
    # the ground 0.3 m lower or the vehicle pitched 3 deg nose-up stays inside the range
    assert _plane_disparity(c, ground_h=-0.3)[300:340].min() >= dmin
    # rays that can miss the ground (horizon in the box): no far limit
    assert ground_search_range(c, (0, 60, 640, 140), nd) == (0, nd)
    # the bottom rows see the ground nearer than min_depth_m (5 m here): nothing to search
    nd5 = auto_disparities(StereoConfig(min_depth_m=5.0), c.camera.fx, c.baseline_m)
    assert ground_search_range(c, (0, 480, 640, 512), nd5)[1] == 0
    # near end from the foot: a wall at x = 12 m standing on the ground, its foot row
    wall = _plane_disparity(c, wall_x=12.0)
    col = wall[:, 320]
    foot = int(np.flatnonzero(np.isclose(col, ground[:, 320]) & (np.arange(512) > 120))[0])
    top = foot - 60
    dmin, n = ground_search_range(c, (250, top, 390, foot + 1), nd, foot_row=foot)
    w = wall[top:foot, 250:390]
    assert dmin <= w.min() and w.max() < dmin + n
    assert n < nd                                     # a wall 12 m away needs less than nd
    # something nearer seen in the box by the coarse pass widens the search to cover it
    near = float(wall[top:foot, 250:390].max()) + 40.0
    dmin2, n2 = ground_search_range(c, (250, top, 390, foot + 1), nd, foot_row=foot,
                                    seen_max_disp=near)
    assert dmin2 + n2 >= near and dmin2 <= w.min()
    dmin3, n3 = ground_search_range(c, (250, top, 390, foot + 1), nd, foot_row=foot,
                                    seen_max_disp=10 * nd)
    assert dmin3 + n3 >= nd                           # never past min_depth_m's disparity


def test_strips_cover_the_box_with_their_own_ranges():
    c = _calib(0.5)
    nd = auto_disparities(StereoConfig(), c.camera.fx, c.baseline_m)
    boxes, ranges = strip_boxes(c, [(100, 40, 300, 470)], nd, strip_rows=64)
    assert boxes[0][1] == 40 and all(b[0] == 100 and b[2] == 300 for b in boxes)
    for a, b in zip(boxes, boxes[1:]):
        assert a[3] == b[1]                           # contiguous, no row matched twice
    assert ranges[0] == (0, nd) and ranges[-1][0] > ranges[0][0]
    assert boxes[-1][3] <= 470                        # rows with an empty range are dropped



def test_near_search_reaches_a_wall_in_the_stop_zone_only_from_strips_that_see_near_ground():
    """near_min_depth_m: a wall standing 3.0 m ahead of the vehicle origin (1.8 m from the
    camera: nearer than min_depth_m's 3 m) is beyond the default search (the range stops at
    nd); with nd_near the strips whose own last row sees ground nearer than nd reaches search
    far enough to hold its disparity, and strips that do not see near ground keep nd."""
    c = _calib(0.5)
    nd = auto_disparities(StereoConfig(), c.camera.fx, c.baseline_m)
    fb = c.camera.fx * c.baseline_m
    nd_near = int(np.ceil(fb / 1.6 / 16.0)) * 16
    assert nd_near > nd
    wall = _plane_disparity(c, wall_x=3.0)
    box = (250, 200, 390, 512)                        # the wall down to the image bottom
    w = wall[200:512, 250:390]
    assert w.max() > nd                               # the default cannot reach it
    b0, r0 = strip_boxes(c, [box], nd, strip_rows=64, near_from_foot=True, foot_row=511)
    assert all(dm + n <= nd for dm, n in r0)
    b1, r1 = strip_boxes(c, [box], nd, strip_rows=64, near_from_foot=True, foot_row=511,
                         nd_near=nd_near)
    for (x0, y0, x1, y1), (dm, n) in zip(b1, r1):
        seg = wall[y0:y1, x0:x1]
        if dm + n > nd:                               # an extended strip holds the wall
            assert dm <= seg.min() and seg.max() < dm + n
    assert any(dm + n > nd for dm, n in r1)
    # a strip high in the image (its own last row sees ground beyond min_depth_m) keeps nd
    b2, r2 = strip_boxes(c, [(250, 150, 390, 214)], nd, strip_rows=64, near_from_foot=True,
                         foot_row=511, nd_near=nd_near)
    assert all(dm + n <= nd for dm, n in r2)
    assert (ground_search_range(c, box, nd, foot_row=511, nd_near=nd_near)[1]
            > ground_search_range(c, box, nd, foot_row=511)[1])

def test_matching_resolution_and_scaled_calibration():
    assert match_factor(1280, 640) == 2 and match_factor(640, 640) == 1
    assert match_factor(1281, 640) == 4 and match_factor(1280, 0) == 1
    c = _calib(1.0)
    h = scaled_calibration(c, 2)
    assert (h.camera.width, h.camera.height) == (640, 512)
    assert h.camera.fx == 550.0 and h.camera.cx == pytest.approx(319.75)
    # the same ground plane reprojects to the ground from either resolution
    pts, _ = points_from_disparity(_plane_disparity(h), h, stride=4)
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-6)
    img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    small = downscale(img, 2)
    assert small.shape == (2, 3, 3)
    assert abs(int(small[0, 0, 0]) - img[:2, :2, 0].mean()) <= 0.5     # the 2x2 block mean


def test_dedupe_keeps_the_first_point_of_each_cell():
    xy = np.array([[1.01, 2.01], [1.05, 2.05], [-0.31, 0.0], [1.01, 2.11], [-0.39, 0.09]],
                  np.float32)
    out = dedupe_cells(xy)
    np.testing.assert_array_equal(out, xy[[0, 2, 3]])


@pytest.mark.parametrize("span_m", [20.0, 200.0])      # 16-bit cell keys, and wider ones
def test_dedupe_equals_a_first_occurrence_reference(span_m):
    rng = np.random.default_rng(3)
    xy = (rng.random((20000, 2)) * [30.0, span_m] - [0.0, span_m / 2]).astype(np.float32)
    xy = np.concatenate([xy, xy[:5000] + 0.001])          # many repeats of a cell
    cells = np.floor(xy.astype(np.float64) / 0.1).astype(np.int64)
    seen, want = set(), []
    for i, c in enumerate(map(tuple, cells)):
        if c not in seen:
            seen.add(c)
            want.append(i)
    np.testing.assert_array_equal(dedupe_cells(xy), xy[want])


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


_FRAMES: dict = {}


def _cached_frames(scene, n, start=0):
    """Rendered once per test session (the simulator is the slow part)."""
    key = (scene, n, start)
    if key not in _FRAMES:
        _FRAMES[key] = _sim_frames(scene, n, start)
    return _FRAMES[key]


def _near(points, ob, r=0.6):
    from appliance.evaluation import footprint_distance
    return int((footprint_distance(points, ob) <= r).sum()) if len(points) else 0


def test_novelty_pipeline_learns_the_field_sees_the_person_and_drops_stubble():
    from appliance.config import parse_config
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                       "stereo-novelty": {"matcher": "sgbm",
                                                          "update_every_frames": 2}}})
    learn = _cached_frames("stubble-empty", 6)
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


def _learnt_pipeline(**opts):
    from appliance.config import parse_config
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                       "stereo-novelty": {"matcher": "sgbm",
                                                          "update_every_frames": 2, **opts}}})
    nov = make_pipeline("stereo-novelty", cfg)
    for s in _cached_frames("stubble-empty", 6):
        nov.process(SensorInputs(s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle))
        nov.novelty.wait_idle()
    return nov


def test_depth_cue_sends_the_stubble_coloured_drum_to_dense_stereo():
    course = _sim_frames("stubble-day", 1, start=4)[0]          # the look-alike drum ~8 m ahead
    drum = next(o for o in course.truth if o["class"] == "look-alike-drum")
    inp = SensorInputs(course.stereo.stamp_ns, stereo=course.stereo, vehicle=course.vehicle)
    out = {}
    for cue in ("off", "bm"):
        nov = _learnt_pipeline(depth_cue=cue)
        try:
            out[cue] = nov.process(inp)
        finally:
            nov.close()
    off, on = _near(out["off"].points_xy, drum), _near(out["bm"].points_xy, drum)
    print("points near the look-alike drum: novelty alone", off, "with the depth cue", on)
    assert on >= 2 * off + 10                    # novelty alone barely touches it, the cue does
    rows, cols = out["bm"].debug["grid"]
    assert 0 < out["bm"].debug["cue_cells"]["depth"] < 0.25 * rows * cols
    assert out["off"].debug["cue_cells"] == {}


def _one_novel_cell_and_one_cue_cell():
    """A 4 x 5 grid of 16 px cells (80 x 64 px): novelty's result with cell (1, 1) novel,
    and a cue's cell mask with cell (3, 4) raised."""
    from types import SimpleNamespace
    mask = np.zeros((4, 5), bool)
    mask[1, 1] = True
    cue = np.zeros((4, 5), bool)
    cue[3, 4] = True
    return SimpleNamespace(mask=mask, affine=None, cell_px=16), cue


def test_cells_to_match_is_novel_or_any_extra_cue():
    from appliance.perception.stereo_novelty import StereoNoveltyPipeline
    nov = StereoNoveltyPipeline(background=False)
    try:
        res, cue = _one_novel_cell_and_one_cue_cell()
        out = nov._cells_to_match(res, (80, 64), {"depth": cue, "none": None})
        assert out.shape == (64, 80)
        assert out[16:32, 16:32].all() and out[48:64, 64:80].all()
        assert out.sum() == 2 * 16 * 16 * 255
        only = nov._cells_to_match(res, (80, 64), {})
        assert only.sum() == 16 * 16 * 255
    finally:
        nov.close()


@pytest.mark.parametrize("gate", ["off", "all"])
def test_novelty_gate_off_matches_only_other_cues_and_all_matches_every_cell(gate):
    from appliance.perception.stereo_novelty import (StereoNoveltyConfig,
                                                     StereoNoveltyPipeline)
    nov = StereoNoveltyPipeline(StereoNoveltyConfig(novelty_gate=gate), background=False)
    try:
        res, cue = _one_novel_cell_and_one_cue_cell()
        out = nov._cells_to_match(res, (80, 64), {"depth": cue})
        src = nov._source_masks
        if gate == "off":          # the novel cell is neither matched nor credited to novelty
            assert out.sum() == 16 * 16 * 255 and out[48:64, 64:80].all()
            assert not src["novelty"].any()
        else:                      # everything matched; novelty credited only where it fired
            assert out.all()
            assert src["novelty"].sum() == 16 * 16 * 255 and src["novelty"][16:32, 16:32].all()
        assert src["depth"].sum() == 16 * 16 * 255
    finally:
        nov.close()


def test_novelty_gate_off_loses_what_only_novelty_saw_and_all_matches_the_whole_frame():
    course = _sim_frames("stubble-day", 1, start=20)[0]
    person = next(o for o in course.truth if o["class"] == "person")
    inp = SensorInputs(course.stereo.stamp_ns, stereo=course.stereo, vehicle=course.vehicle)
    out = {}
    for gate in ("on", "off", "all"):
        # depth cue off: what is matched is novelty's choice alone (or nothing, or everything)
        nov = _learnt_pipeline(depth_cue="off", novelty_gate=gate)
        try:
            out[gate] = nov.process(inp)
        finally:
            nov.close()
    assert _near(out["on"].points_xy, person) > 0
    assert _near(out["off"].points_xy, person) == 0 and out["off"].debug["boxes"] == 0
    assert _near(out["all"].points_xy, person) > 0     # (region and full-frame matching
    # differ a little: 20 points near the person full-frame, 21 in the novel cells' boxes)
    # the matcher's work (pixels x disparities searched, over the image's pixels): the whole
    # frame is several times what the novel cells' boxes cost (measured 4.7 against 1.0)
    assert out["all"].debug["stereo_px_fraction"] > 3 * out["on"].debug["stereo_px_fraction"]
    assert out["all"].debug["boxes"] > out["on"].debug["boxes"] > 0
    # the model still runs and says what is novel, whatever the gate (what it learns can
    # differ: cells near detected points are kept out of its updates)
    assert out["off"].debug["novel_fraction"] > 0 and out["all"].debug["novel_fraction"] > 0


@pytest.mark.parametrize("f,k", [(1, 1), (2, 2), (2, 1), (1, 2), (2, 4), (4, 2)])
def test_masks_made_at_a_lower_resolution_equal_the_full_resolution_round_trip(f, k):
    """The pipeline makes the matching mask and the boxes' coarse mask from the mask at the
    descriptor resolution (1/f); they must equal what the full-resolution round trip gave
    (nearest up to the camera's size, then area down and > 0)."""
    from appliance.perception.stereo_novelty import coarse_mask, rescale_mask
    rng = np.random.default_rng(f * 10 + k)
    H, W = 1024, 1280
    cells = rng.random((H // f // 16 + 1, W // f // 16 + 1)) < 0.2
    m = cv2.resize(cells.astype(np.uint8) * 255, (cells.shape[1] * 16, cells.shape[0] * 16),
                   interpolation=cv2.INTER_NEAREST)[:H // f, :W // f]
    m[rng.random(m.shape) < 0.001] = 255                    # isolated pixels too
    full = np.zeros((H, W), np.uint8)
    full[:H // f * f, :W // f * f] = cv2.resize(m, (W // f * f, H // f * f),
                                                interpolation=cv2.INTER_NEAREST)
    want_sel = downscale(full, k) > 0 if k > 1 else full > 0
    got_sel = rescale_mask(m, f, k, (H // k, W // k)) > 0
    assert np.array_equal(got_sel, want_sel)
    g = 8
    want_small = cv2.resize(full[:H // g * g, :W // g * g], (W // g, H // g),
                            interpolation=cv2.INTER_AREA) > 0
    assert np.array_equal(coarse_mask(m, f, g, (H // g, W // g)), want_small)


def test_elas_without_pyelas_says_how_to_get_it(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "elas", None)          # import elas -> ImportError
    with pytest.raises(RuntimeError, match="pyelas.*GPLv3.*no-build-isolation"):
        make_matcher(StereoConfig(matcher="elas", num_disparities=64), 1.0, 1.0)


@pytest.mark.skipif(not HAVE_ELAS, reason="pyelas (optional, GPLv3) not installed")
def test_elas_on_a_box_equals_its_full_frame_result_inside_it():
    """Region matching with LIBELAS: a box far from the image border gets (nearly) the
    full-frame disparities (ELAS interpolates from support points, so a crop's support set
    differs a little at its edges)."""
    (full, _), (d, _), box = _cones_full_and_box("elas")
    x0, y0, x1, y1 = box
    both = (full[y0:y1, x0:x1] > 0) & (d[y0:y1, x0:x1] > 0)
    assert both.mean() > 0.8
    assert (np.abs(full[y0:y1, x0:x1] - d[y0:y1, x0:x1])[both] <= 1.0).mean() > 0.9
    assert not d[:y0].any() and not d[y1:].any()


@pytest.mark.parametrize("pipeline", ["stereo", "stereo-novelty"])
def test_elas_without_pyelas_is_a_config_error_at_start(monkeypatch, pipeline, tmp_path,
                                                       capsys):
    """Not a fault on the first frame: the pipeline refuses to be built (eval), naming the key
    and how to get the binding; `config check` (a config for the box) refuses LIBELAS."""
    import sys
    from appliance.cli import main
    from appliance.config import parse_config
    from hal.errors import ConfigError
    monkeypatch.setitem(sys.modules, "elas", None)
    cfg = parse_config({"perception": {"pipelines": [pipeline],
                                       pipeline: {"matcher": "elas"}}})
    with pytest.raises(ConfigError, match=rf"perception.{pipeline}.*pyelas"):
        make_pipeline(pipeline, cfg)
    f = tmp_path / "c.toml"
    f.write_text(f'[perception]\npipelines = ["{pipeline}"]\n[perception.{pipeline}]\n'
                 'matcher = "elas"\n')
    assert main(["config", "check", str(f)]) != 0       # a box's config: refused either way
    err = capsys.readouterr().err
    assert f"[perception.{pipeline}]" in err and "offline comparison" in err


def test_the_daemon_refuses_libelas_and_config_check_says_why(tmp_path, capsys):
    """LIBELAS can segfault the process on small crops: fine for `fieldguard eval`, never in
    the box. The daemon does not start with it; config check names the key."""
    from appliance.cli import main
    from appliance.config import parse_config
    from appliance.daemon import Daemon, sim_config
    from hal.errors import ConfigError
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                       "stereo-novelty": {"matcher": "elas"}}})
    with pytest.raises(ConfigError, match="offline comparison"):
        Daemon(sim_config(cfg), mode="sim", pace=0.0, serve_status=False)
    if HAVE_ELAS:
        make_pipeline("stereo-novelty", cfg).close()         # eval may build it
    f = tmp_path / "c.toml"
    f.write_text('[perception]\npipelines = ["stereo"]\n[perception.stereo]\nmatcher = "elas"\n')
    assert main(["config", "check", str(f)]) != 0
    err = capsys.readouterr().err
    assert "[perception.stereo]" in err and "offline comparison" in err


@pytest.mark.skipif(not HAVE_ELAS, reason="pyelas (optional, GPLv3) not installed")
@pytest.mark.parametrize("rows", [16, 24, 32])
def test_elas_on_short_boxes_does_not_crash_the_process(rows):
    """The crop sizes that made LIBELAS segfault (16-32 rows of texture) are grown to 64 rows
    around the box: run in a child process, so a crash fails this test instead of the suite."""
    import subprocess
    import sys
    code = (
        "import numpy as np\n"
        "from appliance.perception.stereo import StereoConfig, make_matcher, disparity_regions\n"
        "rng = np.random.default_rng(0)\n"
        "L = rng.integers(0, 255, (200, 300)).astype(np.uint8)\n"
        "R = np.roll(L, -5, axis=1)\n"
        "m = make_matcher(StereoConfig(matcher='elas', num_disparities=64), 1.0, 1.0)\n"
        f"d, _ = disparity_regions(m, L, R, [(150, 100, 182, {100 + rows})])\n"
        "print('ok', int((np.abs(d[d > 0] - 5) < 1).sum()))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1], timeout=60)
    assert r.returncode == 0, r.stderr[-500:]
    assert r.stdout.split()[-2] == "ok" and int(r.stdout.split()[-1]) > 0


def test_pad_left_matches_the_leftmost_columns():
    """OpenCV leaves the leftmost num_disparities columns without disparity; pad_left matches
    them over the disparities the right image can hold (issue #14: a person 4 m to the left
    at 11 m stood in that blind strip)."""
    from appliance.perception.stereo import StereoConfig, disparity_regions, make_matcher
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur((rng.uniform(0, 255, (120, 400)) > 128).astype(np.uint8) * 255,
                           (3, 3), 0)
    d_true = 20
    left = np.ascontiguousarray(tex[:, 60:360])
    right = np.ascontiguousarray(tex[:, 60 + d_true:360 + d_true])
    left, right = (cv2.cvtColor(x, cv2.COLOR_GRAY2BGR) for x in (left, right))
    m = make_matcher(StereoConfig(matcher="sgbm", num_disparities=64), 500.0, 0.1)
    H, W = left.shape[:2]
    plain, _ = disparity_regions(m, left, right, [(0, 0, W, H)])
    padded, work = disparity_regions(m, left, right, [(0, 0, W, H)], pad_left=True)
    strip = slice(10, 110), slice(d_true + 4, 64)
    assert not (plain[strip] > 0).any()                          # blind
    ok = np.abs(padded[strip] - d_true) <= 1.0
    assert ok.mean() > 0.9
    assert not (padded > np.arange(W)[None, :]).any()            # never off the right image
    np.testing.assert_allclose(padded[:, 70:], plain[:, 70:], atol=1.0)
    # a box with its own range near the edge too
    boxed, _ = disparity_regions(m, left, right, [(0, 0, 80, H)], ranges=[(8, 32)],
                                 pad_left=True)
    assert (np.abs(boxed[10:110, 30:64] - d_true) <= 1.0).mean() > 0.9


def test_row_counts_equal_the_sum_over_each_row():
    """vertical_support counts its 8 samples per point by the population count of each row's
    64-bit word: the same counts as the sum, for 8 columns (contiguous or not) and any other
    shape (the sum)."""
    from appliance.perception.stereo import _row_counts
    rng = np.random.default_rng(3)
    for shape in [(0, 8), (1, 8), (997, 8), (40, 5), (9, 16)]:
        b = rng.random(shape) < 0.4
        assert np.array_equal(_row_counts(b), b.sum(axis=1))
        t = np.ascontiguousarray(b.T).T                  # the same values, not C-contiguous
        assert np.array_equal(_row_counts(t), b.sum(axis=1))
    assert np.array_equal(_row_counts(np.ones((3, 8), bool)), [8, 8, 8])
