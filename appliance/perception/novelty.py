"""The novelty detector of Ross et al. (seed 000), pure and deterministic apart from the
background model-update thread.

Stages (paper section III):

- :class:`Stabiliser` — a rotation estimate (the vehicle's attitude when the link gives it, else
  monocular visual odometry from OpenCV features, rotation only), high-pass filtered: each step
  the accumulated rotation is scaled by ``(1 - alpha)`` (its rotation vector) before the new
  relative rotation is composed on. The image goes into the stabilised frame by the paper's
  approximate transform: rotated by the roll and shifted by the pitch and yaw (the first-order
  form of the rotation homography ``K Mt R M K^-1``); the novelty mask goes back through the
  inverse.
- :func:`cell_descriptors` — per 32x32-pixel cell ``[Lmu amu bmu Lsd asd bsd u v]`` (eq. 1), each
  in [0, 1], then multiplied by the scaling vector ``s`` (eq. 5).
- :class:`ParzenModel` — the weighted Parzen-window density (eqs. 3, 4, 8) with a spherical
  Gaussian kernel, from the neighbours within 3 sigma found by a k-d tree (the paper's FLANN);
  weights 1 on the first update, lambda after, every update multiplies old weights by
  ``(1 - lambda)`` (eqs. 6, 7), and samples below a weight floor are dropped so memory is bounded.
- :class:`BackgroundUpdater` — the model update every N frames, in its own thread; the loop only
  hands it a snapshot and picks up a finished model (never waits for it).
- :func:`island_filter`, :func:`dilate_cells` — masking; :func:`obstacle_cells` — cells near
  detected obstacles are never learnt.
"""
from __future__ import annotations

import collections
import math
import threading
from dataclasses import dataclass

import cv2
import numpy as np

D = 8                       # descriptor dimensionality (eq. 1)
POOL = 8                    # pixels per pooled sample for the stabilising warp (cell_px / 4)
LIGHT_UPDATES = 20          # a model's light: that of most of its newest updates (the strobe's
#                             unlit probe frames at night are a few of them)
BOOT_LIGHT_FRAMES = 30      # a loaded day model is set aside at a strobe-lit frame this soon
#                             after the load (3 s at 10 Hz: a night boot's unlit first frames)
NIGHT_LIGHT = "night-strobe"  # the frames' illumination when the strobe lights them


# ---------------------------------------------------------------------------------------------
# descriptors (eq. 1, 5)
# ---------------------------------------------------------------------------------------------
def grid_shape(height: int, width: int, cell_px: int) -> tuple[int, int]:
    """(rows, cols) of the cell grid: whole cells only, at least one."""
    return max(1, height // cell_px), max(1, width // cell_px)


_scratch = threading.local()


def _buffer(name: str, shape: tuple, dtype=np.float32) -> np.ndarray:
    """A per-thread scratch array reused from frame to frame: a fresh multi-megabyte array
    costs its page faults on every frame (measured: half the descriptor stage at 640x512)."""
    bufs = getattr(_scratch, "bufs", None)
    if bufs is None:
        bufs = _scratch.bufs = {}
    b = bufs.get(name)
    if b is None or b.shape != shape or b.dtype != dtype:
        b = bufs[name] = np.empty(shape, dtype)
    return b


def lab_planes(bgr: np.ndarray, reuse: bool = False) -> np.ndarray:
    """Lab in [0, 1] per channel, float32 (OpenCV's 8-bit Lab: L*255/100, a+128, b+128).
    ``reuse``: write into this thread's scratch buffer (valid until the next call)."""
    if bgr.ndim == 2:
        bgr = cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
    if bgr.dtype != np.uint8:
        raise ValueError(f"expected a uint8 BGR image, got {bgr.dtype}")
    lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2Lab)
    if not reuse:
        return lab.astype(np.float32) * np.float32(1.0 / 255.0)
    out = _buffer("lab", lab.shape)
    np.multiply(lab, np.float32(1.0 / 255.0), out=out, casting="unsafe")
    return out


def _moments_to_descriptors(mean: np.ndarray, sq: np.ndarray, centre=None) -> np.ndarray:
    """From per-cell E[x - c] and E[(x - c)^2] (c = ``centre``, default 0)."""
    rows, cols = mean.shape[:2]
    # std of a [0, 1] variable is at most 0.5: doubled so it spans the same range (paper III-B)
    sd = 2.0 * np.sqrt(np.maximum(sq - mean * mean, 0.0))
    if centre is not None:
        mean = mean + centre
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    uu = (u + 0.5) / cols
    vv = (v + 0.5) / rows
    return np.concatenate([mean, sd, uu[..., None], vv[..., None]], axis=2).astype(np.float32)


def cell_descriptors(bgr: np.ndarray, cell_px: int = 32) -> np.ndarray:
    """Unscaled descriptors x-hat (rows, cols, 8) of the image's cells, every entry in [0, 1]."""
    lab = lab_planes(bgr)
    rows, cols = grid_shape(lab.shape[0], lab.shape[1], cell_px)
    f = lab[:rows * cell_px, :cols * cell_px]
    if f.shape[0] < cell_px or f.shape[1] < cell_px:       # smaller than one cell: one cell
        f = lab
    # moments about the image's mean colour: less float32 cancellation in E[x^2] - E[x]^2
    c = np.asarray(cv2.mean(f)[:3], np.float32)
    f = f - c
    mean = cv2.resize(f, (cols, rows), interpolation=cv2.INTER_AREA)
    sq = cv2.resize(f * f, (cols, rows), interpolation=cv2.INTER_AREA)
    return _moments_to_descriptors(mean, sq, c)


# ---------------------------------------------------------------------------------------------
# stabilisation (paper III-A)
# ---------------------------------------------------------------------------------------------
def rotvec_scale(r: np.ndarray, k: float) -> np.ndarray:
    """The rotation with the same axis as ``r`` and ``k`` times its angle."""
    rv, _ = cv2.Rodrigues(np.asarray(r, np.float64))
    out, _ = cv2.Rodrigues(rv * k)
    return out


def rotation_angle_deg(r: np.ndarray) -> float:
    rv, _ = cv2.Rodrigues(np.asarray(r, np.float64))
    return float(np.degrees(np.linalg.norm(rv)))


class VisualOdometry:
    """Frame-to-frame camera rotation from tracked corners (Shi-Tomasi + pyramidal LK), through
    the essential matrix (RANSAC) and ``recoverPose``: the rotation part only."""

    def __init__(self, K: np.ndarray, width: int, max_features: int = 300, work_width: int = 320):
        self.k_full = np.asarray(K, np.float64)
        self.f = min(1.0, work_width / float(width))
        self.K = self.k_full.copy()
        self.K[:2] *= self.f
        self.max_features = max_features
        self.prev = None
        self.method = ""

    def relative(self, bgr: np.ndarray) -> np.ndarray | None:
        """Rotation of the camera since the previous call, as the body-free optical-frame matrix
        R with x_prev = R x_now for a distant point (None on the first frame or on failure)."""
        g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
        if self.f < 1.0:
            g = cv2.resize(g, None, fx=self.f, fy=self.f, interpolation=cv2.INTER_AREA)
        prev, self.prev = self.prev, g
        if prev is None or prev.shape != g.shape:
            return None
        p0 = cv2.goodFeaturesToTrack(prev, self.max_features, 0.01, 7)
        if p0 is None or len(p0) < 12:
            return None
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, g, p0, None, winSize=(15, 15), maxLevel=3)
        ok = st.ravel() == 1
        if ok.sum() < 12:
            return None
        a, b = p0[ok].reshape(-1, 2), p1[ok].reshape(-1, 2)
        # little parallax (a pure rotation, or far scenery): the essential matrix is degenerate,
        # the rotation homography K R K^-1 explains the flow; else rotation from E
        Hm, hin = cv2.findHomography(a, b, cv2.RANSAC, 1.0)
        if Hm is not None and hin is not None and hin.mean() > 0.9:
            R = np.linalg.inv(self.K) @ Hm @ self.K
            U, _, Vt = np.linalg.svd(R)
            R = U @ Vt
            if np.linalg.det(R) < 0:
                return None
            self.method = "homography"
        else:
            E, inl = cv2.findEssentialMat(a, b, self.K, method=cv2.RANSAC, prob=0.999,
                                          threshold=1.0)
            if E is None or E.shape != (3, 3):
                return None
            n, R, _, _ = cv2.recoverPose(E, a, b, self.K, mask=inl)
            if n < 8:
                return None
            self.method = "essential"
        # x_now = R x_prev (+ t): the camera turned by R^T
        return R.T


class Stabiliser:
    """High-pass filtered rotation and the affine that takes camera pixels to the stabilised
    frame. ``mode``: "attitude" (vehicle roll/pitch/yaw), "vo", "auto" (attitude when present,
    else VO) or "off"."""

    def __init__(self, alpha: float = 0.1, mode: str = "auto", max_deg: float = 20.0):
        self.alpha = float(alpha)
        self.mode = mode
        self.max_deg = max_deg
        self.acc = np.eye(3)                  # current attitude relative to the filtered reference
        self._prev_att = None
        self._vo: VisualOdometry | None = None
        self.source = "none"

    def reset(self):
        self.acc = np.eye(3)
        self._prev_att = None
        if self._vo is not None:
            self._vo.prev = None

    def update(self, bgr: np.ndarray, K: np.ndarray, M: np.ndarray, vehicle=None) -> np.ndarray:
        """Step the filter with this frame; returns the accumulated body-frame rotation."""
        from hal.types import rotation_rpy
        if self.mode == "off":
            self.source = "off"
            return self.acc
        delta = None
        if vehicle is not None and self.mode in ("attitude", "auto"):
            att = rotation_rpy(vehicle.roll_rad, vehicle.pitch_rad, vehicle.yaw_rad)
            if self._prev_att is not None:
                delta = self._prev_att.T @ att
            self._prev_att = att
            self.source = "attitude"
        elif self.mode in ("vo", "auto"):
            if self._vo is None or self._vo.k_full.shape != K.shape or not np.allclose(
                    self._vo.k_full, K):
                self._vo = VisualOdometry(K, bgr.shape[1])
            r_opt = self._vo.relative(bgr)
            if r_opt is not None:
                delta = M @ r_opt @ M.T          # optical -> vehicle body
            self.source = "vo"
        scaled = rotvec_scale(self.acc, 1.0 - self.alpha)
        self.acc = scaled @ delta if delta is not None else scaled
        if rotation_angle_deg(self.acc) > self.max_deg:   # a wild estimate: start again
            self.acc = np.eye(3)
        return self.acc

    @staticmethod
    def affine(acc: np.ndarray, K: np.ndarray, M: np.ndarray) -> np.ndarray:
        """2x3 affine (camera px -> stabilised px): the paper's approximation of the homography
        H = K M^T acc M K^-1 — a rotation by the roll about the principal point and a shift by
        pitch and yaw, matched to H at the principal point."""
        H = K @ M.T @ acc @ M @ np.linalg.inv(K)

        def ap(p):
            q = H @ np.array([p[0], p[1], 1.0])
            return q[:2] / q[2]
        c = np.array([K[0, 2], K[1, 2]])
        c2 = ap(c)
        e = ap(c + np.array([100.0, 0.0])) - c2
        th = math.atan2(e[1], e[0])                      # in-image rotation (the roll)
        cs, sn = math.cos(th), math.sin(th)
        R2 = np.array([[cs, -sn], [sn, cs]])
        t = c2 - R2 @ c
        return np.hstack([R2, t[:, None]])


def invert_affine(A: np.ndarray) -> np.ndarray:
    return cv2.invertAffineTransform(np.asarray(A, np.float64))


def stabilised_descriptors(bgr: np.ndarray, cell_px: int, A: np.ndarray | None):
    """Descriptors (rows, cols, 8) of the stabilised image and the cells' validity (the share of
    each stabilised cell that came from inside the camera image >= 0.75).

    The image's Lab and Lab^2 are pooled to POOL-pixel blocks (exact block means), warped by the
    affine at that resolution, and pooled again to cells: identical to :func:`cell_descriptors`
    when ``A`` is the identity."""
    H, W = bgr.shape[:2]
    rows, cols = grid_shape(H, W, cell_px)
    pool = max(1, cell_px // 4) if cell_px % 4 == 0 else 1
    if A is None or np.allclose(A, [[1, 0, 0], [0, 1, 0]], atol=1e-6):
        return cell_descriptors(bgr, cell_px), np.ones((rows, cols), bool)
    lab = lab_planes(bgr, reuse=True)
    f = lab[:rows * cell_px, :cols * cell_px]
    c = np.asarray(cv2.mean(f)[:3], np.float32)
    # in the scratch buffers, through OpenCV: numpy broadcasting the 3-vector over the last
    # axis runs an inner loop of length 3 (measured 2 ms of the 6 ms stage at 640x512)
    cv2.subtract(f, (float(c[0]), float(c[1]), float(c[2]), 0.0), dst=f)
    sq = cv2.multiply(f, f, dst=_buffer("lab2", f.shape))
    sw, sh = cols * cell_px // pool, rows * cell_px // pool
    m1 = cv2.resize(f, (sw, sh), interpolation=cv2.INTER_AREA)
    m2 = cv2.resize(sq, (sw, sh), interpolation=cv2.INTER_AREA)
    S = np.diag([1.0 / pool, 1.0 / pool, 1.0])
    A3 = np.vstack([A, [0, 0, 1]])
    # pooled-pixel centre (i+0.5)*pool - 0.5 in full px: use the same scaling both ways
    Ap = (S @ A3 @ np.linalg.inv(S))[:2]
    flags = cv2.INTER_LINEAR
    w1 = cv2.warpAffine(m1, Ap, (sw, sh), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    w2 = cv2.warpAffine(m2, Ap, (sw, sh), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    cover = cv2.warpAffine(np.ones((sh, sw), np.float32), Ap, (sw, sh), flags=flags,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    mean = cv2.resize(w1, (cols, rows), interpolation=cv2.INTER_AREA)
    sq = cv2.resize(w2, (cols, rows), interpolation=cv2.INTER_AREA)
    valid = cv2.resize(cover, (cols, rows), interpolation=cv2.INTER_AREA) >= 0.75
    return _moments_to_descriptors(mean, sq, c), valid


def mask_to_camera(mask_cells: np.ndarray, A: np.ndarray | None, size_wh: tuple[int, int],
                   cell_px: int) -> np.ndarray:
    """A stabilised-frame cell mask back into the camera frame, as a uint8 image of ``size_wh``
    (255 = novel), through the inverse of the stabilising affine."""
    W, H = size_wh
    rows, cols = mask_cells.shape
    m = mask_cells.astype(np.uint8) * 255
    big = np.zeros((H, W), np.uint8)
    up = cv2.resize(m, (cols * cell_px, rows * cell_px), interpolation=cv2.INTER_NEAREST)
    big[:up.shape[0], :up.shape[1]] = up[:H, :W]
    if A is None or np.allclose(A, [[1, 0, 0], [0, 1, 0]], atol=1e-6):
        return big
    # dst(x) = src(A x): camera pixel x maps to stabilised A x
    return cv2.warpAffine(big, np.asarray(A, np.float64), (W, H),
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


# ---------------------------------------------------------------------------------------------
# the weighted Parzen model (eqs. 2-9)
# ---------------------------------------------------------------------------------------------
def kernel_norm(sigma: float, dim: int = D) -> float:
    """1 / (sigma^D (2 pi)^(D/2)) of eq. 4."""
    return 1.0 / (sigma ** dim * (2.0 * math.pi) ** (dim / 2.0))


def parzen_density_bruteforce(q: np.ndarray, x: np.ndarray, w: np.ndarray, sigma: float,
                              cutoff_sigmas: float | None = None) -> np.ndarray:
    """Eq. 3 by brute force over every sample (the reference for tests)."""
    q = np.asarray(q, np.float64)
    x = np.asarray(x, np.float64)
    w = np.asarray(w, np.float64)
    if len(x) == 0:
        return np.zeros(len(q))
    d2 = ((q[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    k = kernel_norm(sigma, q.shape[1]) * np.exp(-d2 / (2 * sigma * sigma))
    if cutoff_sigmas is not None:
        k[d2 > (cutoff_sigmas * sigma) ** 2] = 0.0
    return (k * w[None, :]).sum(1) / w.sum()


@dataclass(frozen=True)
class _Snapshot:
    x: np.ndarray              # (N, D) float32 scaled samples
    w: np.ndarray              # (N,) float64 weights
    wsum: float
    tree: object               # scipy cKDTree or None
    updates: int


class ParzenModel:
    """Weighted samples and their k-d tree. :meth:`update` (eqs. 6, 7 and pruning) builds a new
    immutable snapshot and swaps it in with one assignment, so :meth:`density` may run in
    another thread at the same time without locks."""

    def __init__(self, sigma: float, forget: float, weight_floor: float,
                 max_neighbours: int = 64, cutoff_sigmas: float = 3.0, dim: int = D):
        if not (0.0 < forget < 1.0):
            raise ValueError("forget (lambda) must be in (0, 1)")
        self.sigma = float(sigma)
        self.forget = float(forget)
        self.weight_floor = float(weight_floor)
        self.max_neighbours = int(max_neighbours)
        self.cutoff = float(cutoff_sigmas) * self.sigma
        self.dim = dim
        self._snap = _Snapshot(np.zeros((0, dim), np.float32), np.zeros(0), 0.0, None, 0)

    # ---- reading ---------------------------------------------------------------------------
    @property
    def size(self) -> int:
        return len(self._snap.w)

    @property
    def updates(self) -> int:
        return self._snap.updates

    @property
    def empty(self) -> bool:
        return self.size == 0

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        s = self._snap
        return s.x, s.w

    def state(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Samples, weights and updates of one snapshot (a save while the background update
        runs must not pair one update's samples with the next one's count)."""
        s = self._snap
        return s.x, s.w, s.updates

    def memory_bytes(self) -> int:
        s = self._snap
        return int(s.x.nbytes + s.w.nbytes)

    def density(self, q: np.ndarray) -> np.ndarray:
        """p(x) of eq. 3 at each query (M, D): the kernel summed over the (at most
        ``max_neighbours``) samples within 3 sigma. Exact whenever fewer than max_neighbours
        samples lie within 3 sigma; otherwise a lower bound that is already far above any
        sensible threshold. Zero for an empty model."""
        s = self._snap
        q = np.asarray(q, np.float32).reshape(-1, self.dim)
        if s.tree is None or len(q) == 0:
            return np.zeros(len(q))
        k = min(self.max_neighbours, len(s.w))
        dist, idx = s.tree.query(q, k=k, distance_upper_bound=self.cutoff)
        dist = np.asarray(dist, np.float64).reshape(len(q), k)
        idx = np.asarray(idx).reshape(len(q), k)
        ok = np.isfinite(dist)
        idx = np.where(ok, idx, 0)
        kern = np.where(ok, np.exp(-(dist * dist) / (2 * self.sigma ** 2)), 0.0)
        p = (kern * s.w[idx]).sum(1) * kernel_norm(self.sigma, self.dim) / s.wsum
        return p

    def density_screened(self, q: np.ndarray, threshold: float, k_first: int = 1) -> np.ndarray:
        """:meth:`density` where it matters for ``density < threshold``: each query first sums
        its ``k_first`` nearest samples (within 3 sigma); that partial sum is a lower bound, so
        a query already at or above ``threshold`` is certainly not novel and keeps it; the rest
        are evaluated in full. The decision ``p < threshold`` is the same as with
        :meth:`density`; values at or above ``threshold`` are lower bounds. (About 4x faster on
        a model of a few thousand samples: most cells look like the field. ``k_first`` = 1:
        the nearest sample alone already clears rho for the field's cells; 4 found the same
        novel cells on the bench frames at twice the time, 1.0 vs 2.0 ms at 40x32 cells.)"""
        s = self._snap
        q = np.asarray(q, np.float32).reshape(-1, self.dim)
        if s.tree is None or len(q) == 0:
            return np.zeros(len(q))
        k0 = min(k_first, self.max_neighbours, len(s.w))
        p = self._sum(s, q, k0)
        if k0 < min(self.max_neighbours, len(s.w)):
            low = np.flatnonzero(p < threshold)
            if len(low):
                p[low] = self._sum(s, q[low], min(self.max_neighbours, len(s.w)))
        return p

    def _sum(self, s: _Snapshot, q: np.ndarray, k: int) -> np.ndarray:
        dist, idx = s.tree.query(q, k=k, distance_upper_bound=self.cutoff)
        dist = np.asarray(dist, np.float64).reshape(len(q), k)
        idx = np.asarray(idx).reshape(len(q), k)
        ok = np.isfinite(dist)
        idx = np.where(ok, idx, 0)
        kern = np.where(ok, np.exp(-(dist * dist) / (2 * self.sigma ** 2)), 0.0)
        return (kern * s.w[idx]).sum(1) * kernel_norm(self.sigma, self.dim) / s.wsum

    # ---- writing (background thread) -------------------------------------------------------
    def update(self, samples: np.ndarray) -> None:
        """One model update: old weights times (1 - lambda) (eq. 7), new samples weighted 1 on
        the first update and lambda after (eq. 6), samples below the floor dropped, tree
        rebuilt."""
        from scipy.spatial import cKDTree
        s = self._snap
        new = np.asarray(samples, np.float32).reshape(-1, self.dim)
        first = s.updates == 0
        w_old = s.w * (1.0 - self.forget)
        w_new = np.full(len(new), 1.0 if first else self.forget)
        x = np.concatenate([s.x, new]) if len(s.x) else new.copy()
        w = np.concatenate([w_old, w_new])
        keep = w >= self.weight_floor
        x, w = np.ascontiguousarray(x[keep]), w[keep]
        tree = cKDTree(x, leafsize=32, balanced_tree=False, compact_nodes=False) if len(x) else None
        self._snap = _Snapshot(x, w, float(w.sum()), tree, s.updates + 1)

    def load(self, x: np.ndarray, w: np.ndarray, updates: int) -> None:
        """Replace the samples (a saved model); the tree is rebuilt."""
        from scipy.spatial import cKDTree
        x = np.ascontiguousarray(x, np.float32).reshape(-1, self.dim)
        w = np.asarray(w, np.float64).reshape(-1)
        tree = cKDTree(x, leafsize=32, balanced_tree=False, compact_nodes=False) if len(x) else None
        self._snap = _Snapshot(x, w, float(w.sum()), tree, int(updates))

    def max_size(self, samples_per_update: int) -> int:
        """The most samples the model can ever hold when each update adds at most
        ``samples_per_update``: the batches younger than the lifetime of a lambda-weighted
        sample, plus the first batch (weight 1) while it lives."""
        lam, fl = self.forget, self.weight_floor
        if fl <= 0:
            return -1                                  # unbounded
        life = 0 if lam < fl else 1 + int(math.floor(math.log(fl / lam) / math.log(1 - lam)))
        return samples_per_update * (life + 1)


def effective_forget(lam: float, frames_between_updates: int) -> float:
    """Eq. 9: the per-frame forgetting factor equivalent to lambda every N frames."""
    return 1.0 - (1.0 - lam) ** (1.0 / frames_between_updates)


class BackgroundUpdater:
    """Runs :meth:`ParzenModel.update` in a daemon thread. :meth:`submit` hands over samples and
    returns at once; if an update is still running the new samples replace any waiting ones (a
    slot, not a queue), and the skip is counted."""

    def __init__(self, model: ParzenModel):
        self.model = model
        self._cv = threading.Condition()
        self._pending: np.ndarray | None = None
        self._busy = False
        self._stop = False
        self.skipped = 0
        self.done = 0
        self.last_update_s = 0.0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="novelty-update", daemon=True)
        self._thread.start()

    def submit(self, samples: np.ndarray) -> None:
        with self._cv:
            if self._pending is not None or self._busy:
                self.skipped += int(self._pending is not None)
            self._pending = np.array(samples, np.float32, copy=True)
            self._cv.notify()

    def _run(self):
        import time
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                samples, self._pending = self._pending, None
                self._busy = True
            t0 = time.perf_counter()
            try:
                self.model.update(samples)
            except BaseException as exc:          # noqa: BLE001 - reported through .error
                self.error = exc
            self.last_update_s = time.perf_counter() - t0
            with self._cv:
                self._busy = False
                self.done += 1
                self._cv.notify_all()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until no update is waiting or running (tests and offline tools only)."""
        with self._cv:
            return self._cv.wait_for(lambda: self._pending is None and not self._busy, timeout)

    def close(self):
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout=5.0)


# ---------------------------------------------------------------------------------------------
# masking (paper III-C)
# ---------------------------------------------------------------------------------------------
_K8 = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.float32)


def island_filter(mask: np.ndarray, min_neighbours: int = 1) -> np.ndarray:
    """Keep novel cells with at least ``min_neighbours`` novel 8-neighbours."""
    m = mask.astype(np.float32)
    n = cv2.filter2D(m, -1, _K8, borderType=cv2.BORDER_CONSTANT)
    return mask.astype(bool) & (n >= min_neighbours - 0.5)


def dilate_cells(mask: np.ndarray, cells: int = 1) -> np.ndarray:
    if cells <= 0:
        return mask.astype(bool)
    k = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def obstacle_cells(obstacle_px: np.ndarray, grid: tuple[int, int], cell_px: int,
                   margin_px: float) -> np.ndarray:
    """Cells (rows, cols) whose centre lies within ``margin_px`` (Chebyshev, in image pixels)
    of a pixel (N, 2: u, v) where an obstacle was detected: never learnt."""
    rows, cols = grid
    out = np.zeros((rows, cols), bool)
    p = np.asarray(obstacle_px, np.float64).reshape(-1, 2)
    if len(p) == 0:
        return out
    # per column: clipping an (N, 2) array against a 2-list broadcasts with an inner loop of 2
    cu = np.clip((p[:, 0] // cell_px).astype(np.intp), 0, cols - 1)
    cv = np.clip((p[:, 1] // cell_px).astype(np.intp), 0, rows - 1)
    out[cv, cu] = True
    r = int(math.ceil(margin_px / cell_px))
    return dilate_cells(out, r)


# ---------------------------------------------------------------------------------------------
# the detector
# ---------------------------------------------------------------------------------------------
@dataclass
class NoveltyResult:
    score: np.ndarray          # (rows, cols) float32: -log10 density (higher = more novel);
    #                            exact for novel cells, an upper bound for the others
    raw: np.ndarray            # (rows, cols) bool: density < rho (stabilised frame)
    mask: np.ndarray           # (rows, cols) bool: after islanding and dilation (stabilised)
    valid: np.ndarray          # (rows, cols) bool: stabilised cell inside the camera image
    descriptors: np.ndarray    # (rows, cols, 8) scaled
    affine: np.ndarray | None  # camera -> stabilised
    model_empty: bool
    cell_px: int = 32


class NoveltyDetector:
    """Descriptors, density, masks and learning. ``options`` is any object with the novelty
    fields of :class:`appliance.perception.stereo_novelty.StereoNoveltyConfig`."""

    def __init__(self, options, background: bool = True, exact_scores: bool = False):
        """``exact_scores``: the full density for every cell (offline tools that show the
        scores); by default only the novel cells' scores are exact (the loop needs the mask)."""
        o = options
        self.exact_scores = exact_scores
        self.o = o
        self.scale = np.asarray(o.descriptor_scale, np.float32)
        if self.scale.shape != (D,):
            raise ValueError(f"descriptor_scale needs {D} numbers, got {len(self.scale)}")
        self.model = ParzenModel(o.sigma, o.forget, o.weight_floor, o.max_neighbours,
                                 o.cutoff_sigmas)
        self.updater = BackgroundUpdater(self.model) if background else None
        self.stabiliser = Stabiliser(o.alpha, o.stabilise)
        self.frames = 0
        self._first_sent = False
        self._handed = 0                       # updates handed over (or loaded)
        self._boot_exclude = None              # the boot check's cells (the first update's)
        self._log_rho = -math.log10(o.rho)
        self._lights: collections.deque = collections.deque(maxlen=LIGHT_UPDATES)
        self.loaded_light: str | None = None   # the light a loaded model was learnt under
        self._loaded_at = None                 # self.frames when it was loaded
        self._night_state = None               # a kept strobe-lit model (keep_night_model)

    # ---- per frame -------------------------------------------------------------------------
    def cell_px_for(self, width: int) -> int:
        """The configured cell size, or width / 40 (the paper's grid) when it is 0."""
        return int(self.o.cell_px) or max(4, int(round(width / 40.0)))

    def detect(self, bgr: np.ndarray, K: np.ndarray | None = None, M: np.ndarray | None = None,
               vehicle=None, cell_px: int | None = None) -> NoveltyResult:
        """``cell_px`` overrides the configured cell size (a caller that hands over a
        downscaled image passes the cell size scaled with it)."""
        cell = cell_px or self.cell_px_for(bgr.shape[1])
        A = None
        if K is not None and M is not None and self.o.stabilise != "off":
            acc = self.stabiliser.update(bgr, K, M, vehicle)
            A = Stabiliser.affine(acc, K, M)
        desc, valid = stabilised_descriptors(bgr, cell, A)
        x = desc * self.scale
        rows, cols = x.shape[:2]
        if self.model.empty:
            score = np.full((rows, cols), np.inf, np.float32)
        else:
            # exact below rho (the novel cells), a lower bound on the density above it
            q = x.reshape(-1, D)
            p = (self.model.density(q) if self.exact_scores
                 else self.model.density_screened(q, self.o.rho)).reshape(rows, cols)
            with np.errstate(divide="ignore"):
                score = (-np.log10(p)).astype(np.float32)
        raw = (score > self._log_rho) & valid
        mask = island_filter(raw, self.o.island_min_neighbours)
        mask = dilate_cells(mask, self.o.dilate_cells) & valid
        return NoveltyResult(score, raw, mask, valid, x, A, self.model.empty, cell)

    @property
    def first_sent(self) -> bool:
        """True once the first update has been handed over (or a saved model was loaded)."""
        return self._first_sent

    @property
    def light(self) -> str | None:
        """The light (a frame's ``illumination``) most of the model's newest updates were
        learnt under; None before the first or when no frame said."""
        named = [x for x in self._lights if x]
        if not named:
            return None
        # a tie goes to the newer light (never to a set's order: the file would differ by run)
        return max(dict.fromkeys(reversed(named)), key=named.count)

    def set_aside_other_light(self, light: str | None) -> str | None:
        """A model loaded from the state directory that was learnt by day, met by a frame lit
        by the strobe within ``BOOT_LIGHT_FRAMES`` of the load: it is set aside, and replaced
        by the strobe-lit model kept beside it (:meth:`keep_night_model`: the state
        directory's night file) if there is one, else the detector starts empty (the first
        update, with the boot check, is this frame's). Returns what happened: "night model",
        "empty", or None (nothing). Only that way round: measured (tools/boot_with_model.py
        --cross, thirtieth session), a night model by day changed nothing, a day model at
        night made the boot's false stops; and a box booting at night labels its first frames
        "day" (the strobe is off until the day/night switch has seen a dark frame), so a day
        frame says nothing at boot."""
        if (self.loaded_light != "day" or light != NIGHT_LIGHT or self._loaded_at is None
                or self.frames - self._loaded_at > BOOT_LIGHT_FRAMES):
            return None
        self.wait_idle(5.0)
        night, self._night_state = self._night_state, None
        self._boot_exclude = None
        if night is not None:
            self._install(*night)
            return "night model"
        self.model.load(np.zeros((0, D), np.float32), np.zeros(0), 0)
        self._first_sent = False
        self._handed = 0
        self._lights.clear()
        self.loaded_light = self._loaded_at = None
        return "empty"

    def learn(self, result: NoveltyResult, exclude: np.ndarray | None = None,
              force: bool = False, first_exclude: np.ndarray | None = None,
              light: str | None = None) -> bool:
        """Count a frame; on the first frame and every ``update_every_frames`` hand its valid
        cells (minus ``exclude``, cells near obstacles) to the background update. Returns True
        when samples were handed over.

        The first update ignores ``exclude`` (the paper's model "fully initialised at
        start-up": an empty model calls everything novel, so stereo noise near the ground
        would otherwise keep those cells out of the model for good) and leaves out only
        ``first_exclude``: what the boot check (full-frame stereo, the learned cue) vouches
        stands above the ground (issue #14: never learn a person standing ahead at boot).
        The warm-up's updates (``warmup_updates``) leave ``first_exclude`` out too: the young
        model is not to learn at 2-frame intervals what the boot check could not vouch for."""
        self.frames += 1
        first = not self._first_sent
        period = self.o.update_every_frames
        warming = self._handed < getattr(self.o, "warmup_updates", 0)
        if warming:
            period = min(period, self.o.warmup_every_frames)
        if not (first or force or self.frames % period == 0):
            return False
        keep = result.valid.copy()
        if first and first_exclude is not None:
            keep &= ~first_exclude
            self._boot_exclude = first_exclude.copy()
        if exclude is not None and not first:
            keep &= ~exclude
        if (warming and not first and self._boot_exclude is not None
                and self._boot_exclude.shape == keep.shape):
            keep &= ~self._boot_exclude
        samples = result.descriptors[keep]
        if len(samples) == 0:
            return False
        self._first_sent = True
        self._handed += 1
        self._lights.append(light)
        if self.updater is not None:
            self.updater.submit(samples)
        else:
            self.model.update(samples)
        return True

    def wait_idle(self, timeout: float = 10.0) -> bool:
        return True if self.updater is None else self.updater.wait_idle(timeout)

    # ---- persistence (the file itself is appliance.novelty_store's: perception does no I/O)
    STATE_VERSION = 1

    def fingerprint(self) -> dict:
        """What a saved model must match to be this detector's: the descriptor's definition
        and the kernel (a model of other units is a foreign model)."""
        o = self.o
        return {"dim": D, "descriptor_scale": [float(v) for v in self.scale],
                "sigma": float(o.sigma), "cell_px": int(o.cell_px),
                "descriptor_width_px": int(getattr(o, "descriptor_width_px", 0))}

    def export_state(self) -> dict:
        """The model as plain arrays and numbers (None while it is empty)."""
        x, w, updates = self.model.state()
        if len(w) == 0:
            return None
        out = {"version": self.STATE_VERSION, "fingerprint": self.fingerprint(),
               "x": np.array(x, np.float32), "w": np.array(w, np.float64),
               "updates": int(updates)}
        if self.light is not None:
            out["light"] = self.light
        return out

    def _checked(self, state: dict) -> tuple:
        """(x, w, updates, light) of a saved model (from :meth:`export_state`), or ValueError
        naming what does not fit this detector (version, fingerprint, shapes, values)."""
        if not isinstance(state, dict):
            raise ValueError("not a novelty model")
        if state.get("version") != self.STATE_VERSION:
            raise ValueError(f"model version {state.get('version')!r}, this build reads "
                             f"{self.STATE_VERSION}")
        fp = state.get("fingerprint")
        if fp != self.fingerprint():
            raise ValueError(f"model made with other settings ({fp}, here "
                             f"{self.fingerprint()})")
        x = np.asarray(state.get("x"))
        w = np.asarray(state.get("w"))
        if x.ndim != 2 or x.shape[1] != D or w.shape != (len(x),) or len(x) == 0:
            raise ValueError(f"model arrays of shapes {x.shape} and {w.shape}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(w)) and np.all(w > 0)):
            raise ValueError("model holds non-finite samples or non-positive weights")
        updates = int(state.get("updates", 1))
        light = state.get("light")
        if light is not None and not isinstance(light, str):
            raise ValueError(f"model light {light!r} is not a name")
        return x.astype(np.float32), w.astype(np.float64), max(1, updates), light

    def import_state(self, state: dict) -> None:
        """Take a saved model (from :meth:`export_state`). Raises ValueError naming what does
        not fit (version, fingerprint, shapes, values); the detector is unchanged then."""
        self._install(*self._checked(state))

    def keep_night_model(self, state: dict) -> None:
        """Keep a saved strobe-lit model (checked as :meth:`import_state` checks; ValueError
        otherwise, and nothing kept) to replace a day model loaded at boot if the strobe turns
        out to light the frames (:meth:`set_aside_other_light`)."""
        x, w, updates, light = self._checked(state)
        if light != NIGHT_LIGHT:
            raise ValueError(f"model learnt under {light or 'unrecorded'} light, not "
                             f"{NIGHT_LIGHT}")
        self._night_state = (x, w, updates, light)

    def _install(self, x, w, updates, light) -> None:
        self.model.load(x, w, updates)
        self.loaded_light, self._loaded_at = light, self.frames
        self._lights.clear()
        self._lights.append(light)
        self._first_sent = True
        # a model learnt before (the state directory's) is no young one: no warm-up
        self._handed = max(1, updates, getattr(self.o, "warmup_updates", 0))

    def close(self):
        if self.updater is not None:
            self.updater.close()
