"""The novelty detector, step by step (paper seed 000, eqs. 1-9)."""
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.perception.novelty import (BackgroundUpdater, NoveltyDetector, ParzenModel,
                                          Stabiliser, VisualOdometry, cell_descriptors,
                                          dilate_cells, effective_forget, island_filter,
                                          kernel_norm, mask_to_camera, obstacle_cells,
                                          parzen_density_bruteforce, stabilised_descriptors)
from appliance.perception.stereo_novelty import StereoNoveltyConfig
from hal.types import Mount, VehicleState

REAL = Path(__file__).parent / "data" / "real" / "textures"


def _real(name):
    g = cv2.imread(str(REAL / name), cv2.IMREAD_GRAYSCALE)
    assert g is not None, name
    return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)


# ---- descriptors (eq. 1) -----------------------------------------------------------------
def test_descriptor_of_a_uniform_colour():
    bgr = (30, 140, 200)
    img = np.zeros((64, 96, 3), np.uint8)
    img[:] = bgr
    d = cell_descriptors(img, 32)
    assert d.shape == (2, 3, 8)
    lab = cv2.cvtColor(np.uint8([[bgr]]), cv2.COLOR_BGR2Lab)[0, 0] / 255.0
    np.testing.assert_allclose(d[..., :3], np.broadcast_to(lab, (2, 3, 3)), atol=1e-6)
    np.testing.assert_allclose(d[..., 3:6], 0.0, atol=1e-3)
    # cell centres, scaled to [0, 1]
    np.testing.assert_allclose(d[0, :, 6], [1 / 6, 3 / 6, 5 / 6], atol=1e-6)
    np.testing.assert_allclose(d[:, 0, 7], [1 / 4, 3 / 4], atol=1e-6)


def test_descriptor_std_of_black_and_white_is_one():
    img = np.zeros((32, 32, 3), np.uint8)
    img[:, ::2] = 255                              # half black, half white: L std = 0.5 -> 1.0
    d = cell_descriptors(img, 32)
    assert d.shape == (1, 1, 8)
    assert d[0, 0, 0] == pytest.approx(0.5, abs=1e-3)
    assert d[0, 0, 3] == pytest.approx(1.0, abs=1e-3)
    assert d[0, 0, 4] == pytest.approx(0.0, abs=1e-2) and d[0, 0, 5] == pytest.approx(0.0, abs=1e-2)


def test_descriptors_match_numpy_on_a_real_photo_of_any_size():
    img = _real("grass.png")[:300, :450]            # not a multiple of 32: whole cells only
    d = cell_descriptors(img, 32)
    assert d.shape == (9, 14, 8)
    lab = cv2.cvtColor(img, cv2.COLOR_BGR2Lab).astype(np.float64) / 255.0
    for r, c in [(0, 0), (4, 7), (8, 13)]:
        blk = lab[r * 32:(r + 1) * 32, c * 32:(c + 1) * 32].reshape(-1, 3)
        np.testing.assert_allclose(d[r, c, :3], blk.mean(0), atol=1e-4)
        np.testing.assert_allclose(d[r, c, 3:6], 2 * blk.std(0), atol=1e-3)
    assert 0.0 <= d.min() and d.max() <= 1.0


def test_stabilised_descriptors_identity_and_shift():
    img = _real("gravel.png")
    d0 = cell_descriptors(img, 32)
    d1, valid = stabilised_descriptors(img, 32, np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    np.testing.assert_array_equal(d0, d1)
    assert valid.all()
    # stabilised = camera shifted 32 px right: stabilised cell c shows camera cell c-1
    A = np.array([[1.0, 0, 32.0], [0, 1.0, 0]])
    d2, valid = stabilised_descriptors(img, 32, A)
    np.testing.assert_allclose(d2[:, 1:, :6], d0[:, :-1, :6], atol=2e-3)
    assert not valid[:, 0].any() and valid[:, 1:].all()
    # and the novelty mask goes back: a stabilised cell lands on the camera cell it came from
    m = np.zeros(d0.shape[:2], bool)
    m[3, 5] = True
    cam = mask_to_camera(m, A, (img.shape[1], img.shape[0]), 32)
    ys, xs = np.nonzero(cam)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (4 * 32, 5 * 32 - 1, 3 * 32, 4 * 32 - 1)


# ---- density (eqs. 3, 4, 8) ---------------------------------------------------------------
def test_density_matches_brute_force():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (3000, 8)).astype(np.float32)
    x[:1500, :3] *= 0.2                                    # a dense cluster and a sparse part
    w = rng.uniform(0.05, 1.0, 3000)
    sigma = 0.12
    m = ParzenModel(sigma, forget=0.1, weight_floor=0.0, max_neighbours=3000)
    m.update(x)
    # put the test's weights in (update gives every first sample weight 1)
    from scipy.spatial import cKDTree
    from appliance.perception.novelty import _Snapshot
    m._snap = _Snapshot(x, w, float(w.sum()), cKDTree(x), 1)
    q = np.vstack([x[:50] + 0.01, rng.uniform(0, 1, (200, 8))]).astype(np.float32)
    got = m.density(q)
    ref3 = parzen_density_bruteforce(q, x, w, sigma, cutoff_sigmas=3.0)
    np.testing.assert_allclose(got, ref3, rtol=1e-5, atol=1e-12 * kernel_norm(sigma))
    # the 3-sigma cut only drops far samples: near a dense cluster it keeps most of the mass
    full = parzen_density_bruteforce(q, x, w, sigma)
    assert np.all(got <= full * (1 + 1e-6)) and np.all(got[:50] >= 0.8 * full[:50])


def test_density_with_few_neighbours_is_a_lower_bound_and_empty_model_is_zero():
    rng = np.random.default_rng(1)
    x = rng.normal(0.5, 0.02, (500, 8)).astype(np.float32)
    m = ParzenModel(0.05, 0.1, 0.0, max_neighbours=16)
    assert m.density(x[:3]).tolist() == [0.0, 0.0, 0.0]
    m.update(x)
    got = m.density(x[:20])
    ref = parzen_density_bruteforce(x[:20], x, np.ones(500), 0.05, 3.0)
    assert np.all(got <= ref * (1 + 1e-6)) and np.all(got > 0)


@pytest.mark.parametrize("k_first", [1, 8])
def test_screened_density_decides_exactly_like_the_full_query(k_first):
    rng = np.random.default_rng(2)
    x = rng.normal(0.5, 0.03, (4000, 8)).astype(np.float32)
    x[:400] = rng.uniform(0, 1, (400, 8))                  # a sparse part: low densities
    m = ParzenModel(0.05, 0.1, 0.0, max_neighbours=64)
    m.update(x)
    q = np.vstack([x[:300] + 0.005, rng.uniform(0, 1, (300, 8)),
                   rng.normal(0.5, 0.05, (300, 8))]).astype(np.float32)
    full = m.density(q)
    assert (full == 0).any() and (full > 0).mean() > 0.5
    for rho in np.quantile(full[full > 0], [0.05, 0.5, 0.95]):
        got = m.density_screened(q, rho, k_first=k_first)
        np.testing.assert_array_equal(got < rho, full < rho)         # the same novel cells
        low = full < rho
        assert low.any() and (~low).any()
        np.testing.assert_allclose(got[low], full[low], rtol=1e-9)   # exact where novel
        assert np.all(got[~low] >= rho) and np.all(got <= full * (1 + 1e-9))


def test_detector_scores_exact_for_novel_cells_or_everywhere_on_request():
    o = StereoNoveltyConfig(cell_px=32, rho=1e4)
    grass = _real("grass.png")
    other = _real("brick.png")[:grass.shape[0], :grass.shape[1]]
    img = grass.copy()
    img[:, : img.shape[1] // 2] = other[:, : img.shape[1] // 2]        # half new texture
    fast, exact = NoveltyDetector(o, background=False), NoveltyDetector(o, background=False,
                                                                        exact_scores=True)
    for d in (fast, exact):
        d.learn(d.detect(grass), force=True)
    a, b = fast.detect(img), exact.detect(img)
    np.testing.assert_array_equal(a.raw, b.raw)                       # the same novel cells
    assert a.raw.any() and (~a.raw).any()
    np.testing.assert_allclose(a.score[a.raw], b.score[a.raw], rtol=1e-5)
    assert np.all(a.score[~a.raw] >= b.score[~a.raw] - 1e-4)          # upper bound elsewhere
    ref = -np.log10(np.maximum(exact.model.density(b.descriptors.reshape(-1, 8)), 1e-300))
    finite = np.isfinite(b.score.ravel())
    np.testing.assert_allclose(b.score.ravel()[finite], ref[finite], rtol=1e-5)


# ---- forgetting and pruning (eqs. 6, 7, 9) ------------------------------------------------
def test_weights_first_one_then_lambda_with_decay():
    lam = 0.2
    m = ParzenModel(0.1, lam, weight_floor=0.0)
    a, b, c = (np.full((2, 8), v, np.float32) for v in (0.1, 0.5, 0.9))
    m.update(a)
    m.update(b)
    m.update(c)
    _, w = m.samples()
    np.testing.assert_allclose(w, [(1 - lam) ** 2] * 2 + [lam * (1 - lam)] * 2 + [lam] * 2)
    assert effective_forget(lam, 40) == pytest.approx(1 - (1 - lam) ** (1 / 40))
    # forgetting 40 times at lambda_eff equals one step at lambda (eq. 9)
    assert (1 - effective_forget(lam, 40)) ** 40 == pytest.approx(1 - lam)


def test_pruning_bounds_memory_and_forgets_old_appearance():
    lam, floor, per = 0.3, 0.01, 50
    m = ParzenModel(0.05, lam, weight_floor=floor)
    rng = np.random.default_rng(2)
    old = rng.normal(0.2, 0.01, (per, 8)).astype(np.float32)
    m.update(old)
    assert m.density(old[:5]).min() > 0
    sizes = []
    for _ in range(40):
        m.update(rng.normal(0.8, 0.01, (per, 8)).astype(np.float32))
        sizes.append(m.size)
    assert max(sizes) <= m.max_size(per)
    assert sizes[-1] == sizes[-10]                      # plateau
    _, w = m.samples()
    assert w.min() >= floor
    assert m.density(old[:5]).max() == 0.0               # the old field has been forgotten


def test_background_update_runs_in_its_own_thread():
    m = ParzenModel(0.05, 0.1, 0.0)
    seen = []
    real = m.update

    def slow_update(samples):
        seen.append(threading.current_thread().name)
        time.sleep(0.2)
        real(samples)
    m.update = slow_update
    up = BackgroundUpdater(m)
    try:
        t0 = time.perf_counter()
        up.submit(np.zeros((10, 8), np.float32))
        assert time.perf_counter() - t0 < 0.05           # the caller never waits
        assert up.wait_idle(5.0)
        assert seen == ["novelty-update"] and m.size == 10
    finally:
        up.close()


# ---- masking ------------------------------------------------------------------------------
def test_islanding_keeps_only_cells_with_novel_neighbours_and_dilation_grows():
    m = np.zeros((8, 10), bool)
    m[1, 1] = True                       # isolated: dropped
    m[5, 5] = m[5, 6] = True             # a pair: kept
    m[2, 8] = m[3, 9] = True             # diagonal neighbours count
    out = island_filter(m, 1)
    assert not out[1, 1] and out[5, 5] and out[5, 6] and out[2, 8] and out[3, 9]
    assert island_filter(m, 0).sum() == m.sum()
    d = dilate_cells(out, 1)
    assert d[4:7, 4:8].all() and d.sum() == 12 + 11  # 3x4 block + the clipped diagonal pair
    assert not d[0, 0]


def test_obstacle_cells_margin():
    ex = obstacle_cells(np.array([[100.0, 70.0]]), (10, 10), 32, 40.0)
    # pixel (100, 70) is in cell (row 2, col 3); 40 px margin -> 2 cells around it
    assert ex[2, 3] and ex[0, 1] and ex[4, 5] and not ex[5, 3] and not ex[2, 6]
    assert ex.sum() == 25


def _cfg(**kw):
    base = dict(cell_px=32, sigma=0.05, rho=1.0, forget=0.3, update_every_frames=1, weight_floor=1e-3,
                stabilise="off", island_min_neighbours=1, dilate_cells=0)
    base.update(kw)
    return StereoNoveltyConfig(**base)


def _scene_with_patch(grass, brick, patch=True):
    img = grass.copy()
    if patch:
        img[160:288, 192:320] = brick[160:288, 192:320]
    return img


def test_novel_patch_is_found_and_obstacle_feedback_keeps_it_novel():
    grass, brick = _real("grass.png"), _real("brick.png")
    brick = (brick * np.array([0.4, 0.6, 1.0])).astype(np.uint8)      # a reddish object
    det = NoveltyDetector(_cfg(), background=False)
    ref = det.detect(_scene_with_patch(grass, brick, False))
    assert ref.mask.all()                               # empty model: everything novel
    det.learn(ref)
    img = _scene_with_patch(grass, brick)
    patch = np.zeros(ref.mask.shape, bool)
    patch[5:9, 6:10] = True
    r = det.detect(img)
    assert r.mask[patch].mean() > 0.9 and r.mask[~patch].mean() < 0.1
    # keep learning this view, with the obstacle cells masked out: the patch stays novel
    for _ in range(10):
        r = det.detect(img)
        det.learn(r, exclude=patch)
    assert r.mask[patch].mean() > 0.9
    # without the feedback the obstacle becomes "normal"
    det2 = NoveltyDetector(_cfg(), background=False)
    det2.learn(det2.detect(_scene_with_patch(grass, brick, False)))
    for _ in range(10):
        r2 = det2.detect(img)
        det2.learn(r2)
    assert r2.mask[patch].mean() < 0.1


# ---- stabilisation ------------------------------------------------------------------------
def _cam():
    K = np.array([[550.0, 0, 320], [0, 550.0, 256], [0, 0, 1]])
    M = Mount(1.2, 0, 1.55, 0, 15.0, 0).camera_to_vehicle()
    return K, M


def _project(K, M, att, pw):
    c = M.T @ att.T @ pw
    p = K @ c
    return p[:2] / p[2]


def test_affine_takes_the_pixel_back_to_where_the_reference_attitude_saw_it():
    from hal.types import rotation_rpy
    K, M = _cam()
    prev = rotation_rpy(0.0, 0.0, 0.0)
    for r, p, y in [(0.0, 0.02, 0.0), (0.0, 0.0, -0.015), (0.02, 0.0, 0.0), (0.01, -0.02, 0.01)]:
        now = rotation_rpy(r, p, y)
        delta = prev.T @ now
        A = Stabiliser.affine(delta, K, M)
        for pw in ([10.0, 0.0, -1.5], [8.0, 2.0, -1.0], [20.0, -3.0, 0.0]):
            pw = np.array(pw)
            u_now, u_ref = _project(K, M, now, pw), _project(K, M, prev, pw)
            got = A[:, :2] @ u_now + A[:, 2]
            assert np.abs(got - u_ref).max() < 1.5, (r, p, y, got, u_ref)
    # nose down: the scene moves up in the camera, the stabilised image moves it back down
    A = Stabiliser.affine(rotation_rpy(0, 0.02, 0), K, M)
    assert A[1, 2] == pytest.approx(550 * math.tan(0.02), rel=0.05)


def test_high_pass_decays_a_held_attitude_by_one_minus_alpha():
    K, M = _cam()
    st = Stabiliser(alpha=0.2, mode="attitude")
    img = np.zeros((512, 640, 3), np.uint8)
    v = lambda p: VehicleState(0, 0, pitch_rad=p)  # noqa: E731
    st.update(img, K, M, v(0.0))
    acc = st.update(img, K, M, v(0.03))                 # a step of 0.03 rad nose down
    assert math.degrees(0.03) == pytest.approx(_angle(acc), rel=1e-6)
    for n in range(1, 6):
        acc = st.update(img, K, M, v(0.03))             # held: no relative rotation
        assert _angle(acc) == pytest.approx(math.degrees(0.03) * 0.8 ** n, rel=1e-6)


def _angle(r):
    from appliance.perception.novelty import rotation_angle_deg
    return rotation_angle_deg(r)


def test_visual_odometry_recovers_a_rotation_of_a_real_photo():
    img = _real("gravel.png")
    K = np.array([[400.0, 0, 256], [0, 400.0, 256], [0, 0, 1]])
    vo = VisualOdometry(K, img.shape[1], work_width=512)
    assert vo.relative(img) is None
    rv = np.array([0.0, 0.03, 0.0])                      # a yaw of the optical frame
    R, _ = cv2.Rodrigues(rv)
    H = K @ R @ np.linalg.inv(K)
    img2 = cv2.warpPerspective(img, H, (img.shape[1], img.shape[0]),
                               borderMode=cv2.BORDER_REFLECT)
    got = vo.relative(img2)
    assert got is not None
    rv_got, _ = cv2.Rodrigues(got)
    # x_now = R x_prev for image points: the camera turned by R^T
    np.testing.assert_allclose(rv_got.ravel(), -rv, atol=3e-3)
