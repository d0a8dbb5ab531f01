"""Per-cell features of the learned cue (issue #8): shape and texture, not only colour.

Both papers decide from colour statistics (the stereo paper's Lab cell descriptor, the
greenhouse paper's Mahalanobis colour classes); an obstacle coloured like the field passes
both. The learned cue scores each image cell from what colour statistics leave out:

- colour, for context: Lab of the cell's mean colour and the B, G, R standard deviations (6);
- gradient energy: RMS of d/dx and d/dy, RMS gradient magnitude, mean |Laplacian| (4);
- edge orientation, from the cell's structure tensor J = mean [gx^2, gx gy; gx gy, gy^2]:
  anisotropy (Jxx - Jyy) / tr J, shear 2 Jxy / tr J and coherence
  ((Jxx - Jyy)^2 + 4 Jxy^2) / tr J^2 (3) -- ground seen at a grazing angle is foreshortened
  (horizontal structure: strong vertical gradients), a standing surface is not;
- micro-texture: rotation-invariant uniform LBP (8 neighbours, 10 codes) histogram (10) --
  leaves and stubble against the smooth faces of crates, drums and clothing;
- layout inside the cell: the grey means of its 2x2 quarters minus the cell mean (4);
- position: cell centre u, v in [0, 1] (2);
- context: the cell's colour, gradient, orientation and LBP features minus their median over
  its image row of cells (at a given row most cells are the ground at one distance) (20);
- neighbourhood: the 3x3 box mean of the colour and gradient features (10).

59 numbers per cell, float32: the feature set ``FEATURE_SET`` (camera images alone, the
stereo pipeline's). With registered depth (RGB-D) the set ``DEPTH_FEATURE_SET`` adds 6
numbers of shape the image cannot give: the share of valid depth, the mean depth, and the mean
and spread of the vertical and horizontal depth gradients relative to the depth (a crate's
face is a smooth plane, a bush's leaves are rough, the ground recedes evenly). A model file
records the set it was trained on and the loader refuses any other (appliance.cue_model).
Pure code: arrays in, arrays out. (Version 1 of the sets had a 6-bin orientation histogram;
the structure tensor gives the same kind of information for a third of the cost.)
"""
from __future__ import annotations

import cv2
import numpy as np

from .rgbd_texture import lbp_codes

FEATURE_SET = "fieldguard-cell-v2"

_BASE_NAMES = (["L_mean", "a_mean", "b_mean", "B_std", "G_std", "R_std",
                "gx", "gy", "grad", "laplace", "anisotropy", "shear", "coherence"]
               + [f"lbp_riu2_{i}" for i in range(10)]
               + [f"quarter_{i}" for i in range(4)]
               + ["u", "v"])
# indices into the base features: those given row context and neighbourhood means
_ROW_CONTEXT = tuple(range(0, 3)) + tuple(range(6, 23))          # 3 + 4 + 3 + 10 = 20
_NEIGHBOURHOOD = tuple(range(0, 10))                              # colour + gradient: 10
FEATURE_NAMES = tuple(_BASE_NAMES
                      + [f"row_ctx_{_BASE_NAMES[i]}" for i in _ROW_CONTEXT]
                      + [f"nbhd_{_BASE_NAMES[i]}" for i in _NEIGHBOURHOOD])
N_FEATURES = len(FEATURE_NAMES)
DEPTH_FEATURE_SET = "fieldguard-cell-depth-v2"
DEPTH_FEATURE_NAMES = FEATURE_NAMES + ("depth_valid", "depth_mean", "dz_dv", "dz_du",
                                       "dz_dv_spread", "dz_du_spread")
FEATURE_SETS = {FEATURE_SET: FEATURE_NAMES, DEPTH_FEATURE_SET: DEPTH_FEATURE_NAMES}
DEPTH_SCALE_M = 5.0        # depth_mean is depth / this


def _riu2_table() -> np.ndarray:
    """LBP code (eq. 6 bit order, clockwise) -> rotation-invariant uniform code 0..9: the number
    of set bits for a uniform pattern (at most 2 transitions round the circle), 9 otherwise."""
    t = np.zeros(256, np.int64)
    for c in range(256):
        bits = [(c >> i) & 1 for i in range(8)]
        trans = sum(bits[i] != bits[(i + 1) % 8] for i in range(8))
        t[c] = sum(bits) if trans <= 2 else 9
    return t


RIU2 = _riu2_table()
_RIU2_U8 = RIU2.astype(np.uint8)

_INDEX_CACHE: dict[tuple[int, int, int, int], np.ndarray] = {}


def _cell_index(rows: int, cols: int, cell: int, bins: int = 1) -> np.ndarray:
    """Per pixel (flattened): its cell's number times ``bins`` (int64, cached)."""
    key = (rows, cols, cell, bins)
    idx = _INDEX_CACHE.get(key)
    if idx is None:
        r = np.arange(rows * cell) // cell
        c = np.arange(cols * cell) // cell
        idx = ((r[:, None] * cols + c[None, :]) * bins).astype(np.int64).ravel()
        _INDEX_CACHE[key] = idx
    return idx


def scale_to_width(img: np.ndarray, width: int, min_height: int = 1,
                   depth_m: np.ndarray | None = None):
    """(image, depth) scaled to ``width`` px wide, keeping the aspect (at least ``min_height``
    rows): area-averaged when shrinking, bilinear when enlarging, depth by nearest neighbour
    (no mixed depths at edges). The one place training and the box resize an image for the
    cue, so both see the same pixels."""
    h, w = img.shape[:2]
    if w == width:
        return img, depth_m
    size = (int(width), max(int(min_height), int(round(h * width / float(w)))))
    out = cv2.resize(img, size, interpolation=cv2.INTER_AREA if w > width else cv2.INTER_LINEAR)
    d = None if depth_m is None else cv2.resize(depth_m, size, interpolation=cv2.INTER_NEAREST)
    return out, d


def grid_shape(image_shape: tuple[int, ...], cell_px: int) -> tuple[int, int]:
    """(rows, cols) of whole cells; a partial cell at the right or bottom edge is left out."""
    return int(image_shape[0]) // cell_px, int(image_shape[1]) // cell_px


def depth_features(depth_m: np.ndarray, rows: int, cols: int, cell_px: int) -> np.ndarray:
    """(rows, cols, 6) depth-shape features of the cells (depth in metres, 0 = no reading).
    Gradients only where the pixel and its 8 neighbours all have depth."""
    c = cell_px
    z = np.ascontiguousarray(depth_m[:rows * c, :cols * c], np.float32)
    valid = (z > 0).astype(np.float32)
    area = (cols, rows)

    def mean(x):
        return cv2.resize(x, area, interpolation=cv2.INTER_AREA)

    inner = cv2.erode(valid, np.ones((3, 3), np.uint8))      # pixel and neighbours valid
    zv = cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3) * np.float32(0.125) * inner
    zu = cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3) * np.float32(0.125) * inner
    n_in = mean(inner)
    safe = np.maximum(n_in, 1e-3)
    vf = mean(valid)
    zm = mean(z) / np.maximum(vf, 1e-3)                        # mean over valid pixels
    zr = np.maximum(zm, 0.1)
    out = np.zeros((rows, cols, 6), np.float32)
    out[..., 0] = vf
    out[..., 1] = zm / DEPTH_SCALE_M
    for k, g in ((2, zv), (3, zu)):
        m1 = mean(g) / safe
        m2 = mean(g * g) / safe
        out[..., k] = np.clip(m1 / zr, -1, 1)                 # slope per pixel, relative
        out[..., k + 2] = np.clip(np.sqrt(np.maximum(m2 - m1 * m1, 0)) / zr, 0, 1)
    out[n_in <= 0, 2:] = 0.0
    return out


def cell_features(bgr: np.ndarray, cell_px: int, depth_m: np.ndarray | None = None
                  ) -> np.ndarray:
    """(rows, cols, F) float32 features of the whole ``cell_px`` cells of a BGR uint8 image
    (any size; a grey image is taken as BGR): F = N_FEATURES, or with ``depth_m`` (registered,
    the image's size) the DEPTH_FEATURE_SET's 71. Raises ValueError on an image smaller than
    one cell or a cell under 4 px."""
    img = np.asarray(bgr)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"cue features need a BGR or grey image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"cue features need an 8-bit image, got {img.dtype}")
    if cell_px < 4:
        raise ValueError(f"cell_px must be >= 4, got {cell_px}")
    rows, cols = grid_shape(img.shape, cell_px)
    if rows < 1 or cols < 1:
        raise ValueError(f"image {img.shape[1]}x{img.shape[0]} is smaller than one "
                         f"{cell_px}-px cell")
    if depth_m is not None and depth_m.shape[:2] != img.shape[:2]:
        raise ValueError(f"depth {depth_m.shape[:2]} and image {img.shape[:2]} differ (depth "
                         "must be registered to the image)")
    c = cell_px
    img = np.ascontiguousarray(img[:rows * c, :cols * c])
    area = (cols, rows)

    def mean(x):                          # exact box mean per cell (integer factor)
        return cv2.resize(x, area, interpolation=cv2.INTER_AREA)

    # colour: Lab of the cell's mean colour (converting the cell means, not every pixel: the
    # per-pixel Lab conversion alone would cost more than all the rest), BGR spread
    bgr_m = mean(img.astype(np.float32))
    sq = img.astype(np.uint16)
    sq *= sq                                    # <= 65025: exact in 16 bits, cheap to average
    spread = np.sqrt(np.maximum(mean(sq).astype(np.float32) - bgr_m * bgr_m, 0.0))
    lab_m = cv2.cvtColor(np.ascontiguousarray(bgr_m * np.float32(1 / 255.0)),
                         cv2.COLOR_BGR2Lab)
    lab_m *= np.array([0.01, 1 / 128.0, 1 / 128.0], np.float32)       # ~[0, 1], [-1, 1]
    lab_s = spread * np.float32(1 / 255.0)
    g8 = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    grey = g8.astype(np.float32) * np.float32(1 / 255.0)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    jxx = mean(cv2.multiply(gx, gx))
    jyy = mean(cv2.multiply(gy, gy))
    jxy = mean(cv2.multiply(gx, gy))
    lap = mean(cv2.absdiff(cv2.Laplacian(grey, cv2.CV_32F, ksize=1), 0.0))
    tr = jxx + jyy
    safe = tr + np.float32(1e-6)
    grad = np.stack([np.sqrt(jxx), np.sqrt(jyy), np.sqrt(tr), lap,
                     (jxx - jyy) / safe, 2.0 * jxy / safe,
                     ((jxx - jyy) ** 2 + 4.0 * jxy * jxy) / (safe * safe)], axis=-1)
    n = rows * cols
    lbp = cv2.LUT(lbp_codes(g8), _RIU2_U8)
    hist = np.bincount(_cell_index(rows, cols, c, 10) + lbp.ravel(), minlength=n * 10)
    hist = hist.reshape(rows, cols, 10) * (1.0 / (c * c))
    quarters = cv2.resize(grey, (2 * cols, 2 * rows), interpolation=cv2.INTER_AREA)
    gm = mean(grey)
    q = quarters.reshape(rows, 2, cols, 2).transpose(0, 2, 1, 3).reshape(rows, cols, 4)
    q = q - gm[:, :, None]
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    pos = np.stack([(u + 0.5) / cols, (v + 0.5) / rows], axis=-1)
    base = np.concatenate([lab_m, lab_s, grad, hist, q, pos], axis=-1).astype(np.float32)
    ctx_src = base[:, :, _ROW_CONTEXT]
    row_ctx = ctx_src - np.median(ctx_src, axis=1, keepdims=True)
    nb = cv2.blur(np.ascontiguousarray(base[:, :, _NEIGHBOURHOOD]), (3, 3),
                  borderType=cv2.BORDER_REPLICATE)
    if nb.ndim == 2:                       # OpenCV drops a unit axis
        nb = nb.reshape(rows, cols, -1)
    parts = [base, row_ctx, nb]
    if depth_m is not None:
        parts.append(depth_features(depth_m, rows, cols, c))
    return np.ascontiguousarray(np.concatenate(parts, axis=-1), np.float32)
