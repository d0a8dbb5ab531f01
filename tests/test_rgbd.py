"""The RGB-D pipeline (greenhouse paper): slope, colour, texture, decision, model file, training,
real depth frames."""
import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.distance import mahalanobis as scipy_mahalanobis

from appliance import rgbd_model
from appliance.perception import SensorInputs, make_pipeline
from appliance.perception.rgbd import PAPER_RULE, RgbdPipeline, RgbdPipelineConfig
from appliance.perception.rgbd_classes import train_model
from appliance.perception.rgbd_colour import (COLOUR_SPACES, UNDEFINED, ColourClassifier,
                                              colour_features, fit_gaussian, fit_mixture,
                                              mahalanobis)
from appliance.perception.rgbd_decision import (NOT_CLASSIFIED, Rule, decide, not_traversable,
                                                obstacle_groups, touching_ground)
from appliance.perception.rgbd_slope import (paper_vertical_angles, slope_map, steep_map,
                                             vertical_angles)
from appliance.perception.rgbd_texture import (chi_square, classify_histograms, lbp_codes, to_grey,
                                               window_index,
                                               normalised_histogram, window_histograms)
from hal.types import DepthCalibration, DepthFrame, Mount, PinholeCalibration

REAL = Path(__file__).resolve().parent / "data" / "real" / "rgbd"


# ---------------------------------------------------------------------------------------------
# slope (eq. 4)
# ---------------------------------------------------------------------------------------------
def plane_depth(h, w, fy, cy, pitch_deg, cam_h, tilt_deg, f0):
    """z-depth image of the surface 'height = tan(tilt) * (fwd - f0)' (ground below f0 is cut
    by the same plane), seen by a camera cam_h above the ground pitched pitch_deg down."""
    b, sec = vertical_angles(h, fy, cy, math.radians(pitch_deg))
    t = math.tan(math.radians(tilt_deg))
    # R sin b = cam_h - t (R cos b - f0)  ->  R = (cam_h + t f0) / (sin b + t cos b)
    r = (cam_h + t * f0) / (np.sin(b) + t * np.cos(b))
    z = np.where(r > 0, r / sec, 0.0)
    return np.repeat(z[:, None], w, axis=1).astype(np.float32)


@pytest.mark.parametrize("tilt", [0.0, 10.0, 30.0, 45.0, 60.0])
@pytest.mark.parametrize("pitch,fy,cy", [(10.0, 609.3, 239.5), (25.0, 500.0, 260.0)])
def test_slope_of_a_tilted_plane_is_its_angle(tilt, pitch, fy, cy):
    z = plane_depth(480, 64, fy, cy, pitch, 0.9, tilt, 1.0)
    s = slope_map(z, fy, cy, math.radians(pitch), 0.5, 5.0, 1)
    ok = np.isfinite(s)
    assert ok.sum() > 1000
    assert np.allclose(s[ok], tilt, atol=0.05), (np.nanmin(s), np.nanmax(s))
    s4 = slope_map(z, fy, cy, math.radians(pitch), 0.5, 5.0, 4)
    assert np.allclose(s4[np.isfinite(s4)], tilt, atol=0.05)


def test_thresholded_slope_is_the_slope_map_thresholded():
    """steep_map (the pipeline's fast path, no angles) says what slope_map > 40 deg says."""
    rng = np.random.default_rng(11)
    depths = [plane_depth(480, 16, 609.3, 239.5, 10.0, 0.9, t, 1.0) for t in (0, 39, 41, 60)]
    z = rng.uniform(0.3, 6.0, (120, 160)).astype(np.float32)     # rough, some out of range
    z[rng.random(z.shape) < 0.1] = 0.0
    depths.append(cv2.GaussianBlur(z, (7, 7), 2.0))
    for z in depths:
        for step in (1, 4):
            s = slope_map(z, 609.3, 239.5, 0.17, 0.5, 5.0, step)
            steep, level = steep_map(z, 609.3, 239.5, 0.17, 0.5, 5.0, step, 40.0)
            with np.errstate(invalid="ignore"):
                ref_s, ref_l = s > 40.0, s <= 40.0
                sure = ~(np.abs(s - 40.0) < 1e-3)          # float32 rounding at 40 deg itself
            assert np.array_equal(steep[sure], ref_s[sure])
            assert np.array_equal(level[sure], ref_l[sure])
            assert not (steep & level).any()


def test_vertical_wall_is_90_degrees_and_ignores_out_of_range_depth():
    fy, cy = 580.0, 239.5
    b, sec = vertical_angles(480, fy, cy, math.radians(10))
    z = np.repeat((2.0 / np.cos(b) / sec)[:, None], 8, 1).astype(np.float32)   # wall 2 m ahead
    s = slope_map(z, fy, cy, math.radians(10), 0.5, 5.0)
    assert np.allclose(s[np.isfinite(s)], 90.0, atol=0.01)
    z[100:110] = 0.0                 # no reading
    z[200:210] = 6.0                 # beyond the 5 m range
    s = slope_map(z, fy, cy, math.radians(10), 0.5, 5.0)
    assert np.isnan(s[99:110]).all() and np.isnan(s[199:210]).all()
    assert np.isfinite(s[120:190]).all()


def test_wrong_pitch_tilts_the_ground_so_the_mount_pitch_matters():
    z = plane_depth(480, 8, 580.0, 239.5, 30.0, 1.2, 0.0, 1.0)
    right = slope_map(z, 580.0, 239.5, math.radians(30.0))
    level = slope_map(z, 580.0, 239.5, 0.0)          # the paper's level-camera assumption
    assert np.nanmax(right) < 0.05
    assert abs(np.nanmedian(level) - 30.0) < 0.05


def test_paper_angles_are_the_linear_version_of_ours():
    fy = 240.0 / math.tan(math.radians(21.5))
    ours, _ = vertical_angles(480, fy, 239.5, 0.0)
    paper = paper_vertical_angles(480)
    assert abs(math.degrees(paper[-1]) - 21.5) < 1e-9
    assert np.max(np.abs(np.degrees(ours - paper))) < 0.8   # linear vs atan, at the edges
    assert abs(math.degrees(ours[240] - paper[240])) < 0.2


# ---------------------------------------------------------------------------------------------
# colour (eq. 5)
# ---------------------------------------------------------------------------------------------
def test_colour_spaces_follow_the_paper_formulas():
    px = np.array([[[30, 200, 90]]], np.uint8)            # BGR: R=90, G=200, B=30
    r, g, b = 90.0, 200.0, 30.0
    exp = {"rgb": (r, g, b),
           "delta-rgb": ((r - g) + (r - b), (g - r) + (g - b), (b - g) + (b - r)),
           "i-rgb": ((r + g + b) / 3, (r - b) / 2, (2 * g - r - b) / 4),
           "i0-rgb": ((r + g + b) / 3, r - b, (2 * g - r - b) / 2)}
    for space, v in exp.items():
        assert np.allclose(colour_features(px, space)[0, 0], v, atol=1e-4), space
    lab = colour_features(px, "lab")[0, 0]
    ref = cv2.cvtColor(px.astype(np.float32) / 255, cv2.COLOR_BGR2Lab)[0, 0]
    assert np.allclose(lab, ref) and 0 <= lab[0] <= 100 and lab[1] < 0   # green: a* < 0


def test_no_suspected_pixels_in_any_colour_space():
    empty = np.zeros((0, 3), np.uint8)
    for space in COLOUR_SPACES:
        assert colour_features(empty, space).shape == (0, 3)
    frame, _ = _frame(CRATE)
    flat = DepthFrame(0, 0, frame.color, np.zeros_like(frame.depth_m), frame.calib)
    for space in COLOUR_SPACES:
        pipe = RgbdPipeline(RgbdPipelineConfig(colour_space=space, texture="always",
                                               colour_lut_bits=0), model=_model())
        assert len(pipe.process(SensorInputs(0, rgbd=flat)).points_xy) == 0


def test_mahalanobis_matches_scipy_and_the_classifier():
    rng = np.random.default_rng(3)
    a = rng.multivariate_normal([80, 120, 60], [[300, 200, 50], [200, 400, 80], [50, 80, 200]],
                                2000)
    b = rng.multivariate_normal([200, 60, 60], [[100, 0, 0], [0, 150, 30], [0, 30, 90]], 2000)
    ga, gb = fit_gaussian(a, ridge=0.0), fit_gaussian(b, ridge=0.0)
    z = rng.uniform(0, 255, (200, 3))
    ref = np.array([[scipy_mahalanobis(p, g.means[0], np.linalg.inv(g.covs[0])) for g in (ga, gb)]
                    for p in z])
    assert np.allclose(mahalanobis(z, ga.means[0], ga.covs[0]), ref[:, 0], rtol=1e-9)
    clf = ColourClassifier([ga, gb], threshold=3.0)
    assert np.allclose(clf.distances(z), ref, rtol=1e-4, atol=1e-4)
    want = np.where(ref.min(1) < 3.0, ref.argmin(1), UNDEFINED)
    assert np.array_equal(clf.classify(z), want)
    assert set(want) == {0, 1, UNDEFINED}             # all three outcomes exercised


@pytest.mark.parametrize("space", ["rgb", "lab"])
def test_colour_lookup_table_agrees_with_the_exact_distances(space):
    """The 8-bit table (the default) is eq. 5 for every colour. The 7-bit one classifies each
    2x2x2 cell at its centre: it may differ only within the quantisation error of the threshold
    or of a class boundary."""
    m = rgbd_model.load(None)
    rng = np.random.default_rng(12)
    px = [rng.multivariate_normal(g.means[0], g.covs[0] * 4, 3000) for g in m.mixtures("rgb")]
    px.append(rng.uniform(0, 255, (3000, 3)))
    bgr = np.clip(np.concatenate(px), 0, 255).astype(np.uint8)[:, ::-1]   # model RGB -> BGR
    img = np.ascontiguousarray(bgr).reshape(-1, 1, 3)
    exact = ColourClassifier(m.mixtures(space), 3.5)
    feats = colour_features(bgr, space)
    want = exact.classify(feats)
    assert len(set(want)) == 5                                    # 4 classes + undefined
    full = ColourClassifier(m.mixtures(space), 3.5, space, 8)     # built in the background
    assert full.wait_lut(30.0) and full.lut_ready()
    assert np.array_equal(full.classify_image(img)[:, 0], want)
    got7 = ColourClassifier(m.mixtures(space), 3.5, space, 7).classify_image(img)[:, 0]
    d = np.sort(exact.distances(feats), axis=1)
    clear = (np.abs(d[:, 0] - 3.5) > 0.8) & (d[:, 1] - d[:, 0] > 0.8)
    assert clear.mean() > 0.5
    assert np.array_equal(got7[clear], want[clear])
    assert np.mean(got7 == want) > 0.95


def test_linear_colour_spaces_give_rgb_distances_delta_rgb_does_not():
    rng = np.random.default_rng(4)
    px = rng.integers(0, 256, (3000, 3), dtype=np.uint8)
    ref = px[:1000]
    test = px[1000:]
    d = {}
    for s in COLOUR_SPACES:
        g = fit_gaussian(colour_features(ref, s), ridge=0.0 if s != "delta-rgb" else 1.0)
        d[s] = mahalanobis(colour_features(test, s), g.means[0], g.covs[0])
    assert np.allclose(d["i-rgb"], d["rgb"], rtol=1e-6)
    assert np.allclose(d["i0-rgb"], d["rgb"], rtol=1e-6)
    assert not np.allclose(d["delta-rgb"], d["rgb"], rtol=1e-2)


def test_mixture_fits_two_modes_better_than_one_gaussian():
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal([60, 90, 50], 6, (800, 3)), rng.normal([20, 35, 20], 4, (800, 3))])
    mix, one = fit_mixture(x, 2), fit_gaussian(x)
    assert mix.k == 2 and np.isclose(mix.weights.sum(), 1.0)
    between = np.array([[40.0, 62.0, 35.0]])          # between the modes: not this class
    c_mix = ColourClassifier([mix], 3.0)
    c_one = ColourClassifier([one], 3.0)
    assert c_mix.classify(between)[0] == UNDEFINED
    assert c_one.classify(between)[0] == 0


# ---------------------------------------------------------------------------------------------
# texture (eqs. 6-8)
# ---------------------------------------------------------------------------------------------
def test_lbp_codes_of_known_patches():
    # neighbours p=1..8: top-left, top, top-right, right, bottom-right, bottom, bottom-left, left
    patch = np.array([[9, 1, 5],
                      [4, 5, 6],
                      [0, 7, 5]], np.uint8)
    # >= 5: top-left(1) yes, top(2) no, top-right(4) yes, right(8) yes, bottom-right(16) yes,
    # bottom(32) yes, bottom-left(64) no, left(128) no
    assert lbp_codes(patch)[1, 1] == 1 + 4 + 8 + 16 + 32
    assert (lbp_codes(np.full((5, 5), 77, np.uint8)) == 255).all()       # flat: all >= centre
    ramp = np.tile(np.arange(10, dtype=np.uint8) * 10, (6, 1))           # brighter to the right
    assert (lbp_codes(ramp)[1:-1, 1:-1] == 2 + 4 + 8 + 16 + 32).all()
    spot = np.zeros((3, 3), np.uint8)
    spot[1, 1] = 200                                                      # bright centre
    assert lbp_codes(spot)[1, 1] == 0


def test_window_histograms_and_chi_square():
    codes = np.zeros((40, 60), np.uint8)
    codes[:20, :20] = 7
    codes[:20, 20:40] = np.arange(20, dtype=np.uint8)[None, :]            # 20 codes x 20 rows
    codes[20:, :] = 255
    h = window_histograms(codes, 20)
    assert h.shape == (6, 256)
    assert h[0, 7] == 1.0 and np.isclose(h[1, :20], 1 / 20).all() and h[3, 255] == 1.0
    assert np.allclose(h.sum(1), 1.0)
    only = window_histograms(codes, 20, windows=np.array([1]))
    assert only[0].sum() == 0 and np.allclose(only[1], h[1])
    rng = np.random.default_rng(6)
    t, m = rng.random((5, 256)), rng.random((3, 256))
    t /= t.sum(1, keepdims=True)
    m /= m.sum(1, keepdims=True)
    ref = np.array([[sum((a - b) ** 2 / (a + b) for a, b in zip(ti, mi) if a + b > 0)
                     for mi in m] for ti in t])
    assert np.allclose(chi_square(t[:, None], m[None]), ref)
    assert chi_square(h[0], h[0]) == 0.0 and np.isclose(chi_square(h[0], h[3]), 2.0)
    cls = classify_histograms(np.stack([h[0], h[3], h[1]]), np.stack([h[3], h[0]]), 0.5)
    assert list(cls) == [1, 0, UNDEFINED]
    assert np.isclose(normalised_histogram(np.array([3, 3, 4, 4])).sum(), 1.0)


def test_window_classes_are_the_nearest_chi_square_under_the_threshold():
    rng = np.random.default_rng(13)
    t, m = rng.random((200, 256)), rng.random((4, 256))
    t[t < 0.8] = 0.0                                  # sparse, like 400-pixel windows
    m[1, m[1] < 0.5] = 0.0                            # a class with empty bins
    t /= t.sum(1, keepdims=True)
    m /= m.sum(1, keepdims=True)
    d = chi_square(t[:, None], m[None])
    thr = float(np.median(d.min(1)))
    want = np.where(d.min(1) < thr, d.argmin(1), UNDEFINED)
    assert np.array_equal(classify_histograms(t, m, thr), want)
    assert len(set(want)) >= 3


@pytest.mark.parametrize("window", [20, 7])          # whole windows, and ragged edge windows
def test_texture_map_classifies_the_window_of_every_suspected_pixel(window):
    frame, _ = _frame(BUSH)
    pipe = RgbdPipeline(RgbdPipelineConfig(texture="always", texture_window_px=window),
                        model=_model())
    res = pipe.analyse(SensorInputs(0, rgbd=frame))
    codes = lbp_codes(to_grey(frame.color))
    cls = classify_histograms(window_histograms(codes, window), pipe.model.lbp, 0.5)
    widx, _, _ = window_index(codes.shape, window)
    assert res.suspected.any()
    assert np.array_equal(res.texture_class, np.where(res.suspected, cls[widx], NOT_CLASSIFIED))
    one = np.zeros(res.suspected.shape, bool)
    one[50, 70] = True                                # one suspected pixel in its window
    tmap = pipe._texture_map(frame.color, one)
    assert tmap[50, 70] == cls[widx[50, 70]] and (tmap[~one] == NOT_CLASSIFIED).all()


# ---------------------------------------------------------------------------------------------
# the decision rule
# ---------------------------------------------------------------------------------------------
def _maps():
    surface = np.zeros((60, 80), bool)
    surface[40:] = True                                # ground in the lower third
    return surface


def test_paper_dilation_puts_a_ground_coloured_fringe_round_a_bush_coloured_box():
    """The paper's 3x3 dilation grows the suspected map one pixel onto the ground round an
    obstacle; those pixels are ground-coloured, and ground is not traversable in the paper's
    rule, so the fringe alone makes an obstacle group (why ``morphology = "close"`` exists)."""
    frame, face = _frame(BUSH)
    paper = {**PAPER_RULE, "texture": "off", "depth_median_px": 0, "slope_step_px": 1}
    pipe = RgbdPipeline(RgbdPipelineConfig(**paper), model=_model())
    res = pipe.analyse(SensorInputs(0, rgbd=frame))
    assert res.groups_colour == 1
    assert not res.colour_obstacles[np.ix_(face, np.arange(61, 99))].any()   # not the face
    assert res.colour_obstacles[:, 59].any() and res.colour_obstacles[:, 100].any()
    # ours: a ground-coloured pixel at ground height is traversable, so no fringe group
    ours = RgbdPipeline(RgbdPipelineConfig(texture="off", depth_median_px=0, slope_step_px=1),
                        model=_model())
    assert ours.analyse(SensorInputs(0, rgbd=frame)).groups_colour == 0


def test_decision_group_size_contact_and_classes():
    surface = _maps()
    cand = np.zeros_like(surface)
    cand[34:40, 10:15] = True                          # 30 px standing on the ground
    cand[34:40, 30:34] = True                          # 24 px on the ground: too small
    cand[10:20, 50:60] = True                          # 100 px floating: not on the ground
    mask, n = obstacle_groups(cand, surface, 30, 1)
    assert n == 1 and mask[34:40, 10:15].all() and not mask[:, 25:].any()
    mask, n = obstacle_groups(cand, surface, 24, 1)
    assert n == 2 and mask[34:40, 30:34].all()
    # traversable class (0 = bush, 1 = pepper) vs undefined (-1) and others (2 = ground)
    classes = np.full(surface.shape, 0, np.int16)
    classes[34:40, 10:15] = UNDEFINED
    classes[34:40, 16:21] = 1
    classes[34:40, 22:27] = 2
    sus = np.zeros_like(surface)
    sus[34:40, 10:27] = True
    cand = sus & not_traversable(classes, [0, 1])
    mask, n = obstacle_groups(cand, surface, 30, 1)
    assert n == 2 and mask[34:40, 10:15].all() and not mask[34:40, 16:21].any()
    assert mask[34:40, 22:27].all()
    mask, n = obstacle_groups(sus & not_traversable(classes, [0, 1, 2]), surface, 30, 1)
    assert n == 1 and not mask[34:40, 22:27].any()


def test_contact_looks_up_to_k_rows_down():
    rng = np.random.default_rng(14)
    for k in (1, 2, 3, 20):
        m, surf = rng.random((60, 50)) < 0.3, rng.random((60, 50)) < 0.2
        ref = np.zeros_like(m)
        for j in range(1, k + 1):
            ref[:-j] |= m[:-j] & surf[j:]
        assert np.array_equal(touching_ground(m, surf, k), ref), k


def test_decision_rule_paper_versus_ours():
    """Classes 0 bush, 1 pepper (traversable), 2 ground, 3 cover. Groups standing on the surface
    (rows 40+): A ground-coloured at ground height, B undefined colour and tall, C undefined but
    flat on the ground, D1 bush-coloured with the cover's texture, D2 bush-coloured with undefined
    texture."""
    surface = _maps()
    height = np.zeros(surface.shape, np.float32)
    height[:40] = ((40 - np.arange(40)) * 0.03)[:, None]       # 0.3 m at row 30 .. 0.03 at 39
    sus = np.zeros_like(surface)
    colour = np.full(surface.shape, NOT_CLASSIFIED, np.int16)
    texture = np.full(surface.shape, NOT_CLASSIFIED, np.int16)
    groups = {"A": (slice(36, 40), slice(5, 15), 2, 0), "B": (slice(30, 40), slice(20, 30), -1, 0),
              "C": (slice(36, 40), slice(35, 45), -1, 0), "D1": (slice(30, 40), slice(50, 60), 0, 3),
              "D2": (slice(30, 40), slice(62, 72), 0, -1)}
    for r, c, col, tex in groups.values():
        sus[r, c] = True
        colour[r, c] = col
        texture[r, c] = tex

    def found(d):
        return {g for g, (r, c, _, _) in groups.items() if d.obstacles[r, c].all()}

    paper = decide(sus, surface, colour, texture, Rule.paper([0, 1], 4), height)
    assert (paper.n_colour, paper.n_texture) == (3, 2)
    assert found(paper) == {"A", "B", "C", "D1", "D2"}
    ours = Rule((0, 1), 4, ground_classes=(2,), ground_max_height_m=0.25,
                texture_role="traversable-colour", texture_undefined=False, min_height_m=0.15)
    d = decide(sus, surface, colour, texture, ours, height)
    assert (d.n_colour, d.n_texture) == (1, 1) and found(d) == {"B", "D1"}
    assert not d.texture[groups["B"][0], groups["B"][1]].any()   # texture judges D1 only
    # the same ground-coloured pixels above ground height are not the path
    high = height.copy()
    high[36:40, 5:15] = 0.3
    assert "A" in found(decide(sus, surface, colour, texture, ours, high))
    # without colour classes' help, texture alone (colour pass) is the paper's OR
    d0 = decide(sus, surface, colour, None, ours, height)
    assert d0.texture is None and found(d0) == {"B"}


def test_raised_level_surfaces_of_no_traversable_colour():
    """The top of a box too near for its face to be in view is level and high: with the raised
    cue, a group of such pixels of no traversable colour is an obstacle; a bush top is not."""
    surface = _maps()
    raised = np.zeros_like(surface)
    raised[50:58, 5:15] = True                         # a box top (undefined colour)
    raised[50:58, 30:40] = True                        # a bush top
    colour = np.full(surface.shape, NOT_CLASSIFIED, np.int16)
    colour[50:58, 5:15] = UNDEFINED
    colour[50:58, 30:40] = 0
    sus = np.zeros_like(surface)
    rule = Rule((0, 1), 4)
    d = decide(sus, surface, colour, None, rule, None, raised)
    assert d.n_raised == 1 and d.obstacles[50:58, 5:15].all() and not d.obstacles[:, 30:40].any()
    assert decide(sus, surface, colour, None, rule).n_raised == 0       # cue off
    # at the image bottom only: the box top must reach the last rows
    bottom = Rule((0, 1), 4, bottom_rows=2, raised_bottom_only=True)
    assert decide(sus, surface, colour, None, bottom, None, raised).n_raised == 0
    raised[50:60, 5:15] = True
    colour[50:60, 5:15] = UNDEFINED
    assert decide(sus, surface, colour, None, bottom, None, raised).n_raised == 1


def test_a_group_cut_off_by_the_image_bottom_stands_on_unseen_ground():
    cand = np.zeros((60, 80), bool)
    cand[45:60, 10:20] = True                          # reaches the last row, no surface seen
    none = np.zeros_like(cand)
    assert obstacle_groups(cand, none, 30, 3)[1] == 0
    assert obstacle_groups(cand, none, 30, 3, bottom_rows=8)[1] == 1
    cand[45:60, 10:20] = False
    cand[40:50, 10:20] = True                          # ends 10 rows above the bottom
    assert obstacle_groups(cand, none, 30, 3, bottom_rows=8)[1] == 0


# ---------------------------------------------------------------------------------------------
# the whole pipeline on a synthetic frame: flat ground and a box 3 m ahead
# ---------------------------------------------------------------------------------------------
BUSH = (40, 90, 35)        # BGR
GROUND = (100, 115, 140)
CRATE = (180, 90, 30)


def _model():
    rng = np.random.default_rng(7)
    samples = {}
    for name, col in (("bush", BUSH), ("pepper", (40, 30, 160)), ("ground", GROUND)):
        px = np.clip(rng.normal(col, 6, (500, 3)), 0, 255).astype(np.uint8)
        codes = rng.integers(0, 256, 500).astype(np.uint8)
        samples[name] = [(px, codes)]
    # the greenhouse cover: white and flat (every LBP neighbour >= the centre: code 255)
    px = np.clip(rng.normal(250, 3, (500, 3)), 0, 255).astype(np.uint8)
    samples["cover"] = [(px, np.full(500, 255, np.uint8))]
    return train_model(samples)


def _frame(box_colour, box_x=3.0, box_h=0.4, flat_face=False):
    """160x120 frame: level ground under a camera 0.9 m up pitched 10 deg down at x = 1 m, a box
    face (columns 60-99) box_x ahead of the vehicle origin, white cover above the horizon."""
    w, h = 160, 120
    fy = 150.0
    cam = PinholeCalibration(w, h, 150.0, fy, 79.5, 59.5)
    mount = Mount(1.0, 0.0, 0.9, 0.0, 10.0, 0.0)
    b, sec = vertical_angles(h, fy, 59.5, math.radians(10.0))
    below = np.sin(b) > 1e-6
    r_ground = np.where(below, 0.9 / np.where(below, np.sin(b), 1.0), 0.0)
    d = box_x - mount.x_m                                   # face distance from the camera
    drop = d * np.tan(b)
    face = below & (r_ground * np.cos(b) > d) & (drop >= 0.9 - box_h)
    z_ground = r_ground / sec
    z_box = np.where(face, d / np.cos(b) / sec, z_ground)
    z = np.repeat(z_ground[:, None], w, 1).astype(np.float32)
    z[:, 60:100] = z_box[:, None]
    z[(z < 0.5) | (z > 5.0)] = 0.0
    colour = np.empty((h, w, 3), np.uint8)
    colour[:] = GROUND
    colour[~below] = (250, 250, 250)
    colour[np.ix_(face, np.arange(60, 100))] = box_colour
    rng = np.random.default_rng(8)
    colour = np.clip(colour + rng.normal(0, 3, colour.shape), 0, 255).astype(np.uint8)
    if flat_face:                                           # evenly painted: no sensor noise
        colour[np.ix_(face, np.arange(60, 100))] = box_colour
    return DepthFrame(0, 0, colour, z, DepthCalibration(cam, mount)), face


@pytest.mark.parametrize("colour,texture,morphology,rule,expect", [
    (CRATE, "off", "dilate", "paper", True),    # undefined colour, on the ground: obstacle
    (CRATE, "off", "close", "paper", True),
    (CRATE, "off", "dilate", "ours", True),
    (BUSH, "off", "close", "paper", False),     # bush-coloured: traversable
    (BUSH, "off", "dilate", "ours", False),
    (BUSH, "always", "close", "paper", True),   # ... its texture is no class: texture finds it
    (BUSH, "always", "dilate", "ours", True),   # ... its texture is the flat cover's: found
])
def test_pipeline_finds_a_box_on_the_ground(colour, texture, morphology, rule, expect):
    frame, face = _frame(colour, flat_face=True)
    opts = RgbdPipelineConfig(**{**(PAPER_RULE if rule == "paper" else {}), "texture": texture,
                                 "depth_median_px": 0, "slope_step_px": 1,
                                 "texture_window_px": 10, "morphology": morphology})
    pipe = RgbdPipeline(opts, model=_model())
    res = pipe.analyse(SensorInputs(0, rgbd=frame))
    pts = res.points_xy
    if not expect:
        assert len(pts) == 0 and not res.obstacles.any()
        return
    assert len(pts) > 30
    # the face is at x = 3 m; the dilation adds a few ground pixels right beside its foot
    assert np.all(np.abs(pts[:, 0] - 3.0) < 0.2), (pts[:, 0].min(), pts[:, 0].max())
    assert np.median(np.abs(pts[:, 0] - 3.0)) < 0.02
    assert np.all(np.abs(pts[:, 1]) < 0.9)
    # process() (no slope map in degrees, strided projection) says the same
    fast = pipe.process(SensorInputs(0, rgbd=frame)).points_xy
    assert len(fast) > 10 and np.all(np.abs(fast[:, 0] - 3.0) < 0.2)


def test_pipeline_ignores_a_box_beyond_the_range_and_rejects_mismatched_frames():
    frame, _ = _frame(CRATE, box_x=7.0)
    pipe = RgbdPipeline(RgbdPipelineConfig(texture="off"), model=_model())
    assert len(pipe.process(SensorInputs(0, rgbd=frame)).points_xy) == 0
    bad = DepthFrame(0, 0, frame.color[:-1], frame.depth_m, frame.calib)
    with pytest.raises(ValueError, match="differ"):
        pipe.process(SensorInputs(0, rgbd=bad))


def test_depth_holes_standing_on_the_ground_are_obstacles():
    """A shiny face returns no depth (the paper's Fig. 8): with ``holes`` a solid hole of no
    traversable colour standing on the ground is placed where its foot meets the ground; a hole
    in the cover's colour (the view beyond the range) and a narrow one (a depth shadow) are not."""
    frame, face = _frame(CRATE)
    cols = np.arange(60, 100)
    z = frame.depth_m.copy()
    z[np.ix_(face, cols)] = 0.0
    shiny = DepthFrame(0, 0, frame.color, z, frame.calib)
    on = RgbdPipeline(RgbdPipelineConfig(texture="off"), model=_model())
    res = on.analyse(SensorInputs(0, rgbd=shiny))
    assert res.groups_holes == 1 and res.groups_colour == 0
    pts = res.points_xy
    assert len(pts) > 20 and np.all(np.abs(pts[:, 0] - 3.0) < 0.25), pts[:, 0]
    off = RgbdPipeline(RgbdPipelineConfig(texture="off", holes=False), model=_model())
    assert len(off.process(SensorInputs(0, rgbd=shiny)).points_xy) == 0
    white = frame.color.copy()
    white[np.ix_(face, cols)] = (250, 250, 250)
    assert on.analyse(SensorInputs(0, rgbd=DepthFrame(0, 0, white, z, frame.calib))).groups_holes \
        == 0
    ground, _ = _frame(CRATE, box_h=0.0)               # no box: a hole in the ground's depth
    for width, n in ((8, 0), (30, 1)):
        zz = ground.depth_m.copy()
        zz[70:95, 60:60 + width] = 0.0
        cc = ground.color.copy()
        cc[70:95, 60:60 + width] = CRATE
        r = on.analyse(SensorInputs(0, rgbd=DepthFrame(0, 0, cc, zz, ground.calib)))
        assert r.groups_holes == n, width


# ---------------------------------------------------------------------------------------------
# the model file and training
# ---------------------------------------------------------------------------------------------
def test_model_file_round_trip_and_clear_errors(tmp_path):
    m = _model()
    p = rgbd_model.save(m, tmp_path / "m.npz")
    back = rgbd_model.load(p)
    assert back.classes == m.classes and np.allclose(back.lbp, m.lbp)
    for s in COLOUR_SPACES:
        assert np.allclose(back.colour[s][0].covs, m.colour[s][0].covs)
    with pytest.raises(rgbd_model.RgbdModelError, match="no such file"):
        rgbd_model.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip at all")
    with pytest.raises(rgbd_model.RgbdModelError, match="not a readable model"):
        rgbd_model.load(tmp_path / "junk.npz")
    data = dict(np.load(p))
    data["version"] = np.array(99)
    np.savez(tmp_path / "v99.npz", **data)
    with pytest.raises(rgbd_model.RgbdModelError, match="version 99"):
        rgbd_model.load(tmp_path / "v99.npz")
    data["version"] = np.array(1)
    data["lbp"] = data["lbp"][:, :10]
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(rgbd_model.RgbdModelError, match="inconsistent"):
        rgbd_model.load(tmp_path / "bad.npz")
    with pytest.raises(rgbd_model.RgbdModelError, match="no such file"):
        make_pipeline_with_model(tmp_path / "missing.npz")


def make_pipeline_with_model(path):
    from appliance.config import default_config
    import dataclasses
    import types
    cfg = default_config()
    extra = {"rgbd": RgbdPipelineConfig(model=str(path))}
    cfg = dataclasses.replace(cfg, perception=dataclasses.replace(
        cfg.perception, extra=types.MappingProxyType(extra)))
    return make_pipeline("rgbd", cfg)


def test_shipped_greenhouse_model_loads_with_the_paper_classes(tmp_path):
    m = rgbd_model.load(None)
    assert m.classes == ("bush", "pepper", "ground", "cover")
    # package data (an installed wheel has it), found through importlib.resources
    p = rgbd_model.default_model_path()
    assert p.is_file() and p.parent.name == "models" and p.parent.parent.name == "appliance"
    assert rgbd_model.load("").classes == m.classes
    # a configured path still overrides the shipped model
    other = rgbd_model.save(dataclasses.replace(m, classes=("a", "b", "c", "d")),
                            tmp_path / "other.npz")
    assert rgbd_model.load(str(other)).classes == ("a", "b", "c", "d")
    pipe = make_pipeline("rgbd")
    assert isinstance(pipe, RgbdPipeline) and pipe.traversable_idx == [0, 1]


def test_train_classes_cli_from_rectangles_and_polygons(tmp_path, capsys):
    from appliance.cli import main
    rng = np.random.default_rng(9)
    frames = []
    for i in range(2):
        img = np.empty((60, 80, 3), np.uint8)
        img[:, :40] = BUSH
        img[:, 40:] = GROUND
        img = np.clip(img + rng.normal(0, 5, img.shape), 0, 255).astype(np.uint8)
        d = tmp_path / f"run{i}" / "rgbd" / "color"
        d.mkdir(parents=True)
        cv2.imwrite(str(d / "000003.png"), img)
        frames.append(str(d / "000003.png"))
    ann = {"format": "fieldguard-rgbd-annotations", "version": 1, "classes": ["bush", "ground"],
           "frames": {"run0/rgbd/color/000003.png": [{"class": "bush", "rect": [2, 2, 30, 50]}],
                      "run1/rgbd/color/000003.png": [
                          {"class": "ground", "polygon": [[45, 5], [75, 5], [75, 55], [45, 55]]},
                          {"class": "bush", "rect": [5, 5, 10, 10]}]}}
    af = tmp_path / "ann.json"
    af.write_text(json.dumps(ann))
    out = tmp_path / "model.npz"
    assert main(["train-classes", *frames, "--annotations", str(af), "--out", str(out)]) == 0
    m = rgbd_model.load(out)
    assert m.classes == ("bush", "ground")
    assert m.meta["pixels"] == {"bush": 30 * 50 + 10 * 10, "ground": 31 * 51}
    assert np.allclose(m.colour["rgb"][0].means[0], BUSH[::-1], atol=1.5)
    assert "wrote" in capsys.readouterr().out
    # errors name the problem
    ann["frames"]["run0/rgbd/color/000003.png"][0]["class"] = "tree"
    af.write_text(json.dumps(ann))
    assert main(["train-classes", *frames, "--annotations", str(af), "--out", str(out)]) != 0
    assert "must be one of" in capsys.readouterr().err
    ann["frames"] = {"000003.png": [{"class": "bush", "rect": [0, 0, 5, 5]}]}
    af.write_text(json.dumps(ann))
    assert main(["train-classes", *frames, "--annotations", str(af), "--out", str(out)]) != 0
    assert "matches several frames" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# real Kinect-class frames: the floor is low slope, furniture fronts and walls are steep
# ---------------------------------------------------------------------------------------------
def _pitch_from_floor(z, fy, cy, rows, cols):
    """Camera pitch (down) from a floor patch: optical Y = a + b Z on a level floor, b = -tan p."""
    v = np.arange(z.shape[0], dtype=np.float64)[rows][:, None] * np.ones((1, z[:, cols].shape[1]))
    zz = z[rows, cols].astype(np.float64)
    ok = zz > 0
    b = np.polyfit(zz[ok], (v[ok] - cy) / fy * zz[ok], 1)[0]
    return math.atan(-b)


@pytest.mark.parametrize("name,scale,fy,cy,fit,floor,steep,pitch_range", [
    ("TUM_depth.png", 5000.0, 525.0, 239.5, (slice(440, 476), slice(240, 370)),
     (slice(330, 420), slice(250, 340)),
     {"desk back panel": (slice(20, 160), slice(250, 560)),
      "chair back": (slice(270, 400), slice(20, 140))}, (15, 35)),
    ("slambook_ch5_depth_1.pgm", 1000.0, 519.0, 253.5, (slice(420, 470), slice(60, 200)),
     (slice(300, 400), slice(60, 200)),
     {"cabinet front": (slice(40, 200), slice(440, 560)),
      "chair": (slice(180, 400), slice(250, 300))}, (5, 25)),
])
def test_real_frames_floor_is_low_slope_furniture_is_steep(name, scale, fy, cy, fit, floor,
                                                            steep, pitch_range):
    raw = cv2.imread(str(REAL / name), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16 and raw.shape == (480, 640)
    z = raw.astype(np.float32) / np.float32(scale)
    pitch = _pitch_from_floor(z, fy, cy, *fit)          # fitted on one floor patch ...
    assert pitch_range[0] < math.degrees(pitch) < pitch_range[1]
    cam = PinholeCalibration(640, 480, 525.0, fy, 319.5, cy)
    frame = DepthFrame(0, 0, np.zeros((480, 640, 3), np.uint8), z,
                       DepthCalibration(cam, Mount(0, 0, 1.0, 0, math.degrees(pitch), 0)))
    pipe = RgbdPipeline(RgbdPipelineConfig(texture="off"), model=_model())
    res = pipe.analyse(SensorInputs(0, rgbd=frame))
    s = res.slope_deg[floor]                           # ... judged on another
    s = s[np.isfinite(s)]
    assert s.size > 5000
    assert np.median(s) < 20 and np.mean(s > 40) < 0.15, (np.median(s), np.mean(s > 40))
    assert res.surface[floor].mean() > 0.6
    for what, (r, c) in steep.items():
        s = res.slope_deg[r, c]
        s = s[np.isfinite(s)]
        assert np.median(s) > 50 and np.mean(s > 40) > 0.6, (what, np.median(s))
        assert res.suspected[r, c].mean() > 0.6, what


@pytest.mark.parametrize("n_classes", [3, 300])
def test_not_traversable_is_the_class_table_per_pixel(n_classes):
    # an OpenCV byte table when the classes fit one, a gather otherwise: both are the table
    rng = np.random.default_rng(n_classes)
    cmap = rng.integers(NOT_CLASSIFIED, n_classes, (48, 64)).astype(np.int16)
    trav = [0, 2, n_classes - 1]
    want = np.array([[c not in trav for c in row] for row in cmap.tolist()])
    assert np.array_equal(not_traversable(cmap, trav), want)
    assert not_traversable(cmap, []).all()
