"""Step 1 of the greenhouse paper (Nissimov et al. 2015, section 3.2): the vertical slope map.

For two vertically neighbouring depth pixels j (upper) and k (lower) of one column, eq. 4:

    tan(theta) = -(R_j sin b_j - R_k sin b_k) / (R_j cos b_j - R_k cos b_k)

where R is the range to the point in the column's vertical plane and b its vertical angle below
the horizontal. The paper hard-codes a level 640x480 Kinect (b_j = (y_j - 240.5) * 21.5 / 239.5).
Here the angle comes from the camera's real intrinsics and the mount pitch (positive = looking
down), optionally plus the vehicle's pitch:

    b(v) = atan((v - cy) / fy) + pitch,      R(v) = z * sqrt(1 + ((v - cy) / fy)^2)

with z the z-depth the HAL delivers. Then R sin b is the point's drop below the optical centre and
R cos b its distance forward, both in the level frame of the mount (exactly, for any column: the
lateral offset does not enter), so eq. 4 is the rise over run of the segment between the two
points. The slope returned is |theta| in degrees (0 = level ground, 90 = a wall facing the
camera); pairs with a depth outside [min_range, max_range] are NaN (ignored, as in the paper).
"""
from __future__ import annotations

import cv2
import numpy as np


def vertical_angles(height: int, fy: float, cy: float, pitch_rad: float) -> tuple[np.ndarray,
                                                                                  np.ndarray]:
    """Per image row: (b, sec) = (angle below the horizontal in radians, R / z)."""
    t = (np.arange(height, dtype=np.float64) - cy) / fy
    return np.arctan(t) + pitch_rad, np.sqrt(1.0 + t * t)


def paper_vertical_angles(height: int = 480) -> np.ndarray:
    """The paper's own b_j in radians (level 640x480 Kinect, 43 deg vertical FOV); for reference."""
    y = np.arange(1, height + 1, dtype=np.float64)          # the paper counts rows from 1
    return np.radians((y - 240.5) * 21.5 / 239.5)


def slope_map(depth_m: np.ndarray, fy: float, cy: float, pitch_rad: float,
              min_range_m: float = 0.5, max_range_m: float = 5.0, step_px: int = 1) -> np.ndarray:
    """HxW float32 slope in degrees (eq. 4) between pixel (v, u) and (v + step_px, u); NaN where
    either depth is outside the valid range and on the last ``step_px`` rows."""
    z = np.asarray(depth_m, dtype=np.float32)
    h = z.shape[0]
    b, sec = vertical_angles(h, fy, cy, pitch_rad)
    sb = (np.sin(b) * sec).astype(np.float32)[:, None]     # R sin b = z * sec * sin b
    cb = (np.cos(b) * sec).astype(np.float32)[:, None]
    down = z * sb
    fwd = z * cb
    valid = (z >= np.float32(min_range_m)) & (z <= np.float32(max_range_m))
    s = step_px
    dd = down[:-s] - down[s:]
    df = fwd[:-s] - fwd[s:]
    out = np.full(z.shape, np.nan, np.float32)
    ang = np.degrees(np.arctan2(np.abs(dd), np.abs(df)))
    ok = valid[:-s] & valid[s:]
    out[:-s] = np.where(ok, ang, np.float32(np.nan))
    return out


_ROW_CACHE: dict = {}


def _row_factors(height: int, fy: float, cy: float, pitch_rad: float):
    """(R sin b / z, R cos b / z) per row as float32 columns, cached (same camera every frame)."""
    key = (height, float(fy), float(cy), float(pitch_rad))
    f = _ROW_CACHE.get(key)
    if f is None:
        b, sec = vertical_angles(height, fy, cy, pitch_rad)
        f = ((np.sin(b) * sec).astype(np.float32)[:, None],
             (np.cos(b) * sec).astype(np.float32)[:, None])
        if len(_ROW_CACHE) > 64:
            _ROW_CACHE.clear()
        _ROW_CACHE[key] = f
    return f


def steep_map(depth_m: np.ndarray, fy: float, cy: float, pitch_rad: float,
              min_range_m: float = 0.5, max_range_m: float = 5.0, step_px: int = 1,
              threshold_deg: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """The thresholded eq. 4 without the angles (the fast path of the pipeline): (steep, level)
    bool maps, steep = slope_map(...) > threshold_deg, level = slope_map(...) <= threshold_deg,
    both False where the slope is undefined. |theta| > t  <=>  |drop| > tan(t) |run|."""
    z = np.asarray(depth_m, dtype=np.float32)
    s = step_px
    sb, cb = _row_factors(z.shape[0], fy, cy, pitch_rad)
    down = z * sb
    fwd = z * cb
    dd = np.abs(down[:-s] - down[s:])
    df = np.abs(fwd[:-s] - fwd[s:])
    df *= np.float32(np.tan(np.radians(threshold_deg)))
    valid = (z >= np.float32(min_range_m)) & (z <= np.float32(max_range_m))
    ok = valid[:-s] & valid[s:]
    steep = np.zeros(z.shape, bool)
    level = np.zeros(z.shape, bool)
    gt = dd > df
    np.logical_and(ok, gt, out=steep[:-s])
    np.logical_and(ok, ~gt, out=level[:-s])
    return steep, level


def height_map(depth_m: np.ndarray, fy: float, cy: float, pitch_rad: float,
               camera_height_m: float) -> np.ndarray:
    """HxW float32 height of each depth pixel above the ground plane under the mount (level
    ground assumed): camera height minus the point's drop R sin b."""
    sb, _ = _row_factors(depth_m.shape[0], fy, cy, pitch_rad)
    return np.float32(camera_height_m) - np.asarray(depth_m, np.float32) * sb


def suspected_map(slope_deg: np.ndarray, threshold_deg: float = 40.0,
                  dilate_px: int = 3, close: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(suspected, surface) boolean maps: slope above the threshold, dilated by a dilate_px x
    dilate_px square (the paper's 3x3, closing small gaps); surface = valid slope at or under the
    threshold and not suspected after the dilation."""
    with np.errstate(invalid="ignore"):
        sus = slope_deg > np.float32(threshold_deg)
        low = slope_deg <= np.float32(threshold_deg)
    return suspected_from(sus, low, dilate_px, close)


def suspected_from(steep: np.ndarray, level: np.ndarray, dilate_px: int = 3,
                   close: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """suspected_map from the steep / level maps of steep_map."""
    sus, low = steep, level
    if dilate_px > 1:
        k = np.ones((dilate_px, dilate_px), np.uint8)
        if close:       # dilation then erosion: closes the gaps without growing the region
            sus = cv2.morphologyEx(sus.view(np.uint8), cv2.MORPH_CLOSE, k) > 0
        else:
            sus = cv2.dilate(sus.view(np.uint8), k) > 0
    return sus, low & ~sus

