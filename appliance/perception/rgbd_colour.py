"""Step 2 of the greenhouse paper (section 3.3, eq. 5): per-pixel colour classes.

Five colour features (section 4.1), computed from 8-bit R, G, B:

- ``rgb``:       (R, G, B)
- ``delta-rgb``: ((R-G)+(R-B), (G-R)+(G-B), (B-G)+(B-R))   -- sums to 0: rank 2
- ``i-rgb``:     ((R+G+B)/3, (R-B)/2, (2G-R-B)/4)
- ``i0-rgb``:    ((R+G+B)/3, (R-B), (2G-R-B)/2)
- ``lab``:       CIE L*a*b* (OpenCV, from float RGB in [0, 1]: L 0..100, a/b about -128..127)

Each class is a Gaussian (the paper) or a small mixture of Gaussians (the paper's future work)
per colour space; the distance of a pixel z to a class is the Mahalanobis distance (eq. 5)
d(z, m) = sqrt((z - m)^T C^-1 (z - m)), for a mixture the smallest over its components. A pixel
takes the nearest class when that distance is under the threshold, else ``UNDEFINED`` (-1).

Note (measured in docs/rgbd.md): I-RGB and I0-RGB are invertible linear maps of RGB, and the
Mahalanobis distance is invariant under those, so RGB, I-RGB and I0-RGB give the same classes up
to rounding -- which is what the paper's Tables 2-4 show. Delta-RGB loses the intensity (its
covariance is singular; a small ridge is added), which is why it does worse there and here.
"""
from __future__ import annotations

import sys
import threading
import weakref
from dataclasses import dataclass

import cv2
import numpy as np

COLOUR_SPACES = ("rgb", "delta-rgb", "i-rgb", "i0-rgb", "lab")
UNDEFINED = -1


def colour_features(bgr: np.ndarray, space: str) -> np.ndarray:
    """(..., 3) uint8 BGR -> (..., 3) float32 features of colour space ``space``."""
    img = np.asarray(bgr)
    if space == "lab":
        if img.size == 0:                       # OpenCV refuses an empty image
            return np.zeros(img.shape, np.float32)
        flat = img.reshape(-1, 1, 3)
        lab = cv2.cvtColor(flat.astype(np.float32) * np.float32(1 / 255), cv2.COLOR_BGR2Lab)
        return lab.reshape(img.shape).astype(np.float32)
    f = img.astype(np.float32)
    b, g, r = f[..., 0], f[..., 1], f[..., 2]
    if space == "rgb":
        out = (r, g, b)
    elif space == "delta-rgb":
        out = ((r - g) + (r - b), (g - r) + (g - b), (b - g) + (b - r))
    elif space == "i-rgb":
        out = ((r + g + b) / 3, (r - b) / 2, (2 * g - r - b) / 4)
    elif space == "i0-rgb":
        out = ((r + g + b) / 3, (r - b), (2 * g - r - b) / 2)
    else:
        raise ValueError(f"unknown colour space {space!r}; known: {', '.join(COLOUR_SPACES)}")
    return np.stack(out, axis=-1).astype(np.float32)


@dataclass(frozen=True)
class GaussianMixture:
    """K Gaussians in one colour space: means (K, 3), covariances (K, 3, 3), weights (K,)."""

    means: np.ndarray
    covs: np.ndarray
    weights: np.ndarray

    @property
    def k(self) -> int:
        return int(self.means.shape[0])

    def whiteners(self) -> np.ndarray:
        """(K, 3, 3) W with (z - m) W W^T (z - m)^T = (z - m)^T C^-1 (z - m) (W = chol(C^-1))."""
        return np.stack([np.linalg.cholesky(np.linalg.inv(c)) for c in self.covs])


def mahalanobis(z: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Eq. 5 for samples z (N, 3): sqrt((z - m)^T C^-1 (z - m)), float64."""
    d = np.asarray(z, np.float64) - np.asarray(mean, np.float64)
    ci = np.linalg.inv(np.asarray(cov, np.float64))
    return np.sqrt(np.einsum("ni,ij,nj->n", d, ci, d))


_LUT_CACHE: dict[tuple, np.ndarray] = {}
# the exact tables being built beside the loop: key -> weak references to the classifiers
# waiting for it (one build a key however many classifiers ask; a build nobody waits for any
# more is dropped between two chunks). Guarded by _LUT_LOCK, as _LUT_CACHE is.
_LUT_BUILDS: dict[tuple, list] = {}
_LUT_LOCK = threading.Lock()


class ColourClassifier:
    """Nearest class by Mahalanobis distance under a threshold; precomputes the whiteners.

    With ``space`` and ``lut_bits`` (5..8) it also builds a lookup table over BGR quantised to
    ``lut_bits`` per channel, each cell classified at its centre colour: classify_image() is then
    one gather per pixel in any colour space (Lab included). 8 bits: every colour has its own
    cell, so the table is exact (16 MB, 1-3 s to build once per model/space/threshold, cached
    for the process). 7 bits (2 MB, 8x faster to build): a cell spans 2 levels, so a colour
    within the quantisation error of the threshold or of a class boundary can differ from the
    exact distance (a tight class such as the greenhouse bush has ~0.5 distance units per level;
    test)."""

    def __init__(self, mixtures: list[GaussianMixture], threshold: float,
                 space: str | None = None, lut_bits: int = 0, background: bool = True):
        self.threshold = float(threshold)
        self._means = [m.means.astype(np.float32) for m in mixtures]
        self._w = [m.whiteners().astype(np.float32) for m in mixtures]
        self.space = space
        self.lut_bits = int(lut_bits)
        self._lut = None
        self._ready = threading.Event()
        if not self.lut_bits:
            return
        if space is None or not 5 <= self.lut_bits <= 8:
            raise ValueError("a colour lookup table needs a colour space and 5..8 bits")
        self._key = (space, self.lut_bits, self.threshold,
                     tuple(np.concatenate([m.ravel() for m in self._means]).tolist()),
                     tuple(np.concatenate([w.ravel() for w in self._w]).tolist()))
        with _LUT_LOCK:
            lut = _LUT_CACHE.get(self._key)
            waiting = _LUT_BUILDS.get(self._key) if lut is None and background else None
            if waiting is not None:
                waiting.append(weakref.ref(self))    # being built already: wait for that one
            elif lut is None and self.lut_bits == 8 and background:
                _LUT_BUILDS[self._key] = [weakref.ref(self)]
        if lut is not None:
            self._set(lut)
        elif waiting is not None:
            return                                   # that build hands this one the table
        elif self.lut_bits == 8 and background:
            # the exact table takes 1-3 s: build it beside the loop; until it is there the
            # caller classifies per pixel (lut_ready() False), with the same result. The
            # thread holds a copy without the table, never this classifier: a classifier
            # dropped before its table is done (a pipeline built and thrown away; the suite
            # made dozens, and their orphaned builds took ~1-3 CPU-s each from whatever ran
            # next) stops the build (2026-12-07)
            threading.Thread(target=_build_beside, args=(self._bare(), self._key),
                             name="rgbd-colour-lut", daemon=True).start()
        else:
            self._set(self._store(self._build_lut()))

    def _bare(self) -> "ColourClassifier":
        """A copy that classifies as this one does, with no table, no waiters, no event."""
        c = object.__new__(ColourClassifier)
        c.threshold, c._means, c._w = self.threshold, self._means, self._w
        c.space, c.lut_bits, c._key, c._lut = self.space, self.lut_bits, self._key, None
        return c

    def _store(self, lut: np.ndarray) -> np.ndarray:
        """The built table in its final layout, put in the process's cache."""
        if self.lut_bits == 8:
            # the exact table indexed R<<16 | G<<8 | B: a BGRA pixel read as one little-endian
            # 32-bit word is that index plus the alpha byte (classify_image: one conversion and
            # one mask instead of three strided channel reads, ~0.5 ms less a 640x480 frame)
            lut = np.ascontiguousarray(lut.reshape(256, 256, 256).transpose(2, 1, 0)).ravel()
        with _LUT_LOCK:
            if len(_LUT_CACHE) > 8:
                _LUT_CACHE.clear()
            _LUT_CACHE[self._key] = lut
        return lut

    def _set(self, lut: np.ndarray) -> None:
        self._lut = lut
        self._ready.set()

    def lut_ready(self) -> bool:
        return self._lut is not None

    def wait_lut(self, timeout: float | None = None) -> bool:
        """Block until the lookup table is built (tools, tests); True when it is."""
        return self._ready.wait(timeout) if self.lut_bits else False

    def _build_lut(self, wanted=None) -> np.ndarray | None:
        """The table (n**3 classes, blue-major); None when ``wanted()`` said no between two
        chunks (nobody waits for it any more)."""
        bits = self.lut_bits
        n = 1 << bits
        step = 256 // n
        centre = (np.arange(n, dtype=np.float32) * step + (step - 1) / 2.0).astype(np.float32)
        lut = np.empty(n ** 3, np.int8)
        gr, rr = np.meshgrid(centre, centre, indexing="ij")
        gr, rr = gr.ravel(), rr.ravel()
        per = max(1, (1 << 18) // (n * n))          # blue planes per chunk: bounded memory
        for b0 in range(0, n, per):
            if wanted is not None and not wanted():
                return None
            bs = centre[b0:b0 + per]
            bgr = np.stack([np.repeat(bs, n * n), np.tile(gr, len(bs)), np.tile(rr, len(bs))],
                           axis=1)
            lut[b0 * n * n:(b0 + len(bs)) * n * n] = self.classify(colour_features(bgr,
                                                                                 self.space))
        return lut

    def classify_image(self, bgr: np.ndarray) -> np.ndarray:
        """HxWx3 uint8 BGR -> HxW int16 classes through the lookup table."""
        if self._lut is None:
            img = np.asarray(bgr)
            return self.classify(colour_features(img.reshape(-1, 3), self.space or "rgb")) \
                .reshape(img.shape[:2])
        bits = self.lut_bits
        c = np.asarray(bgr, np.uint8)
        if bits == 8 and sys.byteorder == "little":
            v = cv2.cvtColor(np.ascontiguousarray(c), cv2.COLOR_BGR2BGRA).view(np.uint32)[..., 0]
            np.bitwise_and(v, np.uint32(0xFFFFFF), out=v)
            return np.take(self._lut, v).astype(np.int16)
        if bits == 8:                                   # (the table is in R, G, B order)
            idx = c[..., 2].astype(np.int32)
            idx <<= 8
            idx |= c[..., 1]
            idx <<= 8
            idx |= c[..., 0]
            return self._lut[idx].astype(np.int16)
        if bits < 8:
            c = c >> np.uint8(8 - bits)
        idx = c[..., 0].astype(np.int32)
        idx <<= bits
        idx |= c[..., 1]
        idx <<= bits
        idx |= c[..., 2]
        return self._lut[idx].astype(np.int16)

    def distances(self, feats: np.ndarray) -> np.ndarray:
        """(N, 3) features -> (N, C) Mahalanobis distance to each class (min over components)."""
        z = np.asarray(feats, np.float32).reshape(-1, 3)
        zc = [np.ascontiguousarray(z[:, i]) for i in range(3)]     # planar: fast on 3x3
        out = np.empty((z.shape[0], len(self._means)), np.float32)
        d = [np.empty_like(zc[0]) for _ in range(3)]
        y = np.empty_like(zc[0])
        acc = np.empty_like(zc[0])
        for c, (means, ws) in enumerate(zip(self._means, self._w)):
            best = None
            for m, w in zip(means, ws):
                for i in range(3):
                    np.subtract(zc[i], m[i], out=d[i])
                d2 = np.zeros_like(zc[0])
                for j in range(3):                    # y_j = sum_i d_i W_ij (W lower-tri)
                    np.multiply(d[j], w[j, j], out=y)
                    for i in range(j + 1, 3):
                        np.multiply(d[i], w[i, j], out=acc)
                        y += acc
                    y *= y
                    d2 += y
                best = d2 if best is None else np.minimum(best, d2, out=best)
            out[:, c] = np.sqrt(best)
        return out

    def classify(self, feats: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) int16 class index, UNDEFINED when no class is under the threshold."""
        d = self.distances(feats)
        if d.shape[1] == 0:
            return np.full(d.shape[0], UNDEFINED, np.int16)
        idx = np.argmin(d, axis=1)
        best = d[np.arange(d.shape[0]), idx]
        return np.where(best < self.threshold, idx, UNDEFINED).astype(np.int16)


def _build_beside(proto: ColourClassifier, key: tuple) -> None:
    """The background build of one exact table (a thread): handed to every classifier still
    waiting for it when done; dropped, and forgotten, as soon as none is (then a classifier
    made later starts its own)."""
    def wanted() -> bool:
        with _LUT_LOCK:
            refs = _LUT_BUILDS.get(key, [])
            refs[:] = [r for r in refs if r() is not None]
            if not refs:
                _LUT_BUILDS.pop(key, None)       # atomically with the answer: no waiter lost
            return bool(refs)
    lut = proto._build_lut(wanted)
    if lut is None:
        return
    lut = proto._store(lut)
    with _LUT_LOCK:
        refs = _LUT_BUILDS.pop(key, [])
    for r in refs:
        c = r()
        if c is not None:
            c._set(lut)


# ---------------------------------------------------------------------------------------------
# training (pure maths; the CLI in appliance/cli_rgbd.py reads the frames and annotations)
# ---------------------------------------------------------------------------------------------
def fit_gaussian(samples: np.ndarray, ridge: float = 1.0) -> GaussianMixture:
    """One Gaussian: the sample mean and covariance (+ ``ridge`` * I so that a flat class such as
    saturated white, or rank-2 Delta-RGB, stays invertible)."""
    x = np.asarray(samples, np.float64).reshape(-1, 3)
    if x.shape[0] < 4:
        raise ValueError(f"need at least 4 samples to fit a class, got {x.shape[0]}")
    cov = np.cov(x, rowvar=False) + ridge * np.eye(3)
    return GaussianMixture(x.mean(0)[None], cov[None], np.ones(1))


def fit_mixture(samples: np.ndarray, k: int, ridge: float = 1.0, iters: int = 50,
                seed: int = 0) -> GaussianMixture:
    """K Gaussians by EM (k-means++-style start, fixed seed: deterministic). k=1 is fit_gaussian."""
    if k <= 1:
        return fit_gaussian(samples, ridge)
    x = np.asarray(samples, np.float64).reshape(-1, 3)
    n = x.shape[0]
    if n < 4 * k:
        raise ValueError(f"need at least {4 * k} samples for {k} components, got {n}")
    rng = np.random.default_rng(seed)
    centres = [x[rng.integers(n)]]
    for _ in range(1, k):
        d2 = np.min([((x - c) ** 2).sum(1) for c in centres], axis=0)
        centres.append(x[rng.choice(n, p=d2 / d2.sum())] if d2.sum() > 0 else x[rng.integers(n)])
    means = np.array(centres)
    covs = np.repeat((np.cov(x, rowvar=False) + ridge * np.eye(3))[None], k, 0)
    w = np.full(k, 1.0 / k)
    prev = -np.inf
    for _ in range(iters):
        logp = np.empty((n, k))
        for j in range(k):
            d = x - means[j]
            ci = np.linalg.inv(covs[j])
            _, logdet = np.linalg.slogdet(covs[j])
            logp[:, j] = np.log(w[j]) - 0.5 * (np.einsum("ni,ij,nj->n", d, ci, d) + logdet)
        mx = logp.max(1, keepdims=True)
        ll = float((mx[:, 0] + np.log(np.exp(logp - mx).sum(1))).mean())
        r = np.exp(logp - mx)
        r /= r.sum(1, keepdims=True)
        nk = r.sum(0) + 1e-9
        w = nk / n
        means = (r.T @ x) / nk[:, None]
        for j in range(k):
            d = x - means[j]
            covs[j] = (r[:, j, None] * d).T @ d / nk[j] + ridge * np.eye(3)
        if ll - prev < 1e-6:
            break
        prev = ll
    return GaussianMixture(means, covs, w)
