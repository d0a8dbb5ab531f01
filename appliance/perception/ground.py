"""The ground, estimated every frame from the points the sensor sees (stereo or depth).

Height above a level plane is wrong wherever the ground is not that plane: a contour bank, a
headland slope, and above all a pitching vehicle (1.2 deg of pitch lifts the ground 0.4 m at
20 m, near the height band's lower edge). :func:`fit_ground` fits a smooth surface
``z = a + b x + c y + d x^2 + e x y`` (vehicle frame, metres) to the LOW envelope of the points:

1. the points are binned on the ground plane (``x_bin_m`` by ``y_bin_m``) and each bin gives a
   low percentile of its heights (``percentile``; a 5 cm height histogram per bin, no sort),
   so an obstacle standing in a bin does not lift it while most of the bin sees the ground;
2. the surface is fitted to the bins' heights by iteratively re-weighted least squares
   (Tukey weights, 3 ``robust_m`` after a first wide pass, the bins' weights capped: bins on an obstacle, or a mismatch blob, get weight 0),
   each bin weighted by the square root of its point count, with a ridge prior that pulls the
   surface toward the level plane ``z = 0`` (``prior``): with few bins the level plane wins;
3. what the smooth surface cannot follow (a contour bank's crest) is an along-range profile:
   each range row's mean residual over its bins that see the ground, at most
   ``profile_max_m``, smoothed;
4. a fit that leaves the plausible envelope (more than ``max_dev_m`` + ``max_slope`` x range
   from level anywhere in the fitted area) is refused and the level plane used instead
   (``GroundModel.source = "level"``).

:func:`horizon_far_mask` treats the sky and the far horizon as what they are: a point higher
than the camera and farther than ``far_m`` is the sky or the horizon's skyline (a matcher
fills the textureless sky with small disparities), not an obstacle; an obstacle near enough to
matter is seen by its lower part too.

Pure numpy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_X0 = 10.0                  # feature scaling (x / 10 m): a well-conditioned normal matrix


@dataclass(frozen=True)
class GroundModel:
    """``z = a + b x + c y + d x^2 + e x y`` (x, y scaled by 10 m), vehicle frame."""

    coef: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)
    bins: int = 0               # bins that carried the fit (weight > 0.5)
    source: str = "level"       # "fit" | "level"
    x_max_m: float = 0.0        # the fitted area's far edge (beyond it: the surface at x_max)
    profile_x: tuple = ()       # along-range correction: x of each range row's centre ...
    profile_z: tuple = ()       # ... and the row's residual height (linear in between)

    @staticmethod
    def level() -> "GroundModel":
        return GroundModel()

    def z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        a, b, c, d, e = self.coef
        if self.source == "level":
            return np.zeros(np.shape(x))
        xm = np.minimum(np.asarray(x, np.float64), self.x_max_m)
        xs = xm / _X0
        ys = np.asarray(y, np.float64) / _X0
        z = a + b * xs + c * ys + d * xs * xs + e * xs * ys
        if self.profile_x:
            z = z + np.interp(xm, self.profile_x, self.profile_z)
        return z

    def height(self, pts: np.ndarray) -> np.ndarray:
        """Height (N,) of points (N, 3) above this ground."""
        p = np.asarray(pts).reshape(-1, 3)
        if self.source == "level":
            return p[:, 2].astype(np.float64, copy=True)
        return p[:, 2] - self.z(p[:, 0], p[:, 1])

    def pitch_deg(self) -> float:
        """The ground's mean slope along x over the fitted area's far three quarters, on the
        vehicle's centre line (positive = rising ahead)."""
        if self.source == "level" or self.x_max_m <= 0:
            return 0.0
        x0, x1 = 0.25 * self.x_max_m, self.x_max_m
        z0, z1 = self.z(np.array([x0, x1]), np.zeros(2))
        return float(np.degrees(np.arctan((z1 - z0) / (x1 - x0))))

    def to_dict(self) -> dict:
        return {"source": self.source, "bins": self.bins,
                "coef": [round(float(c), 4) for c in self.coef],
                "pitch_deg": round(self.pitch_deg(), 3)}


def _features(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    xs, ys = x / _X0, y / _X0
    return np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys], axis=1)


def bin_lows(pts: np.ndarray, x_min_m: float, x_max_m: float, y_half_m: float,
             x_bin_m: float, y_bin_m: float, percentile: float, min_points: int,
             z_lo: float = -3.0, z_hi: float = 3.0, z_step: float = 0.05):
    """Per ground bin with >= ``min_points`` points: (x centre, y centre, low-percentile
    height, count). The percentile comes from a ``z_step`` histogram of each bin."""
    p = np.asarray(pts, np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ok = (x >= x_min_m) & (x < x_max_m) & (np.abs(y) < y_half_m) & (z > z_lo) & (z < z_hi)
    x, y, z = x[ok], y[ok], z[ok]
    if len(x) == 0:
        return (np.zeros(0),) * 4
    nx = int(np.ceil((x_max_m - x_min_m) / x_bin_m))
    ny = int(np.ceil(2 * y_half_m / y_bin_m))
    nz = int(np.ceil((z_hi - z_lo) / z_step))
    ix = np.minimum(((x - x_min_m) / x_bin_m).astype(np.intp), nx - 1)
    iy = np.minimum(((y + y_half_m) / y_bin_m).astype(np.intp), ny - 1)
    iz = np.minimum(((z - z_lo) / z_step).astype(np.intp), nz - 1)
    b = ix * ny + iy
    nb = nx * ny
    counts = np.bincount(b, minlength=nb)
    sx = np.bincount(b, x, minlength=nb)
    sy = np.bincount(b, y, minlength=nb)
    hist = np.bincount(b * nz + iz, minlength=nb * nz).reshape(nb, nz)
    use = np.flatnonzero(counts >= min_points)
    if len(use) == 0:
        return (np.zeros(0),) * 4
    cum = np.cumsum(hist[use], axis=1)
    need = np.maximum(1, np.ceil(counts[use] * percentile / 100.0))[:, None]
    k = np.argmax(cum >= need, axis=1)
    zl = z_lo + (k + 0.5) * z_step
    c = counts[use].astype(np.float64)
    return sx[use] / c, sy[use] / c, zl, c


def fit_ground(pts: np.ndarray, x_min_m: float = 2.0, x_max_m: float = 25.0,
               y_half_m: float = 8.0, x_bin_m: float = 1.0, y_bin_m: float = 2.0,
               percentile: float = 30.0, min_points: int = 8, robust_m: float = 0.25,
               prior: float = 2.0, max_dev_m: float = 0.6, max_slope: float = 0.2,
               min_bins: int = 6, iterations: int = 4,
               profile_max_m: float = 0.3) -> GroundModel:
    """The ground under the points (N, 3), vehicle frame; see the module's docstring."""
    bx, by, bz, bc = bin_lows(pts, x_min_m, x_max_m, y_half_m, x_bin_m, y_bin_m, percentile,
                              min_points)
    if len(bx) < min_bins:
        return GroundModel.level()
    A = _features(bx, by)
    # near bins hold far more points than far ones (and a near obstacle's face more than the
    # ground around it): the square root of the count, capped at 3x the median's
    w0 = np.sqrt(np.minimum(bc, 3.0 * np.median(bc)))
    w0 = w0 / w0.mean()
    w = w0.copy()
    reg = prior * np.diag([1.0, 1.0, 1.0, 1.0, 1.0])
    coef = np.zeros(5)
    for it in range(iterations):
        Aw = A * w[:, None]
        coef = np.linalg.solve(Aw.T @ A + reg, Aw.T @ bz)
        r = bz - A @ coef
        # Tukey's biweight, a fixed scale: the bins' heights are good to a few cm where they
        # see the ground; one on an obstacle is off by its height
        u = r / (3.0 * robust_m) if it else r / (8.0 * robust_m)
        w = w0 * np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if w.sum() < 1e-6:
            return GroundModel.level()
    used = int(np.count_nonzero(w > 0.5 * w0))
    if used < min_bins:
        return GroundModel.level()
    xm = float(min(x_max_m, bx.max() + x_bin_m / 2))
    # the along-range profile (what the smooth surface cannot follow: a contour bank's crest,
    # a headland's edge): per range row, the mean residual of its bins that see the ground,
    # clipped to +-profile_max_m and smoothed [1 2 1]; a row of fewer than 2 such bins: 0
    r = bz - A @ coef
    row = ((bx - x_min_m) / x_bin_m).astype(np.intp)
    nrow = int(row.max()) + 1
    good = (w > 0.5 * w0) & (np.abs(r) < 2.0 * robust_m)
    cnt = np.bincount(row[good], minlength=nrow)
    sm = np.bincount(row[good], r[good], minlength=nrow)
    prof = np.where(cnt >= 2, sm / np.maximum(cnt, 1), 0.0)
    prof = np.clip(prof, -profile_max_m, profile_max_m)
    if nrow >= 3:
        pp = np.pad(prof, 1, mode="edge")
        prof = 0.25 * pp[:-2] + 0.5 * pp[1:-1] + 0.25 * pp[2:]
    px = x_min_m + (np.arange(nrow) + 0.5) * x_bin_m
    model = GroundModel(tuple(float(c) for c in coef), used, "fit", xm,
                        tuple(float(v) for v in px) if profile_max_m > 0 else (),
                        tuple(float(v) for v in prof) if profile_max_m > 0 else ())
    # plausibility over the fitted area
    gx, gy = np.meshgrid(np.linspace(x_min_m, xm, 8), np.linspace(-y_half_m, y_half_m, 5))
    dev = np.abs(model.z(gx.ravel(), gy.ravel()))
    if np.any(dev > max_dev_m + max_slope * gx.ravel()):
        return GroundModel.level()
    return model


class LocalGround:
    """A ground that follows the field bin by bin: ``base`` (the fitted surface or the level
    plane) plus a per-bin offset, the low envelope of the points' heights above ``base``
    eroded over the bin's neighbours (see :func:`local_ground`). Same interface as
    :class:`GroundModel` (``z``, ``height``, ``pitch_deg``, ``to_dict``, ``source``)."""

    source = "local"

    def __init__(self, base: GroundModel, x0: float, y0: float, cell_m: float,
                 offset: np.ndarray, bins: int):
        self.base, self.x0, self.y0, self.cell_m = base, float(x0), float(y0), float(cell_m)
        self.offset = offset               # (nx, ny) float64, 0 where nothing was seen
        self.bins = int(bins)
        self.x_max_m = base.x_max_m

    def z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        z = self.base.z(x, y)
        nx, ny = self.offset.shape
        ix = np.floor((x - self.x0) / self.cell_m).astype(np.intp)
        iy = np.floor((y - self.y0) / self.cell_m).astype(np.intp)
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        off = np.zeros(np.shape(x))
        off[inside] = self.offset[ix[inside], iy[inside]]
        return z + off

    def height(self, pts: np.ndarray) -> np.ndarray:
        p = np.asarray(pts).reshape(-1, 3)
        return p[:, 2] - self.z(p[:, 0], p[:, 1])

    def pitch_deg(self) -> float:
        return self.base.pitch_deg()

    def to_dict(self) -> dict:
        d = self.base.to_dict()
        off = self.offset[self.offset != 0]
        d.update({"source": "local", "base": self.base.source, "local_bins": self.bins,
                  "local_offset_m": [round(float(off.min()), 3), round(float(off.max()), 3)]
                  if len(off) else [0.0, 0.0]})
        return d


def local_ground(pts: np.ndarray, base: GroundModel | None = None, x_min_m: float = 0.0,
                 x_max_m: float = 25.0, y_half_m: float = 10.0, cell_m: float = 0.5,
                 percentile: float = 10.0, min_points: int = 6, erode_cells: int = 1,
                 max_dev_m: float = 0.5, z_step: float = 0.02,
                 max_down_m: float | None = None, min_seen: int = 1) -> LocalGround:
    """The ground under every bin of ``cell_m`` (vehicle frame, x in [x_min, x_max), |y| <
    y_half): the ``percentile`` of the heights above ``base`` of the bin's points (>=
    ``min_points`` of them; a ``z_step`` histogram, no sort), then the MINIMUM of that over the
    bin and its neighbours within ``erode_cells`` (an erosion). An object cannot lift the
    ground under it: its foot neighbours bins that see the ground (the soil before and beside
    it), and the erosion takes the lowest. A rise of the field lifts every bin on it, so a
    stubble tuft on a rise is measured from the rise. The offsets are clipped to
    ``[-max_down_m, +max_dev_m]`` around ``base`` (``max_down_m`` None: ``max_dev_m``; a
    mismatch blob below the ground, or a wall filling every bin around, cannot move the
    ground further); a bin whose neighbourhood (itself included) holds fewer than
    ``min_seen`` bins that saw enough points keeps ``base``: far away only the object's own
    bins are seen (the ground around it is too sparse at range), and the erosion would have
    nothing to take the ground from (a pole 15 m ahead lifted its own ground 0.5 m)."""
    max_down_m = max_dev_m if max_down_m is None else max_down_m
    base = base if base is not None else GroundModel.level()
    p = np.asarray(pts, np.float64).reshape(-1, 3)
    nx = max(1, int(np.ceil((x_max_m - x_min_m) / cell_m)))
    ny = max(1, int(np.ceil(2 * y_half_m / cell_m)))
    off = np.zeros((nx, ny))
    if len(p) == 0:
        return LocalGround(base, x_min_m, -y_half_m, cell_m, off, 0)
    r = p[:, 2] - base.z(p[:, 0], p[:, 1])
    lo, hi = -max_down_m - 1.0, max_dev_m + 3.0
    ix = np.floor((p[:, 0] - x_min_m) / cell_m).astype(np.intp)
    iy = np.floor((p[:, 1] + y_half_m) / cell_m).astype(np.intp)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (r > lo) & (r < hi)
    ix, iy, r = ix[ok], iy[ok], r[ok]
    nz = int(np.ceil((hi - lo) / z_step))
    iz = np.minimum(((r - lo) / z_step).astype(np.intp), nz - 1)
    b = ix * ny + iy
    counts = np.bincount(b, minlength=nx * ny)
    use = np.flatnonzero(counts >= min_points)
    env = np.full(nx * ny, np.inf, np.float32)
    if len(use):
        hist = np.bincount(b * nz + iz, minlength=nx * ny * nz).reshape(nx * ny, nz)[use]
        cum = np.cumsum(hist, axis=1)
        need = np.maximum(1, np.ceil(counts[use] * percentile / 100.0))[:, None]
        k = np.argmax(cum >= need, axis=1)
        env[use] = lo + (k + 0.5) * z_step
    env = env.reshape(nx, ny)
    nseen = None
    if erode_cells > 0:
        import cv2
        kern = np.ones((2 * erode_cells + 1,) * 2, np.uint8)
        if min_seen > 1:
            nseen = cv2.filter2D(np.isfinite(env).astype(np.float32), -1,
                                 kern.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
        env = cv2.erode(env, kern, borderType=cv2.BORDER_CONSTANT, borderValue=float(np.inf))
    seen = np.isfinite(env)
    if nseen is not None:
        seen &= nseen >= min_seen - 0.5
    off[seen] = np.clip(env[seen], -max_down_m, max_dev_m)
    return LocalGround(base, x_min_m, -y_half_m, cell_m, off, int(len(use)))


def horizon_far_mask(pts: np.ndarray, camera_z_m: float, far_m: float,
                     ground=None) -> np.ndarray:
    """True for points (N, 3) farther ahead than ``far_m`` and higher above the ground than
    the camera: the sky and the far skyline (see the module's docstring)."""
    p = np.asarray(pts).reshape(-1, 3)
    h = ground.height(p) if ground is not None else p[:, 2]
    return (p[:, 0] > far_m) & (h > camera_z_m)
