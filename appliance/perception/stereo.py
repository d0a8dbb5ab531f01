"""Dense stereo and the height band: the stereo paper's "stereo alone" baseline (pipeline
``stereo``) and the stages ``stereo-novelty`` shares.

- :func:`make_matcher` — OpenCV block matching ("bm"), semi-global matching ("sgbm") or LIBELAS
  ("elas", through the optional GPLv3 ``pyelas`` binding, never a hard dependency).
- :func:`disparity_regions` — dense matching restricted to boxes (the novel regions) plus the
  margin the matcher needs: the box is widened by half the block, and the crop extends the
  search range to the left so every pixel in the box has its whole range. A box may carry its
  own range ``[d_min, d_min + n)``: the right crop is then shifted by ``d_min`` (the matcher
  searches ``n`` disparities and the crop grows by ``n``, not by ``d_min + n``).
- :func:`ground_search_range` — the range a box needs: nothing nearer than ``min_depth_m``,
  and, where every ray of the box hits the ground, nothing farther than the ground (level
  vehicle, with slack for pitch and uneven ground) — a point beyond the ground is under it.
- :func:`match_factor`, :func:`scaled_calibration` — matching at 1/2, 1/4 ... resolution.
- :func:`points_from_disparity` — reprojection to 3-D (optical frame) and into the vehicle frame
  through the mount, the vehicle assumed level on the ground (paper III-D).
- :func:`height_band` — points whose height lies in the band are obstacles.
"""
from __future__ import annotations

import time
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from appliance.schema import _f

from .base import Detections, Pipeline, SensorInputs
from .candidates import cluster_candidates

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
    sgbm_colour: bool = _f(True, doc="sgbm: match the three colour channels (true) or grey "
                                      "(false: ~30 % less matching time, the same error on the "
                                      "Middlebury pairs; see docs/stereo-novelty.md)")
    band_min_m: float = _f(0.5, lo=-5.0, hi=10.0, doc="obstacle height band, lower bound (m)")
    band_max_m: float = _f(3.0, lo=-5.0, hi=20.0, doc="obstacle height band, upper bound (m)")
    max_range_m: float = _f(30.0, lo=0.5, hi=200.0, doc="points farther ahead are dropped")
    point_stride: int = _f(2, lo=1, hi=16, doc="use every n-th pixel in u and v")
    use_attitude: bool = _f(False, doc="project with the vehicle's roll/pitch (the paper "
                                       "assumes the vehicle level on the ground)")
    match_width_px: int = _f(0, lo=0, hi=16384,
                             doc="dense matching on images at most this wide: wider frames are "
                                 "matched at 1/2, 1/4 ... resolution; 0 = native resolution")
    # ---- issue #14's front end (beyond the paper; each stage can be switched off) ----------
    ground_fit: bool = _f(False, doc="height above the ground fitted every frame to the "
                                     "points' low envelope (perception/ground.py) instead of "
                                     "above the level plane z = 0 (paper)")
    ground_max_range_m: float = _f(25.0, lo=3.0, hi=200.0,
                                   doc="ground_fit: points up to this far ahead carry the fit")
    ground_local: bool = _f(False, doc="height above the LOCAL ground: per ground_local_cell_m "
                                        "bin, the low envelope (ground_local_percentile) of "
                                        "the points' heights above the ground (level, or the "
                                        "fit with ground_fit), eroded over the neighbouring "
                                        "bins so an object cannot lift the ground under it "
                                        "(perception/ground.py local_ground). A stubble tuft "
                                        "on a rise is measured from the rise")
    ground_local_cell_m: float = _f(0.5, lo=0.1, hi=5.0, doc="ground_local: bin size (m)")
    ground_local_percentile: float = _f(10.0, lo=0.0, hi=50.0,
                                        doc="ground_local: the bin's low percentile")
    ground_local_erode: int = _f(1, lo=0, hi=5, doc="ground_local: the minimum over the bin "
                                                    "and its neighbours this many bins away")
    ground_local_max_dev_m: float = _f(0.5, lo=0.0, hi=3.0,
                                       doc="ground_local: at most this far above the level "
                                           "plane or the fit")
    ground_local_min_bins: int = _f(4, lo=1, hi=121,
                                    doc="ground_local: a bin's neighbourhood must hold this "
                                        "many bins that saw the ground, else the base ground "
                                        "there (far away only an object's own bins are seen)")
    ground_local_max_down_m: float = _f(0.0, lo=0.0, hi=3.0,
                                        doc="ground_local: at most this far below it (a "
                                            "lower ground makes everything on it taller: "
                                            "mismatches matched too near lie below the "
                                            "ground and pull the low envelope down)")
    sky_far_m: float = _f(0.0, lo=0.0, hi=200.0,
                          doc="points farther than this and higher above the ground than the "
                              "camera are the sky or the skyline, not obstacles (0 = off)")
    dark_level: float = _f(0.0, lo=0.0, hi=255.0,
                           doc="no disparity where the left image's 7x7 mean grey level is "
                               "below this (a black night sky or field beyond the strobe: the "
                               "matcher's disparities there are noise); 0 = off")
    pad_left: bool = _f(False, doc="match the image's leftmost columns too (a zero-padded "
                                   "crop; disparities limited to what the right image holds). "
                                   "Off (paper, OpenCV's default): the leftmost "
                                   "num_disparities columns have no disparity: at 640x512 and "
                                   "min_depth_m 3 the left 13 deg of the view are blind")
    support_min: float = _f(0.0, lo=0.0, hi=1.0,
                            doc="vertical support: an obstacle point needs this share of the "
                                "pixels below it down to its foot (where the ground under it "
                                "is seen) to have its disparity, as a surface standing on the "
                                "ground does (a mismatch blob in the far stubble does not; an "
                                "overhang does not either). 0 = off")
    support_known_min: float = _f(0.0, lo=0.0, hi=1.0,
                                  doc="vertical support (support_min > 0): the share of the "
                                      "samples below an obstacle point that must have a "
                                      "disparity at all; fewer: no support (0 = off: unknown "
                                      "samples say nothing, a mismatch floating above an "
                                      "unmatched column passes)")
    confidence_px: float = _f(1.0, lo=0.05, hi=16.0,
                              doc="per-point confidence: exp(-(|d - median 3x3 of d| / this)^2) "
                                  "(a disparity that disagrees with its neighbours is unsure)")


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
        self.grey = False                             # sgbm on grey images (sgbm_colour off)
        self._o = o
        self._by_range: dict[int, "Matcher"] = {}
        if kind == "bm":
            m = cv2.StereoBM_create(numDisparities=num_disparities, blockSize=max(5, block))
            m.setUniquenessRatio(o.uniqueness)
            m.setTextureThreshold(o.texture_threshold)
            m.setSpeckleWindowSize(o.speckle_window)
            m.setSpeckleRange(o.speckle_range)
            self.m = m
        elif kind == "sgbm":
            self.grey = not getattr(o, "sgbm_colour", True)
            ch = 1 if self.grey else 3
            self.m = cv2.StereoSGBM_create(
                minDisparity=0, numDisparities=num_disparities, blockSize=block,
                P1=8 * ch * block * block, P2=32 * ch * block * block, disp12MaxDiff=1,
                uniquenessRatio=o.uniqueness, speckleWindowSize=o.speckle_window,
                speckleRange=o.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        elif kind == "elas":
            try:
                import elas  # (pyelas, GPLv3: optional, never a dependency)
            except ImportError as exc:
                raise RuntimeError(
                    "matcher 'elas' needs the optional pyelas package (GPLv3), which does not "
                    "build from the package index as published: CFLAGS=-I$(python -c 'import "
                    "numpy; print(numpy.get_include())') pip install --no-build-isolation wheel "
                    "cython pyelas") from exc
            self.m = elas.Elas()
            self.m.set_preset(elas.PRESET_ROBOTICS)      # LIBELAS's robotics setting
            self.m.disp_min = 0
            self.m.disp_max = num_disparities - 1
            self.m.postprocess_only_left = True
        else:
            raise ValueError(f"unknown matcher {kind!r}")

    @property
    def grey_input(self) -> bool:
        """True when the matcher works on grey images (a caller with many crops of one frame
        converts the frame once instead of every crop)."""
        return self.kind in ("bm", "elas") or self.grey

    @property
    def min_crop(self) -> tuple[int, int]:
        """(rows, columns beyond the search range) a crop needs at least. LIBELAS crashes the
        process (a segmentation fault in its triangulation) on crops of 16-32 rows with few
        support points: its crops are at least 64 x (n + 64)."""
        return (64, 64) if self.kind == "elas" else (0, 0)

    @property
    def margin(self) -> int:
        return self.block // 2 + 1

    def with_range(self, n: int) -> "Matcher":
        """The same matcher searching ``n`` disparities (a multiple of 16); cached."""
        if n == self.nd:
            return self
        m = self._by_range.get(n)
        if m is None:
            m = self._by_range[n] = Matcher(self.kind, n, self.block, self._o)
        return m

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        if self.kind == "bm":
            gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
            gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
            d = self.m.compute(gl, gr)
            return d.astype(np.float32) * np.float32(1 / 16.0)
        if self.kind == "sgbm":
            if self.grey:
                left = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
                right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
            return self.m.compute(left, right).astype(np.float32) * np.float32(1 / 16.0)
        gl = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
        gr = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
        # LIBELAS prints warnings with printf: `fieldguard eval --json` keeps them off its
        # stdout (appliance.cli); LIBELAS marks "none" with -10
        dl, _ = self.m.process(np.ascontiguousarray(gl), np.ascontiguousarray(gr))
        return np.asarray(dl, np.float32)


def check_matcher(kind: str, key: str) -> None:
    """Raise a ConfigError naming ``key`` when matcher ``kind`` cannot run here (LIBELAS
    without its optional binding): at start-up, not on the first frame."""
    if kind != "elas":
        return
    try:
        import elas  # noqa: F401
    except ImportError:
        from hal.errors import ConfigError
        raise ConfigError('matcher = "elas" needs the optional pyelas binding (GPLv3), not '
                          'installed: ./tools/install_elas.sh, or matcher = "sgbm"',
                          key=key) from None


def check_daemon_matchers(cfg) -> None:
    """The daemon refuses LIBELAS: it can crash the whole process (a segmentation fault in its
    triangulation on crops with too few support points; seen on 16-32-row crops, and crops are
    now at least 64 rows, but that is not a proof). It is for offline comparison with
    ``fieldguard eval``; a safety box must not run code that can take the loop down."""
    from appliance.perception import pipeline_options
    from hal.errors import ConfigError
    for name in cfg.perception.pipelines:
        if name != "fused" and getattr(pipeline_options(cfg, name), "matcher", None) == "elas":
            raise ConfigError('matcher = "elas" (LIBELAS) is for offline comparison '
                              '(fieldguard eval RUN --pipeline ... --config ...): it can crash '
                              'the process on small crops, so the daemon does not run it; use '
                              '"sgbm"', key=f"perception.{name}", file=cfg.source)


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


def _columns(img: np.ndarray, a: int, b: int) -> np.ndarray:
    """Columns [a, b) of ``img``; columns outside the image are zeros."""
    W = img.shape[1]
    if a >= 0 and b <= W:
        return img[:, a:b]
    out = np.zeros((img.shape[0], b - a) + img.shape[2:], img.dtype)
    s0, s1 = max(a, 0), min(b, W)
    if s1 > s0:
        out[:, s0 - a:s1 - a] = img[:, s0:s1]
    return out


def disparity_regions(matcher: Matcher, left: np.ndarray, right: np.ndarray,
                      boxes: list[tuple[int, int, int, int]],
                      ranges: list[tuple[int, int]] | None = None,
                      parts: list | None = None, pad_left: bool = False
                      ) -> tuple[np.ndarray, int]:
    """Disparity (H, W) float32 computed only inside ``boxes`` (0 elsewhere). Each crop reaches
    the search range further left and the block's margin further out; the returned count is
    the number of pixels matched (crops included).

    ``ranges`` (one ``(d_min, n)`` per box, ``n`` a multiple of 16; ``n = 0`` skips the box):
    the box searches disparities ``[d_min, d_min + n)`` only, by matching the left crop against
    the right crop shifted ``d_min`` to the left. A match on the range's lower end (within
    1 px of ``d_min``) is dropped: the true disparity is probably outside the range. Without
    ``ranges`` every box searches ``[0, num_disparities)`` (the full-frame behaviour).

    ``parts`` (with ``ranges``, from :func:`merge_strips`): per box a list of its members
    ``(x0, x1, d_min, n, y0, y1)``; only the members' rectangles are written, each with only
    the disparities in ``[d_min, d_min + n)`` (above the lower end as above), as if it had
    been matched alone (a merged box spans the union of its members' rows and columns).

    ``pad_left``: see the code (the left columns of the image are matched, not left blind:
    without it the leftmost ``num_disparities`` columns, 22 % of a 640-px frame with 144
    disparities, have no disparity at all)."""
    H, W = left.shape[:2]
    disp = np.zeros((H, W), np.float32)
    m = matcher.margin
    work = 0
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        dmin, nd = (0, matcher.nd) if ranges is None else ranges[i]
        if nd <= 0 or x1 <= x0 or y1 <= y0:
            continue
        mt = matcher.with_range(nd)
        # pad_left: a box whose search range reaches past the image's left edge is matched on
        # a crop padded with zeros there, so its left columns are searched over the
        # disparities the right image can hold (d <= u) instead of not at all
        pad = pad_left and x0 - nd - m < 0
        cx0, cx1 = (x0 - nd - m if pad else max(0, x0 - nd - m)), min(W, x1 + m)
        cy0, cy1 = max(0, y0 - m), min(H, y1 + m)
        if not pad and cx1 - cx0 < nd + 2 * m + 1:   # the matcher needs nd + block columns
            cx0 = max(0, cx1 - (nd + 2 * m + 1))
            if cx1 - cx0 < nd + 2 * m + 1:
                cx1 = min(W, cx0 + nd + 2 * m + 1)
        if cy1 - cy0 < 2 * m + 1:
            cy0, cy1 = max(0, cy0 - m), min(H, cy1 + m)
        rows, cols_extra = matcher.min_crop
        if cy1 - cy0 < rows:                          # grow about the box, inside the image
            grow = rows - (cy1 - cy0)
            cy0 = max(0, cy0 - grow // 2)
            cy1 = min(H, cy0 + rows)
            cy0 = max(0, cy1 - rows)
        if not pad and cx1 - cx0 < nd + cols_extra:
            cx1 = min(W, cx0 + nd + cols_extra)
            cx0 = max(0, cx1 - (nd + cols_extra))
        elif pad and cx1 - cx0 < nd + cols_extra:
            cx1 = cx0 + nd + cols_extra             # (zeros beyond the right edge too)
        lc = np.ascontiguousarray(_columns(left[cy0:cy1], cx0, cx1) if pad
                                  else left[cy0:cy1, cx0:cx1])
        rc = np.ascontiguousarray(_columns(right[cy0:cy1], cx0 - dmin, cx1 - dmin))
        d = mt.compute(lc, rc)
        work += d.size
        cols = np.arange(cx0, cx1)[None, :]
        # a pixel whose search would leave the crop (or the right image) on the left is not
        # trustworthy
        if pad:
            valid = (cols - cx0 >= nd) & (cols >= 0)
            d = np.where(valid & (d >= (1.0 if dmin > 0 else 0.0)), d + np.float32(dmin),
                         np.float32(0.0))
            d[d > cols.astype(np.float32)] = 0.0          # its match would be off the image
        else:
            valid = (cols - cx0 >= nd) if cx0 > 0 else np.ones((1, cx1 - cx0), bool)
            if dmin > 0:
                valid = valid & (cols >= dmin + nd)
                d = np.where(valid & (d >= 1.0), d + np.float32(dmin), np.float32(0.0))
            else:
                d = np.where(valid, d, np.float32(0.0))
        if cx1 > W:
            d = d[:, :W - cx0]
            cx1 = W
        if parts is not None and len(parts[i]) > 1:
            # each member's own rectangle, with only its own range's disparities
            for (px0, px1, pd, pn, py0, py1) in parts[i]:
                seg = d[py0 - cy0:py1 - cy0, px0 - cx0:px1 - cx0]
                lo = pd + 1.0 if pd > 0 else 0.0
                disp[py0:py1, px0:px1] = np.where((seg < lo) | (seg >= pd + pn),
                                                  np.float32(0.0), seg)
        else:
            sx0, sy0 = x0 - cx0, y0 - cy0
            disp[y0:y1, x0:x1] = d[sy0:sy0 + (y1 - y0), sx0:sx0 + (x1 - x0)]
    return disp, work


def match_factor(width: int, match_width_px: int) -> int:
    """The power-of-two divisor that brings ``width`` to at most ``match_width_px`` (1 when
    ``match_width_px`` is 0)."""
    k = 1
    if match_width_px > 0:
        while width / k > match_width_px and width // (2 * k) >= 16:
            k *= 2
    return k


def downscale(img: np.ndarray, k: int) -> np.ndarray:
    """Area-average ``img`` by the integer factor ``k`` (whole k x k blocks only)."""
    if k == 1:
        return img
    H, W = img.shape[:2]
    h, w = H // k, W // k
    return cv2.resize(img[:h * k, :w * k], (w, h), interpolation=cv2.INTER_AREA)


def scaled_calibration(calib, k: int):
    """The stereo calibration of the pair downscaled by ``k`` (pixel centres kept)."""
    if k == 1:
        return calib
    cam, s = calib.camera, 1.0 / k
    c2 = replace(cam, width=cam.width // k, height=cam.height // k, fx=cam.fx * s,
                 fy=cam.fy * s, cx=(cam.cx + 0.5) * s - 0.5, cy=(cam.cy + 0.5) * s - 0.5)
    return replace(calib, camera=c2)


@lru_cache(maxsize=64)
def _height_rows(mount, roll: float, pitch: float) -> tuple[tuple[float, float, float], float]:
    """The z row of the optical->vehicle rotation with the vehicle at (roll, pitch), and the
    optical centre's height (cached: a few attitudes per frame)."""
    from hal.types import rotation_rpy
    R = rotation_rpy(roll, pitch, 0.0) @ mount.camera_to_vehicle()
    return (float(R[2, 0]), float(R[2, 1]), float(R[2, 2])), float(mount.z_m)


def _ground_depth(calib, us, vs, roll: float, pitch: float, ground_m: float) -> list[float]:
    """z-depth at which the rays through pixels (us, vs) meet the plane ``z = ground_m`` of the
    vehicle frame, the vehicle at (roll, pitch); inf where a ray does not go down."""
    cam = calib.camera
    (r0, r1, r2), h = _height_rows(calib.mount, float(roll), float(pitch))
    out = []
    for u, v in zip(us, vs):
        a = r0 * (u - cam.cx) / cam.fx + r1 * (v - cam.cy) / cam.fy + r2   # height per metre
        out.append((h - ground_m) / -a if a < -1e-6 else math.inf)
    return out


def ground_search_range(calib, box: tuple[int, int, int, int], nd: int, vehicle=None,
                        ground_slack_m: float = 0.3, pitch_slack_deg: float = 3.0,
                        margin_px: int = 2, foot_row: int | None = None,
                        seen_max_disp: float = 0.0, nd_near: int | None = None
                        ) -> tuple[int, int]:
    """``(d_min, n)`` for a box (pixels of ``calib``'s image).

    Far end: disparities below ``d_min`` lie beyond the ground plane for every ray of the box,
    with the vehicle level (or at its reported roll/pitch) pitched ``pitch_slack_deg`` further
    nose-up and the ground ``ground_slack_m`` lower — such points would be under the ground.
    When a ray of the box can miss the ground (at or above the horizon) ``d_min`` is 0.

    Near end (only with ``foot_row``, the last row of the region the box belongs to): an
    obstacle standing on the ground with its foot inside the region is no nearer than the
    ground at ``foot_row`` (vehicle pitched ``pitch_slack_deg`` nose-down, ground
    ``ground_slack_m`` higher); without it, or when that row does not see the ground, the
    near end is ``nd`` (``min_depth_m``). ``seen_max_disp``: the largest disparity seen in the
    box by another measurement (a coarse stereo pass); the near end is never below it, so an
    obstacle whose foot is outside the region (an overhang, an unlit lower part) that the
    coarse pass saw is still searched.

    ``nd_near`` (> ``nd``; with ``foot_row``): when the box's own last row sees ground nearer
    than ``nd`` reaches (with the near end's slack), the near end found from the foot may go
    up to this many disparities instead of ``nd``.

    ``n`` is a multiple of 16 and ``[d_min, d_min + n)`` covers the range found; ``n = 0`` when
    the range is empty."""
    cam = calib.camera
    roll = pitch = 0.0
    if vehicle is not None:
        roll, pitch = float(vehicle.roll_rad), float(vehicle.pitch_rad)
    slack = math.radians(pitch_slack_deg)
    x0, y0, x1, y1 = box
    fb = cam.fx * calib.baseline_m
    z_far = max(_ground_depth(calib, [x0, x1 - 1, x0, x1 - 1], [y0, y0, y1 - 1, y1 - 1],
                              roll, pitch - slack, -ground_slack_m))
    dmin = 0 if not math.isfinite(z_far) else max(0, int(math.floor(fb / z_far)) - margin_px)
    dmax = nd
    if foot_row is not None:
        cap = nd
        if nd_near is not None and nd_near > nd:
            z_own = min(_ground_depth(calib, [x0, x1 - 1], [y1 - 1, y1 - 1], roll,
                                      pitch + slack, ground_slack_m))
            if math.isfinite(z_own) and z_own > 0 and fb / z_own > nd:
                cap = nd_near
        z_near = min(_ground_depth(calib, [x0, x1 - 1], [foot_row, foot_row], roll,
                                   pitch + slack, ground_slack_m))
        if math.isfinite(z_near) and z_near > 0:
            dmax = min(cap, max(int(math.ceil(fb / z_near)), int(math.ceil(seen_max_disp)))
                       + margin_px)
    if dmin >= dmax:
        return dmin, 0
    n = int(math.ceil((dmax - dmin) / 16.0)) * 16
    return max(0, dmax - n), n


def strip_boxes(calib, boxes, nd: int, vehicle=None, strip_rows: int = 64,
                ground_slack_m: float = 0.3, pitch_slack_deg: float = 3.0,
                near_from_foot: bool = False, foot_row: int | None = None,
                seen_max_disp: float = 0.0, nd_near: int | None = None):
    """Split boxes into horizontal strips of ``strip_rows`` with the search range of each
    (:func:`ground_search_range`; lower strips see nearer ground, so a narrower range; with
    ``near_from_foot`` the box's last row, or ``foot_row``, is the foot row of every strip).
    ``nd_near`` (> ``nd``, with ``near_from_foot``): a strip whose own last row sees ground
    nearer than ``nd`` reaches may search up to ``nd_near`` (:func:`ground_search_range`).
    Strips with an
    empty range are dropped and neighbouring strips of one box with the same range are
    joined. Returns (boxes, ranges)."""
    out_b, out_r = [], []
    for (x0, y0, x1, y1) in boxes:
        prev = None
        step = strip_rows if strip_rows > 0 else max(1, y1 - y0)
        for ys in range(y0, y1, step):
            ye = min(y1, ys + step)
            r = ground_search_range(calib, (x0, ys, x1, ye), nd, vehicle, ground_slack_m,
                                    pitch_slack_deg,
                                    foot_row=(y1 - 1 if foot_row is None else foot_row)
                                    if near_from_foot else None, seen_max_disp=seen_max_disp,
                                    nd_near=nd_near)
            if r[1] == 0:
                prev = None
                continue
            if prev is not None and out_r[prev] == r:
                b = out_b[prev]
                out_b[prev] = (b[0], b[1], b[2], ye)
                continue
            out_b.append((x0, ys, x1, ye))
            out_r.append(r)
            prev = len(out_b) - 1
    return out_b, out_r


def crop_cost(w: int, n: int, rows: int) -> float:
    """SGBM's CPU time (ms, OpenCV 4 3-way, one core) for a box ``w`` columns wide and ``rows``
    high searching ``n`` disparities: the fit of docs/stereo-novelty.md "Speed" (12 crop sizes,
    134 rows: 1.8e-4 w n + 6.4e-3 w + 5.3e-3 (w + n); the last term is the crop's n extension
    columns every crop pays for) scaled by its rows, plus ~0.05 ms of Python per crop."""
    return rows / 134.0 * (1.8e-4 * w * n + 6.4e-3 * w + 5.3e-3 * (w + n)) + 0.05


def merge_strips(boxes, ranges, margin: int, max_width: int = 0):
    """Join side-by-side boxes (one touching the other's right edge, their rows overlapping:
    neighbouring bands of one region) into one box over the union of their rows and columns
    searching the union of their ranges, when :func:`crop_cost` says that is cheaper; no
    merged box wider than ``max_width`` (0 = no limit). Each box joins the neighbour on its
    left that saves the most; boxes are taken left to right, so a merged box grows to the
    right.

    Returns (boxes, ranges, parts): ``parts[i]`` lists the members of box ``i`` as
    ``(x0, x1, d_min, n, y0, y1)``; pass them to :func:`disparity_regions`, which then keeps in
    each member's rectangle only the disparities its own range allows (the union searches
    more, and a wider range lets more mismatches through: measured 2x the false-positive
    cells on the empty field without this)."""
    m2 = 2 * margin
    cost = lambda b, n: crop_cost(b[2] - b[0] + m2, n, b[3] - b[1] + m2)    # noqa: E731
    out: list = []                                   # [box, range, members, cost]
    for b, r in sorted(zip(boxes, ranges), key=lambda t: (t[0][0], t[0][1])):
        b, r = tuple(int(v) for v in b), tuple(int(v) for v in r)
        part = (b[0], b[2], r[0], r[1], b[1], b[3])
        best = None
        if r[1] > 0:
            own = cost(b, r[1])
            for i, (ob, orr, _, oc) in enumerate(out):
                if ob[2] != b[0] or orr[1] <= 0 or ob[1] >= b[3] or b[1] >= ob[3]:
                    continue
                if max_width > 0 and b[2] - ob[0] > max_width:
                    continue
                lo, hi = min(orr[0], r[0]), max(orr[0] + orr[1], r[0] + r[1])
                n = int(math.ceil((hi - lo) / 16.0)) * 16
                nb = (ob[0], min(ob[1], b[1]), b[2], max(ob[3], b[3]))
                c = cost(nb, n)
                if c <= oc + own and (best is None or oc + own - c > best[0]):
                    best = (oc + own - c, i, nb, (max(0, hi - n), n), c)
        if best is not None:
            _, i, nb, nr, c = best
            out[i] = [nb, nr, out[i][2] + [part], c]
            continue
        out.append([b, r, [part], cost(b, r[1]) if r[1] > 0 else 0.0])
    return [o[0] for o in out], [o[1] for o in out], [o[2] for o in out]


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
    flat = np.flatnonzero(ok)                       # cheaper than np.nonzero's two arrays
    vv, uu = np.divmod(flat, d.shape[1])
    dd = d.ravel()[flat].astype(np.float64)
    u = uu.astype(np.float64) * stride
    v = vv.astype(np.float64) * stride
    z = cam.fx * calib.baseline_m / dd
    x = (u - cam.cx) * z / cam.fx
    y = (v - cam.cy) * z / cam.fy
    R = calib.mount.camera_to_vehicle()
    if use_attitude and vehicle is not None:
        from hal.types import rotation_rpy
        R = rotation_rpy(vehicle.roll_rad, vehicle.pitch_rad, 0.0) @ R
    # R @ [x y z] + position, one output column at a time (no (N, 3) optical array and no
    # matrix product of an (N, 3) array: a third less time on a busy frame)
    pos = calib.mount.position
    pts = np.empty((len(z), 3))
    for i in range(3):
        c = pts[:, i]
        np.multiply(x, R[i, 0], out=c)
        c += y * R[i, 1]
        c += z * R[i, 2]
        c += pos[i]
    return pts, np.stack([u, v], axis=1)


def height_band(points: np.ndarray, band_min_m: float, band_max_m: float,
                max_range_m: float = 1e9) -> np.ndarray:
    """Boolean mask of the points (N, 3) whose height is within [band_min, band_max] and that lie
    ahead within ``max_range_m``."""
    p = np.asarray(points).reshape(-1, 3)
    return (p[:, 2] >= band_min_m) & (p[:, 2] <= band_max_m) & (p[:, 0] > 0) & (
        p[:, 0] <= max_range_m)


def drop_dark(disp: np.ndarray, left: np.ndarray, level: float, win: int = 7) -> np.ndarray:
    """``disp`` with 0 wherever the ``win`` x ``win`` mean grey level of ``left`` (the image
    the disparity is of, BGR or grey) is below ``level`` (in place; returned)."""
    if level <= 0:
        return disp
    g = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
    mu = cv2.blur(g, (win, win))
    disp[mu < level] = 0.0
    return disp


def _row_counts(b: np.ndarray) -> np.ndarray:
    """``b.sum(axis=1)`` (int64) of a 2-D bool array. With 8 columns each row is one 64-bit
    word of 0/1 bytes and its count is the word's population count (numpy >= 2): ~15x faster
    than the sum over the short axis (vertical support's 8 samples of every obstacle point)."""
    if b.ndim == 2 and b.shape[1] == 8 and hasattr(np, "bitwise_count"):
        w = np.ascontiguousarray(b).view(np.uint64).reshape(-1)
        return np.bitwise_count(w).astype(np.int64)
    return b.sum(axis=1)


def match_correlation(left: np.ndarray, right: np.ndarray, px: np.ndarray, d: np.ndarray,
                      scale: float = 1.0, half_rows: int = 3, half_cols: int = 5,
                      min_std: float = 2.0) -> np.ndarray:
    """Per point (pixels ``px`` (N, 2) of the grey pair, disparities ``d`` (N,)): the
    zero-mean normalised correlation of the left window about it and the right window about
    its match (``u - d``, rounded), ``(2 half_rows + 1) x (2 half_cols + 1)`` pixels at 640
    wide (times ``scale``). NaN where a window leaves the image or either is flatter than
    ``min_std`` grey levels (the correlation says nothing there).

    A dense matcher's smoothness carries a disparity into pixels whose own windows do not
    match there: the simulated stubble's phantoms 0.5-0.6 m up at the stop zone's near edge
    are such points, but so are a real obstacle's points at the search's near edge when its
    face is nearer than the search reaches (docs/front-end.md "The match's own
    correlation")."""
    n = len(px)
    out = np.full(n, np.nan)
    if n == 0:
        return out
    hr = max(1, int(round(half_rows * scale)))
    hc = max(1, int(round(half_cols * scale)))
    H, W = left.shape[:2]
    u = np.asarray(px[:, 0], np.intp)
    v = np.asarray(px[:, 1], np.intp)
    d = np.asarray(d, np.float64)
    finite = np.isfinite(d)
    ur = np.rint(u - np.where(finite, d, 0.0)).astype(np.intp)
    ok = (v - hr >= 0) & (v + hr < H) & (u - hc >= 0) & (u + hc < W) & (ur - hc >= 0) & (
        ur + hc < W) & finite
    if not ok.any():
        return out
    dy = np.arange(-hr, hr + 1)[None, :, None]
    dx = np.arange(-hc, hc + 1)[None, None, :]
    rows = v[ok][:, None, None] + dy
    a = left[rows, u[ok][:, None, None] + dx].astype(np.float32)
    b = right[rows, ur[ok][:, None, None] + dx].astype(np.float32)
    a = a.reshape(len(a), -1)
    b = b.reshape(len(b), -1)
    a -= a.mean(1, keepdims=True)
    b -= b.mean(1, keepdims=True)
    sa = np.sqrt((a * a).mean(1))
    sb = np.sqrt((b * b).mean(1))
    flat = (sa < min_std) | (sb < min_std)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (a * b).mean(1) / (sa * sb)
    out[np.flatnonzero(ok)] = np.where(flat, np.nan, r)
    return out


def vertical_support(disp: np.ndarray, px: np.ndarray, pts: np.ndarray, calib, ground,
                     samples: int = 8, tol_px: float = 1.5, tol_frac: float = 0.08,
                     vehicle=None, use_attitude: bool = False,
                     known_min: float = 0.0) -> np.ndarray:
    """Per obstacle point (pixels ``px`` (N, 2) of ``disp``, vehicle-frame ``pts`` (N, 3)):
    the share of ``samples`` pixels of its column between it and its foot (the image row of
    the ground under it, ``ground`` a GroundModel) whose disparity is within
    ``max(tol_px, tol_frac d)`` of its own. Pixels with no disparity do not count; fewer than
    two known samples: 1 (nothing says otherwise). ``known_min`` > 0: a point whose column
    below has fewer than this share of the samples with a disparity at all has support 0
    (a floating mismatch above an unmatched column: nothing says it stands on the ground)."""
    n = len(px)
    if n == 0:
        return np.zeros(0)
    cam = calib.camera
    R = calib.mount.camera_to_vehicle()
    if use_attitude and vehicle is not None:
        from hal.types import rotation_rpy
        R = rotation_rpy(vehicle.roll_rad, vehicle.pitch_rad, 0.0) @ R
    foot = np.array(pts, np.float64).reshape(-1, 3)
    foot[:, 2] = ground.z(foot[:, 0], foot[:, 1])
    q = (foot - calib.mount.position) @ R                  # optical frame (R^T p)
    with np.errstate(divide="ignore", invalid="ignore"):
        vf = cam.fy * q[:, 1] / q[:, 2] + cam.cy
    H, W = disp.shape
    u = px[:, 0].astype(np.intp)
    v = px[:, 1].astype(np.float64)
    vf = np.where(np.isfinite(vf) & (q[:, 2] > 0), vf, v)
    vf = np.clip(vf, v, H - 1)
    t = (np.arange(1, samples + 1) / samples)[None, :]
    rows = np.clip((v[:, None] + (vf - v)[:, None] * t).astype(np.intp), 0, H - 1)
    d0 = disp[v.astype(np.intp), u][:, None]
    ds = disp[rows, u[:, None]]
    known = ds > 0
    agree = known & (np.abs(ds - d0) <= np.maximum(tol_px, tol_frac * d0))
    nk = _row_counts(known)
    sup = np.where(nk >= 2, _row_counts(agree) / np.maximum(nk, 1), 1.0)
    if known_min > 0:
        sup = np.where(nk >= known_min * samples, sup, 0.0)
    return sup


def point_confidence(disp: np.ndarray, px: np.ndarray, scale_px: float) -> np.ndarray:
    """Per point (pixels ``px`` (N, 2) u, v of ``disp``): exp(-(|d - med3(d)| / scale)^2),
    med3 the 3x3 median of the disparity (0 = none counts as a neighbour that disagrees)."""
    if len(px) == 0:
        return np.zeros(0)
    med = cv2.medianBlur(np.ascontiguousarray(disp, np.float32), 3)
    u = px[:, 0].astype(np.intp)
    v = px[:, 1].astype(np.intp)
    dev = np.abs(disp[v, u] - med[v, u]) / np.float32(scale_px)
    return np.exp(-(dev * dev)).astype(np.float64)


def local_heights(pts: np.ndarray, o, camera_z_m: float, fit_pts: np.ndarray | None = None):
    """(heights (N,), ground model) of points (N, 3): above the ground fitted to ``fit_pts``
    (default ``pts``) with ``ground_fit``, else above z = 0 (paper); with ``ground_local``
    above the local low envelope of ``fit_pts`` over that (:func:`.ground.local_ground`). With ``sky_far_m`` the
    points it calls sky get height -inf (never in a band)."""
    from .ground import GroundModel, fit_ground
    src = pts if fit_pts is None else fit_pts
    if getattr(o, "ground_fit", False):
        g = fit_ground(src, x_max_m=min(o.ground_max_range_m, o.max_range_m))
    else:
        g = GroundModel.level()
    if getattr(o, "ground_local", False):
        g = local_ground_of(src, o, g)
    return heights_above(g, pts, o, camera_z_m), g


def heights_above(g, pts: np.ndarray, o, camera_z_m: float) -> np.ndarray:
    """Heights of points (N, 3) above the ground model ``g``; with ``sky_far_m`` the points it
    calls sky or the far skyline get -inf (never in a band)."""
    from .ground import horizon_far_mask
    h = g.height(pts)
    far = getattr(o, "sky_far_m", 0.0)
    if far > 0 and len(h):
        h[horizon_far_mask(pts, camera_z_m, far, g)] = -np.inf
    return h


def local_ground_of(pts: np.ndarray, o, base):
    """``ground_local``: the local ground of points (N, 3) over ``base`` (a GroundModel) with
    the options' bins (:func:`.ground.local_ground`)."""
    from .ground import local_ground
    return local_ground(pts, base, x_max_m=min(o.ground_max_range_m, o.max_range_m),
                        cell_m=o.ground_local_cell_m, percentile=o.ground_local_percentile,
                        erode_cells=o.ground_local_erode, max_dev_m=o.ground_local_max_dev_m,
                        max_down_m=o.ground_local_max_down_m, min_seen=o.ground_local_min_bins)


def band_mask(pts: np.ndarray, h: np.ndarray, band_min_m: float, band_max_m: float,
              max_range_m: float) -> np.ndarray:
    """:func:`height_band` with the heights given (above the local ground)."""
    p = np.asarray(pts).reshape(-1, 3)
    return (h >= band_min_m) & (h <= band_max_m) & (p[:, 0] > 0) & (p[:, 0] <= max_range_m)


def dedupe_cells(xy: np.ndarray, cell_m: float = 0.1) -> np.ndarray:
    """One point per 0.1 m cell (the grid's resolution): fewer points, same occupied cells.
    The first point of each cell is kept, in input order."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32)
    k = np.floor(np.asarray(xy, np.float64) / cell_m).astype(np.int64)
    k -= k.min(axis=0)
    key = k[:, 0] * (int(k[:, 1].max()) + 1) + k[:, 1]      # one integer per cell
    if int(key.max()) < 65536:
        # the usual case (a few tens of metres at 0.1 m): numpy's stable sort of 16-bit keys
        # is a radix sort, 3x faster than np.unique's; the same first-of-each-cell indices
        key16 = key.astype(np.uint16)
        order = np.argsort(key16, kind="stable")
        ks = key16[order]
        first = np.ones(len(ks), bool)
        first[1:] = ks[1:] != ks[:-1]
        idx = order[first]
    else:
        _, idx = np.unique(key, return_index=True)
    return xy[np.sort(idx)].astype(np.float32)


class StereoPipeline(Pipeline):
    """Full-frame dense stereo and the height band: the paper's "stereo alone"."""

    name = "stereo"
    requires = ("stereo",)
    config_class = StereoConfig

    def __init__(self, options=None):
        super().__init__(options)
        check_matcher(self.options.matcher, f"perception.{self.name}")
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
        k = match_factor(fr.left.shape[1], o.match_width_px)
        calib = scaled_calibration(fr.calib, k)
        left, right = downscale(fr.left, k), downscale(fr.right, k)
        m = self.matcher_for(calib)
        H, W = left.shape[:2]
        disp, _ = disparity_regions(m, left, right, [(0, 0, W, H)], pad_left=o.pad_left)
        drop_dark(disp, left, o.dark_level)
        t1 = time.perf_counter()
        pts, px = points_from_disparity(disp, calib, None, max(1, o.point_stride // k),
                                        inputs.vehicle, o.use_attitude)
        h, ground = local_heights(pts, o, calib.mount.z_m)
        keep = band_mask(pts, h, o.band_min_m, o.band_max_m, o.max_range_m)
        if o.support_min > 0 and keep.any():
            idx = np.flatnonzero(keep)
            sup = vertical_support(disp, px[idx], pts[idx], calib, ground,
                                   vehicle=inputs.vehicle, use_attitude=o.use_attitude,
                                   known_min=o.support_known_min)
            keep[idx[sup < o.support_min]] = False
        xy = dedupe_cells(pts[keep, :2])
        conf = point_confidence(disp, px[keep], o.confidence_px)
        cands = cluster_candidates(pts[keep, :2], h[keep], conf, pipeline=self.name)
        t2 = time.perf_counter()
        return Detections(points_xy=xy, candidates=cands, debug={
            "matcher": o.matcher, "num_disparities": m.nd, "points": int(keep.sum()),
            "match_factor": k, "ground": ground.to_dict(), "candidates": len(cands),
            "ms": {"stereo": 1e3 * (t1 - t0), "points": 1e3 * (t2 - t1)}})
