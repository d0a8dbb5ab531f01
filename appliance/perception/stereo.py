"""Dense stereo and the height band: the stereo paper's "stereo alone" baseline (pipeline
``stereo``) and the stages ``stereo-novelty`` shares.

- :func:`make_matcher` — OpenCV block matching ("bm"), semi-global matching ("sgbm") or LIBELAS
  ("elas", through the optional GPLv3 ``pyelas`` binding, never a hard dependency).
- :func:`disparity_regions` — dense matching restricted to boxes (the novel regions) plus the
  margin the matcher needs: the box is widened by half the block, and the crop extends
  ``num_disparities`` to the left so every pixel in the box has its whole search range.
- :func:`points_from_disparity` — reprojection to 3-D (optical frame) and into the vehicle frame
  through the mount, the vehicle assumed level on the ground (paper III-D).
- :func:`height_band` — points whose height lies in the band are obstacles.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.config import _f

from .base import Detections, Pipeline, SensorInputs

MATCHERS = ("bm", "sgbm", "elas")


@dataclass(frozen=True)
class StereoConfig:
    matcher: str = _f("sgbm", choices=MATCHERS, doc="bm | sgbm | elas (elas needs pyelas, GPLv3)")
    num_disparities: int = _f(0, lo=0, hi=512,
                              doc="disparity search range in px (multiple of 16); 0 = from "
                                  "min_depth_m and the calibration")
    min_depth_m: float = _f(3.0, lo=0.5, hi=100.0,
                            doc="with num_disparities = 0: nearest z-depth the search covers")
    block_size: int = _f(0, lo=0, hi=51, doc="matcher block (odd); 0 = 15 for bm, 5 for sgbm")
    uniqueness: int = _f(10, lo=0, hi=100)
    texture_threshold: int = _f(10, lo=0, hi=1000, doc="bm only")
    speckle_window: int = _f(0, lo=0, hi=1000, doc="0 = no speckle filter")
    speckle_range: int = _f(2, lo=0, hi=64)
    band_min_m: float = _f(0.5, lo=-5.0, hi=10.0, doc="obstacle height band, lower bound (m)")
    band_max_m: float = _f(3.0, lo=-5.0, hi=20.0, doc="obstacle height band, upper bound (m)")
    max_range_m: float = _f(30.0, lo=0.5, hi=200.0, doc="points farther ahead are dropped")
    point_stride: int = _f(2, lo=1, hi=16, doc="use every n-th pixel in u and v")
    use_attitude: bool = _f(False, doc="project with the vehicle's roll/pitch (the paper "
                                       "assumes the vehicle level on the ground)")


def auto_disparities(o, fx: float, baseline_m: float) -> int:
    if o.num_disparities:
        return max(16, int(o.num_disparities) // 16 * 16)
    d = fx * baseline_m / o.min_depth_m
    return int(max(16, np.ceil(d / 16.0) * 16))


def block_of(o) -> int:
    b = o.block_size or (15 if o.matcher == "bm" else 5)
    return b | 1


class Matcher:
    """One dense matcher; :meth:`compute` returns float32 disparity in px (<= 0 = none) for a
    left/right pair of equal size (BGR or grey)."""

    def __init__(self, kind: str, num_disparities: int, block: int, o):
        self.kind, self.nd, self.block = kind, num_disparities, block
        if kind == "bm":
            m = cv2.StereoBM_create(numDisparities=num_disparities, blockSize=max(5, block))
            m.setUniquenessRatio(o.uniqueness)
            m.setTextureThreshold(o.texture_threshold)
            m.setSpeckleWindowSize(o.speckle_window)
            m.setSpeckleRange(o.speckle_range)
            self.m = m
        elif kind == "sgbm":
            ch = 3
            self.m = cv2.StereoSGBM_create(
                minDisparity=0, numDisparities=num_disparities, blockSize=block,
                P1=8 * ch * block * block, P2=32 * ch * block * block, disp12MaxDiff=1,
                uniquenessRatio=o.uniqueness, speckleWindowSize=o.speckle_window,
                speckleRange=o.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        elif kind == "elas":
            try:
                import elas  # noqa: F401  (pyelas, GPLv3: optional extra)
            except ImportError as exc:
                raise RuntimeError("matcher 'elas' needs the optional pyelas package "
                                   "(GPLv3): pip install pyelas") from exc
            self.m = None
        else:
            raise ValueError(f"unknown matcher {kind!r}")

    @property
    def margin(self) -> int:
        return self.block // 2 + 1

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        if self.kind == "bm":
            gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
            gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
            d = self.m.compute(gl, gr)
            return d.astype(np.float32) * np.float32(1 / 16.0)
        if self.kind == "sgbm":
            return self.m.compute(left, right).astype(np.float32) * np.float32(1 / 16.0)
        import elas
        gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
        gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
        p = elas.Elas_parameters()
        p.postprocess_only_left = True
        p.disp_max = self.nd
        e = elas.Elas(p)
        dl = np.zeros(gl.shape, np.float32)
        dr = np.zeros(gl.shape, np.float32)
        e.process_stereo(np.ascontiguousarray(gl), np.ascontiguousarray(gr), dl, dr)
        return dl


def make_matcher(o, fx: float, baseline_m: float) -> Matcher:
    return Matcher(o.matcher, auto_disparities(o, fx, baseline_m), block_of(o), o)


def merge_boxes(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Merge overlapping (x0, y0, x1, y1) boxes until none overlap."""
    boxes = [tuple(b) for b in boxes]
    changed = True
    while changed and len(boxes) > 1:
        changed = False
        out: list[tuple[int, int, int, int]] = []
        for b in boxes:
            for i, c in enumerate(out):
                if b[0] < c[2] and c[0] < b[2] and b[1] < c[3] and c[1] < b[3]:
                    out[i] = (min(b[0], c[0]), min(b[1], c[1]), max(b[2], c[2]), max(b[3], c[3]))
                    changed = True
                    break
            else:
                out.append(b)
        boxes = out
    return boxes


def mask_boxes(mask: np.ndarray, margin: int) -> list[tuple[int, int, int, int]]:
    """Bounding boxes (x0, y0, x1, y1) of the mask's connected regions, grown by ``margin`` and
    merged where they overlap."""
    n, _, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8), connectivity=8)
    H, W = mask.shape
    boxes = []
    for i in range(1, n):
        x, y, w, h = stats[i, :4]
        boxes.append((max(0, x - margin), max(0, y - margin), min(W, x + w + margin),
                      min(H, y + h + margin)))
    return merge_boxes(boxes)


def disparity_regions(matcher: Matcher, left: np.ndarray, right: np.ndarray,
                      boxes: list[tuple[int, int, int, int]]) -> tuple[np.ndarray, int]:
    """Disparity (H, W) float32 computed only inside ``boxes`` (0 elsewhere). Each crop reaches
    ``num_disparities`` further left (the search range) and the block's margin further out; the
    returned count is the number of pixels matched (crops included)."""
    H, W = left.shape[:2]
    disp = np.zeros((H, W), np.float32)
    m, nd = matcher.margin, matcher.nd
    work = 0
    for (x0, y0, x1, y1) in boxes:
        cx0, cx1 = max(0, x0 - nd - m), min(W, x1 + m)
        cy0, cy1 = max(0, y0 - m), min(H, y1 + m)
        if cx1 - cx0 < nd + 2 * m + 1:               # the matcher needs nd + block columns
            cx0 = max(0, cx1 - (nd + 2 * m + 1))
            if cx1 - cx0 < nd + 2 * m + 1:
                cx1 = min(W, cx0 + nd + 2 * m + 1)
        if cy1 - cy0 < 2 * m + 1:
            cy0, cy1 = max(0, cy0 - m), min(H, cy1 + m)
        d = matcher.compute(np.ascontiguousarray(left[cy0:cy1, cx0:cx1]),
                            np.ascontiguousarray(right[cy0:cy1, cx0:cx1]))
        work += d.size
        # a pixel whose search would leave the crop on the left is not trustworthy
        valid_from = np.arange(cx0, cx1)[None, :] - cx0 >= nd if cx0 > 0 else np.ones(
            (1, cx1 - cx0), bool)
        d = np.where(valid_from, d, 0.0)
        sx0, sy0 = x0 - cx0, y0 - cy0
        disp[y0:y1, x0:x1] = d[sy0:sy0 + (y1 - y0), sx0:sx0 + (x1 - x0)]
    return disp, work


def points_from_disparity(disp: np.ndarray, calib, select: np.ndarray | None = None,
                          stride: int = 1, vehicle=None, use_attitude: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Reproject disparities > 0 (optionally only where ``select`` is true, every ``stride``-th
    pixel) to the vehicle frame. Returns (points (N, 3) vehicle frame, pixels (N, 2) u, v)."""
    cam = calib.camera
    d = disp[::stride, ::stride]
    ok = d > 0
    if select is not None:
        ok &= select[::stride, ::stride] > 0
    vv, uu = np.nonzero(ok)
    dd = d[vv, uu].astype(np.float64)
    u = uu.astype(np.float64) * stride
    v = vv.astype(np.float64) * stride
    z = cam.fx * calib.baseline_m / dd
    x = (u - cam.cx) * z / cam.fx
    y = (v - cam.cy) * z / cam.fy
    opt = np.stack([x, y, z], axis=1)
    R = calib.mount.camera_to_vehicle()
    if use_attitude and vehicle is not None:
        from hal.types import rotation_rpy
        R = rotation_rpy(vehicle.roll_rad, vehicle.pitch_rad, 0.0) @ R
    pts = opt @ R.T + calib.mount.position
    return pts, np.stack([u, v], axis=1)


def height_band(points: np.ndarray, band_min_m: float, band_max_m: float,
                max_range_m: float = 1e9) -> np.ndarray:
    """Boolean mask of the points (N, 3) whose height is within [band_min, band_max] and that lie
    ahead within ``max_range_m``."""
    p = np.asarray(points).reshape(-1, 3)
    return (p[:, 2] >= band_min_m) & (p[:, 2] <= band_max_m) & (p[:, 0] > 0) & (
        p[:, 0] <= max_range_m)


def dedupe_cells(xy: np.ndarray, cell_m: float = 0.1) -> np.ndarray:
    """One point per 0.1 m cell (the grid's resolution): fewer points, same occupied cells."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32)
    k = np.floor(xy / cell_m).astype(np.int64)
    _, idx = np.unique(k, axis=0, return_index=True)
    return xy[np.sort(idx)].astype(np.float32)


class StereoPipeline(Pipeline):
    """Full-frame dense stereo and the height band: the paper's "stereo alone"."""

    name = "stereo"
    requires = ("stereo",)
    config_class = StereoConfig

    def __init__(self, options=None):
        super().__init__(options)
        self._matcher = None
        self._key = None

    def matcher_for(self, calib) -> Matcher:
        key = (calib.camera.fx, calib.baseline_m)
        if self._matcher is None or self._key != key:
            self._matcher = make_matcher(self.options, calib.camera.fx, calib.baseline_m)
            self._key = key
        return self._matcher

    def process(self, inputs: SensorInputs) -> Detections:
        fr = inputs.stereo
        o = self.options
        t0 = time.perf_counter()
        m = self.matcher_for(fr.calib)
        H, W = fr.left.shape[:2]
        disp, _ = disparity_regions(m, fr.left, fr.right, [(0, 0, W, H)])
        t1 = time.perf_counter()
        pts, _ = points_from_disparity(disp, fr.calib, None, o.point_stride, inputs.vehicle,
                                       o.use_attitude)
        keep = height_band(pts, o.band_min_m, o.band_max_m, o.max_range_m)
        xy = dedupe_cells(pts[keep, :2])
        t2 = time.perf_counter()
        return Detections(points_xy=xy, debug={
            "matcher": o.matcher, "num_disparities": m.nd, "points": int(keep.sum()),
            "ms": {"stereo": 1e3 * (t1 - t0), "points": 1e3 * (t2 - t1)}})
