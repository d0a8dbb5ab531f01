"""Obstacle candidates: a frame's obstacle points grouped into objects.

:func:`cluster_candidates` puts the points (vehicle frame x, y; their height above the local
ground; a per-point confidence; per-point cue flags) on a ground grid of ``cell_m`` cells and
labels its 8-connected components (a gap of one empty cell still joins: the grid is dilated
by ``join_cells`` before labelling, the labels read back on the occupied cells only). Each
component with at least ``min_points`` points is a :class:`~.base.Candidate`:

- footprint: the axis-aligned extent of its points (at least one cell) and its centre;
- ``height_m``: the 95th percentile (by rank) of its points' heights above the ground;
- ``ground_contact``: its lowest points come within ``contact_m`` of the ground (an overhang
  or a mismatch floating in the air does not);
- ``points``: its point count; ``confidence``: the mean point confidence times a support
  term ``1 - exp(-points / support_points)`` (one stray point is not a confident object);
- ``sources``: the cues of which at least ``source_min_share`` of its points carry the flag
  (always at least the pipeline's base source).

Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

import cv2
import numpy as np

from .base import Candidate



def on_footprints(xy: np.ndarray, cands, margin_m: float) -> np.ndarray:
    """Per point of ``xy`` (N, >= 2; vehicle frame): does it lie on the footprint of one of
    ``cands`` grown by ``margin_m`` each way (the points that belong to those candidates)?"""
    p = np.asarray(xy)
    on = np.zeros(len(p), bool)
    for c in cands:
        on |= ((np.abs(p[:, 0] - c.x_m) <= c.length_m / 2 + margin_m)
               & (np.abs(p[:, 1] - c.y_m) <= c.width_m / 2 + margin_m))
    return on

def cell_labels(p: np.ndarray, cell_m: float, join_cells: int = 1
                ) -> tuple[int, np.ndarray] | None:
    """(number of labels, per point its cluster label >= 1) of finite points ``p`` (N >= 1, 2)
    on a ground grid of ``cell_m`` cells, 8-connected with gaps of ``join_cells`` empty cells
    joined (the module's clustering); None when the grid would exceed 4 million cells."""
    g = np.floor(p / cell_m).astype(np.int64)
    gx, gy = g[:, 0], g[:, 1]
    gx -= gx.min() - join_cells
    gy -= gy.min() - join_cells
    H, W = int(gx.max()) + 1 + join_cells, int(gy.max()) + 1 + join_cells
    if H * W > 4_000_000:
        return None
    occ = np.zeros((H, W), np.uint8)
    occ[gx, gy] = 1
    grown = cv2.dilate(occ, np.ones((2 * join_cells + 1,) * 2, np.uint8)) if join_cells else occ
    nlab, lab = cv2.connectedComponents(grown, connectivity=8, ltype=cv2.CV_32S)
    return nlab, lab[gx, gy]


def low_clusters(xy: np.ndarray, height: np.ndarray, min_top_m: float, cell_m: float = 0.1,
                 join_cells: int = 1) -> np.ndarray:
    """Per point (``xy`` (N, 2), ``height`` (N,) above the ground): True when the cluster it
    belongs to (:func:`cell_labels`, as :func:`cluster_candidates` groups them, whatever its
    point count) has its top (the 95th percentile by rank of its heights, a candidate's
    ``height_m``) below ``min_top_m``. Points that are not finite are never low."""
    p = np.asarray(xy, np.float64).reshape(-1, 2)
    h = np.asarray(height, np.float64).reshape(-1)
    out = np.zeros(len(p), bool)
    if len(p) == 0 or min_top_m <= 0:
        return out
    # (column by column: numpy's reductions along the short axis of an (N, 2) array are slow)
    ok = np.isfinite(p[:, 0]) & np.isfinite(p[:, 1]) & np.isfinite(h)
    if ok.all():
        idx, q, hq = slice(None), p, h
    else:
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return out
        q, hq = p[idx], h[idx]
    cm = cell_m
    cl = cell_labels(q, cm, join_cells)
    while cl is None:                # a pathological spread: coarser cells, as the clustering
        cm *= 2
        cl = cell_labels(q, cm, join_cells)
    nlab, pl = cl
    # no sort: the height of rank r (ascending) is below the limit exactly when more than r of
    # the cluster's heights are
    counts = np.bincount(pl, minlength=nlab)
    below = np.bincount(pl[hq < min_top_m], minlength=nlab)
    r_top = np.round(0.95 * (np.maximum(counts, 1) - 1)).astype(np.int64)
    low_label = (counts > 0) & (below > r_top)
    out[idx] = low_label[pl]
    return out


def cluster_candidates(xy: np.ndarray, height: np.ndarray | None = None,
                       confidence: np.ndarray | None = None,
                       flags: dict[str, np.ndarray] | None = None,
                       base_sources: tuple[str, ...] = ("geometry",), pipeline: str = "?",
                       cell_m: float = 0.2, join_cells: int = 1, min_points: int = 3,
                       contact_m: float = 0.8, support_points: float = 10.0,
                       source_min_share: float = 0.2, max_range_m: float = 60.0,
                       max_candidates: int = 64) -> tuple[Candidate, ...]:
    """Candidates from obstacle points ``xy`` (N, 2); see the module's docstring.
    ``height`` (N,) above the local ground (None: unknown, height 0 and no contact claim);
    ``confidence`` (N,) in [0, 1] (None: 1); ``flags``: source name -> bool (N,)."""
    p = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(p)
    if n == 0:
        return ()
    # (column by column: numpy's reductions along the short axis of an (N, 2) array are slow)
    ax, ay = np.abs(p[:, 0]), np.abs(p[:, 1])
    ok = (ax <= max_range_m) & (ay <= max_range_m)           # NaN compares False
    if not np.isfinite(max_range_m):
        ok &= np.isfinite(ax) & np.isfinite(ay)
    idx = None if ok.all() else np.flatnonzero(ok)            # None: every point
    if (n if idx is None else len(idx)) < min_points:
        return ()

    def pick(a, dtype):
        a = np.asarray(a, dtype).reshape(-1)
        return a if idx is None else a[idx]

    if idx is not None:
        p = p[idx]
    h = None if height is None else pick(height, np.float64)
    c = np.ones(len(p)) if confidence is None else np.clip(pick(confidence, np.float64),
                                                            0.0, 1.0)
    fl = {k: pick(v, bool) for k, v in (flags or {}).items()}
    cl = cell_labels(p, cell_m, join_cells)
    if cl is None:                   # a pathological spread: coarser cells
        return cluster_candidates(xy, height, confidence, flags, base_sources, pipeline,
                                  cell_m * 2, join_cells, min_points, contact_m,
                                  support_points, source_min_share, max_range_m,
                                  max_candidates)
    nlab, pl = cl
    # one stable sort by label (a radix sort when the labels fit 16 bits): each label's points
    # are a block, its sums and extents by reduceat: no per-cluster numpy calls but the two
    # height ranks of the kept clusters (a partition of the block)
    order = np.argsort(pl.astype(np.uint16) if nlab <= 1 << 16 else pl, kind="stable")
    pls = pl[order]
    starts = np.flatnonzero(np.r_[True, pls[1:] != pls[:-1]])
    labels = pls[starts]
    counts = np.diff(np.r_[starts, len(pls)])
    px, py = p[:, 0][order], p[:, 1][order]
    lo = np.stack([np.minimum.reduceat(px, starts), np.minimum.reduceat(py, starts)], axis=1)
    hi = np.stack([np.maximum.reduceat(px, starts), np.maximum.reduceat(py, starts)], axis=1)
    csum = np.add.reduceat(c[order], starts)
    fsum = {k: np.add.reduceat(v[order].astype(np.int64), starts) for k, v in fl.items()}
    ho = None if h is None else h[order]
    out = []
    for j in np.flatnonzero((counts >= min_points) & (labels > 0)):
        k = int(counts[j])
        s0 = starts[j]
        ext = np.maximum(hi[j] - lo[j], cell_m)
        if ho is not None:
            r_top, r_low = int(round(0.95 * (k - 1))), int(round(0.05 * (k - 1)))
            blk = np.partition(ho[s0:s0 + k], (r_low, r_top))
            top = float(blk[r_top])
            contact = bool(blk[r_low] <= contact_m)
        else:
            top, contact = 0.0, True
        conf = float(csum[j]) / k * (1.0 - float(np.exp(-k / support_points)))
        src = list(base_sources)
        for name, f in fsum.items():
            if name not in src and f[j] >= source_min_share * k:
                src.append(name)
        out.append(Candidate(x_m=float((lo[j, 0] + hi[j, 0]) / 2),
                             y_m=float((lo[j, 1] + hi[j, 1]) / 2),
                             length_m=float(ext[0]), width_m=float(ext[1]), height_m=top,
                             points=k, confidence=round(conf, 4), sources=tuple(src),
                             ground_contact=contact, pipeline=pipeline))
    out.sort(key=lambda cd: -cd.points)
    return tuple(out[:max_candidates])



def stalk_points(xy: np.ndarray, height: np.ndarray, other_cue: np.ndarray | None,
                 max_width_m: float, max_length_m: float, max_height_m: float,
                 window_x_m: float = 0.2, window_y_m: float = 0.3, cell_m: float = 0.1,
                 other_min_share: float = 0.2, max_range_m: float = np.inf) -> np.ndarray:
    """Per obstacle point (``xy`` (N, 2) vehicle frame, ``height`` (N,) above the ground): True
    when the obstacle material around it is a **stalk**: thin and short. Around a point means
    the points in the ``cell_m`` cells within ``window_x_m`` along and ``window_y_m`` across
    of its own cell; they are a stalk when they span at most ``max_width_m`` across (y) and
    ``max_length_m`` along (x), the highest reaches at most ``max_height_m``, and fewer than
    ``other_min_share`` of them were raised by a cue other than geometry (``other_cue`` (N,)
    bool: novelty, the learned cue; None: none). Only points at most ``max_range_m`` ahead
    (x) are judged: farther away a thing 0.2 m across is a few pixels wide and its points too
    sparse for a width (a crouching person 15 m away at night showed a 0.2 m sliver).

    A stubble tuft that reaches above the band's floor is such a thing (9-17 cm across,
    0.5-0.7 m tall, and the next tall tuft seldom within the window); a person, a pole (tall),
    a drum, a crate, a crouching person (wide) are not. Judged on neighbourhoods, not on
    clusters: the candidates' clusters join tufts with whatever stands 0.4 m away."""
    from scipy.ndimage import maximum_filter, minimum_filter, uniform_filter

    p = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(p)
    out = np.zeros(n, bool)
    if n == 0 or max_width_m <= 0:
        return out
    h = np.asarray(height, np.float64).reshape(-1)
    ok = np.all(np.isfinite(p), axis=1) & np.isfinite(h)
    # points beyond the judged range matter only as neighbours of judged ones
    ok &= p[:, 0] <= max_range_m + window_x_m + 2 * cell_m
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return out
    q = p[idx]
    wx = max(1, int(round(window_x_m / cell_m)))
    wy = max(1, int(round(window_y_m / cell_m)))
    g = np.floor(q / cell_m).astype(np.int64)
    g -= g.min(axis=0)
    H, W = int(g[:, 0].max()) + 1, int(g[:, 1].max()) + 1
    if H * W > 4_000_000:                 # a pathological spread: no stalk judged
        return out
    flat = g[:, 0] * W + g[:, 1]
    big = np.inf

    def cell_reduce(fn, vals, fill):
        a = np.full(H * W, fill)
        fn.at(a, flat, vals)
        return a.reshape(H, W)
    size = (2 * wx + 1, 2 * wy + 1)
    lo_x = minimum_filter(cell_reduce(np.minimum, q[:, 0], big), size=size, mode="constant",
                          cval=big)
    hi_x = maximum_filter(cell_reduce(np.maximum, q[:, 0], -big), size=size, mode="constant",
                          cval=-big)
    lo_y = minimum_filter(cell_reduce(np.minimum, q[:, 1], big), size=size, mode="constant",
                          cval=big)
    hi_y = maximum_filter(cell_reduce(np.maximum, q[:, 1], -big), size=size, mode="constant",
                          cval=-big)
    top = maximum_filter(cell_reduce(np.maximum, h[idx], -big), size=size, mode="constant",
                         cval=-big)
    cnt = uniform_filter(np.bincount(flat, minlength=H * W).reshape(H, W).astype(np.float64),
                         size=size, mode="constant")
    if other_cue is not None:
        oth = uniform_filter(np.bincount(flat, weights=np.asarray(other_cue, bool).reshape(-1)[idx]
                                         .astype(np.float64), minlength=H * W).reshape(H, W),
                             size=size, mode="constant")
    else:
        oth = np.zeros((H, W))
    gi, gj = g[:, 0], g[:, 1]
    stalk = ((hi_y[gi, gj] - lo_y[gi, gj] <= max_width_m)
             & (hi_x[gi, gj] - lo_x[gi, gj] <= max_length_m)
             & (top[gi, gj] <= max_height_m)
             & (oth[gi, gj] < other_min_share * cnt[gi, gj] - 1e-9)
             & (q[:, 0] <= max_range_m))
    out[idx] = stalk
    return out
