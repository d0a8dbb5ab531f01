"""Step 3 of the greenhouse paper (section 3.4, eqs. 6-8): LBP texture classes.

- eq. 6: LBP(c) = sum_{p=1..8} S(g_p - g_c) 2^(p-1), S(x) = 1 if x >= 0 else 0, over the 8
  neighbours of c. Our neighbour order (the paper does not give one; any fixed order is the same
  operator up to a relabelling of the 256 codes): p = 1 top-left, 2 top, 3 top-right, 4 right,
  5 bottom-right, 6 bottom, 7 bottom-left, 8 left (clockwise from the top-left). Image borders
  repeat the edge pixel.
- eq. 7: a 256-bin histogram H(k) = |{c : LBP(c) = k}| per window (20x20 pixels, tiled from the
  top-left corner), normalised to sum 1 (the paper's Fig. 6 and its 0.5 threshold assume that).
- eq. 8: chi-square D(T, L) = sum_x (T_x - L_x)^2 / (T_x + L_x), with 0/0 = 0; a window takes the
  nearest class histogram when D is under the threshold (0.5), else UNDEFINED (-1).
"""
from __future__ import annotations

import cv2
import numpy as np

UNDEFINED = -1
# (dy, dx) of neighbours p = 1..8
NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1))


def to_grey(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2GRAY)


def lbp_codes(grey: np.ndarray) -> np.ndarray:
    """HxW uint8 grey -> HxW uint8 LBP codes (eq. 6)."""
    g = np.asarray(grey, np.uint8)
    h, w = g.shape
    p = cv2.copyMakeBorder(g, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    code = np.zeros((h, w), np.uint8)
    for bit, (dy, dx) in enumerate(NEIGHBOURS):
        nb = p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        # S(g_p - g_c) = 1 when g_p >= g_c; cv2.compare gives 255/0 -> keep one bit
        ge = cv2.compare(nb, g, cv2.CMP_GE)
        code |= ge & np.uint8(1 << bit)
    return code


_BLOCK_CACHE: dict[tuple[int, int, int], tuple[np.ndarray, int, int]] = {}


def window_index(shape: tuple[int, int], window: int) -> tuple[np.ndarray, int, int]:
    """(HxW int32 window number, windows down, windows across) for windows tiled from (0, 0);
    a partial window at the right/bottom edge is a window of its own."""
    key = (shape[0], shape[1], window)
    if key not in _BLOCK_CACHE:
        ny, nx = -(-shape[0] // window), -(-shape[1] // window)
        r = np.arange(shape[0]) // window
        c = np.arange(shape[1]) // window
        _BLOCK_CACHE[key] = ((r[:, None] * nx + c[None, :]).astype(np.int32), ny, nx)
    return _BLOCK_CACHE[key]


_BASE_CACHE: dict[tuple[int, int, int], np.ndarray] = {}


def _window_base(shape: tuple[int, int], window: int) -> np.ndarray:
    """window number * 256 per pixel (int32), cached."""
    key = (shape[0], shape[1], window)
    if key not in _BASE_CACHE:
        _BASE_CACHE[key] = window_index(shape, window)[0] * np.int32(256)
    return _BASE_CACHE[key]


def window_histograms(codes: np.ndarray, window: int = 20,
                      windows: np.ndarray | None = None) -> np.ndarray:
    """Eq. 7 per window, normalised: (n_windows, 256) float32 (rows of empty windows are 0).
    ``windows`` (optional): the window numbers wanted; only their pixels are counted."""
    idx, ny, nx = window_index(codes.shape, window)
    n = ny * nx
    if windows is None:
        flat = (_window_base(codes.shape, window) + codes).ravel()
    else:
        want = np.zeros(n, bool)
        want[windows] = True
        sel = want[idx]
        flat = idx[sel].astype(np.int64) * 256 + codes[sel]
    hist = np.bincount(flat, minlength=n * 256).reshape(n, 256).astype(np.float32)
    tot = hist.sum(1, keepdims=True)
    return np.divide(hist, tot, out=np.zeros_like(hist), where=tot > 0)


def normalised_histogram(codes: np.ndarray) -> np.ndarray:
    """Normalised 256-bin histogram of a set of codes (a class model)."""
    h = np.bincount(np.asarray(codes, np.int64).ravel(), minlength=256).astype(np.float64)
    return (h / h.sum()) if h.sum() > 0 else h


def chi_square(t: np.ndarray, l: np.ndarray) -> np.ndarray:
    """Eq. 8 between histograms t (..., 256) and l (..., 256), broadcasting; 0/0 counts 0."""
    t = np.asarray(t, np.float64)
    l = np.asarray(l, np.float64)
    s = t + l
    d = (t - l) ** 2
    return np.sum(np.divide(d, s, out=np.zeros(np.broadcast(t, l).shape), where=s > 0), axis=-1)


def classify_histograms(hists: np.ndarray, models: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """(N, 256) window histograms vs (C, 256) class histograms -> (N,) int16 class or UNDEFINED.

    Eq. 8 per class in float32 without a masked divide: a class bin of 0 is raised to 1e-12, so
    a bin empty in both gives 0/1e-12 = 0 and any other bin is unchanged to float32 precision."""
    if len(hists) == 0 or len(models) == 0:
        return np.full(len(hists), UNDEFINED, np.int16)
    h = np.asarray(hists, np.float32)
    d = np.empty((h.shape[0], len(models)), np.float32)
    num = np.empty_like(h)
    den = np.empty_like(h)
    for c, m in enumerate(np.asarray(models, np.float32)):
        m = np.maximum(m, np.float32(1e-12))
        np.subtract(h, m, out=num)
        np.multiply(num, num, out=num)
        np.add(h, m, out=den)
        np.divide(num, den, out=num)
        d[:, c] = num.sum(axis=1)
    idx = np.argmin(d, axis=1)
    best = d[np.arange(len(d)), idx]
    return np.where(best < threshold, idx, UNDEFINED).astype(np.int16)
