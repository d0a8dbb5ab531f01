"""Rendering the world for each sensor.

Cameras: the "voxel-space" column algorithm on a LEVEL virtual camera at the real optical centre
(same focal length, enough extra field of view to cover the real camera's pitch and roll), then a
warp to the real camera with the pure-rotation homography K·R·K⁻¹ (exact for a rotation about the
optical centre); z-depth is converted per target pixel. For a level camera every image column
holds the rays of one vertical plane, so each column is a 1-D march over forward depth t: the
world's height at each sample projects to an image row, a running minimum of that row (the
y-buffer) tells which sample each pixel row sees first. The per-row lookup is a histogram +
cumulative sum (no per-pixel search).

Laser: each beam is marched in 3-D against the height field (terrain only where the beam is low
enough to touch it; obstacles only where the beam passes near them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from hal.types import PinholeCalibration

from .world import MAT_GROUND, MAT_OBSTACLE, MAT_SKY, MAT_STUBBLE, World


# the renderer's camera model is the HAL's pinhole calibration (same fields, same matrix())
Intrinsics = PinholeCalibration


@dataclass
class View:
    radiance: np.ndarray      # HxWx3 float32 BGR, linear, before exposure/noise
    zdepth: np.ndarray        # HxW float32 z-depth along the real optical axis, 0 = sky
    mat: np.ndarray           # HxW int16 material code (MAT_SKY for sky)
    albedo_lum: np.ndarray    # HxW float32 albedo luminance (for RGB-D dark-surface holes)


@dataclass(frozen=True)
class Lighting:
    mode: str                                   # "day" | "night-strobe" | "greenhouse"
    sun: tuple[float, float, float] = (0.5, 0.3, 0.81)   # unit vector towards the sun (world)
    strobe_power: float = 30.0
    cloud: float = 0.0                          # 0 clear .. 1 overcast (softer, fewer shadows)
    dusk: float = 0.0                           # 0 day .. 1 dusk (dimmer, warmer)
    wind_mps: tuple[float, float] = (0.0, 0.0)  # cloud shadows drift with the wind


class _Timer:
    """Optional stage timing (set render.TIMING = {} to collect)."""

    def __init__(self):
        import time
        self._time = time.process_time     # CPU time (the machine is shared)
        self.t = self._time()

    def __call__(self, label):
        if TIMING is not None:
            now = self._time()
            TIMING[label] = TIMING.get(label, 0.0) + (now - self.t) * 1e3
            self.t = now


TIMING: dict | None = None


@lru_cache(maxsize=16)
def march_steps(t_min: float, t_max: float, rel: float, step_min: float) -> np.ndarray:
    """Forward depths of the samples: step max(step_min, rel * t)."""
    ts = []
    t = t_min
    while t < t_max:
        ts.append(t)
        t += max(step_min, rel * t)
    return np.array(ts, np.float32)


def _level_basis(yaw: float) -> np.ndarray:
    """Optical->world rotation of a level camera looking along world heading ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


# "numba": the compiled loops of fastrender.py (the default); "numpy": the whole-array code below
ENGINE = "numba"


def _virtual_camera(cam: Intrinsics, r_opt2world: np.ndarray):
    """The level virtual camera that covers the real one: (yaw, M real->virtual optical,
    u0, v0, Wv, Hv, cxv, cyv)."""
    fwd = r_opt2world[:, 2]
    yaw = math.atan2(fwd[1], fwd[0])
    Rv = _level_basis(yaw)
    M = Rv.T @ r_opt2world
    Kinv = np.linalg.inv(cam.matrix())
    n = 24
    us = np.linspace(-0.5, cam.width - 0.5, n)
    vs = np.linspace(-0.5, cam.height - 0.5, n)
    border = np.concatenate([np.stack([us, np.full(n, vs[0])], 1), np.stack([us, np.full(n, vs[-1])], 1),
                             np.stack([np.full(n, us[0]), vs], 1), np.stack([np.full(n, us[-1]), vs], 1)])
    rays = M @ (Kinv @ np.vstack([border.T, np.ones(len(border))]))
    if np.any(rays[2] <= 0.05):
        raise ValueError("camera looks too far up or down for the level-camera renderer")
    pu = cam.fx * rays[0] / rays[2]
    pv = cam.fy * rays[1] / rays[2]
    u0, u1 = math.floor(pu.min()) - 2, math.ceil(pu.max()) + 2
    v0, v1 = math.floor(pv.min()) - 2, math.ceil(pv.max()) + 2
    return yaw, M, Kinv, u1 - u0 + 1, v1 - v0 + 1, float(-u0), float(-v0)


def render_view(world: World, light: Lighting, centre: np.ndarray, r_opt2world: np.ndarray,
                cam: Intrinsics, t_max: float = 80.0, t_min: float = 0.3, rel_step: float = 0.004,
                min_step: float = 0.01, need_depth: bool = True) -> View:
    """Render one pinhole camera (optical centre ``centre`` in world, attitude ``r_opt2world``).
    ``need_depth=False``: only the radiance is warped to the real camera (zdepth, mat and
    albedo_lum are None), which is all a stereo camera needs."""
    if ENGINE == "numba" and world.extent is not None:
        return _render_view_fast(world, light, centre, r_opt2world, cam, t_max, t_min, rel_step,
                                 min_step, need_depth)
    return render_view_numpy(world, light, centre, r_opt2world, cam, t_max, t_min, rel_step,
                             min_step)


def _column_intervals(world: World, C, yaw, a, t, t_min, t_max, idx):
    """(n, Wv, 2) int32 [j0, j1) sample intervals of each obstacle in ``idx`` per column."""
    Wv = a.shape[0]
    f2 = np.array([math.cos(yaw), math.sin(yaw)])
    r2 = np.array([math.sin(yaw), -math.cos(yaw)])
    out = np.zeros((len(idx), Wv, 2), np.int32)
    nrm = np.sqrt(1 + a * a)
    for i, k in enumerate(idx):
        o = world.obstacles[k]
        q = np.array([o.x - C[0], o.y - C[1]])
        qf, qr = float(q @ f2), float(q @ r2)
        R = o.radius
        near = np.abs(qr - a * qf) <= R * nrm
        if not near.any():
            continue
        tc = (qf + a * qr) / (1 + a * a)
        lo = tc - R / nrm
        hi = tc + R / nrm
        j0 = np.searchsorted(t, lo, "left")
        j1 = np.searchsorted(t, hi, "right")
        out[i, :, 0] = np.where(near, j0, 0)
        out[i, :, 1] = np.where(near, j1, 0)
    return out


def _render_view_fast(world, light, centre, r_opt2world, cam, t_max, t_min, rel_step, min_step,
                      need_depth):
    from . import fastrender as fr
    _T = _Timer()
    C = np.asarray(centre, np.float64)
    yaw, M, Kinv, Wv, Hv, cxv, cyv = _virtual_camera(cam, r_opt2world)
    fx, fy = float(cam.fx), float(cam.fy)
    t = march_steps(float(t_min), float(t_max), float(rel_step), float(min_step)).astype(np.float64)
    S = t.shape[0]
    kp = world.kernel_params()
    f2x, f2y = math.cos(yaw), math.sin(yaw)
    r2x, r2y = math.sin(yaw), -math.cos(yaw)
    a = (np.arange(Wv, dtype=np.float64) - cxv) / fx
    # obstacles that can show: in front, within range
    idx = []
    for k, o in enumerate(world.obstacles):
        qf = (o.x - C[0]) * f2x + (o.y - C[1]) * f2y
        if qf + o.radius < t_min or math.hypot(o.x - C[0], o.y - C[1]) - o.radius > t_max:
            continue
        idx.append(k)
    obs = world.obstacle_rows(idx)
    ocols = _column_intervals(world, C, yaw, a, t, t_min, t_max, idx)
    h = np.empty((Wv, S), np.float32)
    mat = np.empty((Wv, S), np.int16)
    jhit = np.empty((Wv, Hv), np.int32)                 # transposed: [column, row]
    Kv = np.array([[fx, 0, cxv], [0, fy, cyv], [0, 0, 1.0]])
    Hm = Kv @ M @ Kinv                                  # real pixel -> virtual pixel
    Hr = np.linalg.inv(Hm)                              # virtual pixel -> real pixel
    # the topmost virtual row each virtual column must have (from the real image's border)
    W_, H_ = cam.width, cam.height
    bu = np.concatenate([np.arange(-2.0, W_ + 2.0), np.full(H_ + 4, W_ + 1.0),
                         np.arange(-2.0, W_ + 2.0), np.full(H_ + 4, -2.0)])
    bv = np.concatenate([np.full(W_ + 4, -2.0), np.arange(-2.0, H_ + 2.0),
                         np.full(W_ + 4, H_ + 1.0), np.arange(-2.0, H_ + 2.0)])
    pb = Hm @ np.vstack([bu, bv, np.ones_like(bu)])
    pcol = np.clip(np.round(pb[0] / pb[2]).astype(np.int64), 0, Wv - 1)
    rmin = np.full(Wv, Hv, np.int64)
    np.minimum.at(rmin, pcol, np.floor(pb[1] / pb[2]).astype(np.int64) - 2)
    # (the border is sampled every real pixel: a column it skips takes its neighbours' row)
    rmin = np.minimum(rmin, np.minimum(np.roll(rmin, 1), np.roll(rmin, -1)))
    _T("0")
    fr.march(kp["kind"], kp["G"], kp["gp"], kp["tp"], kp["bp"], kp["tile77"], kp["top_m"], obs,
             ocols, C, f2x, f2y, r2x, r2y, fx, fy, cxv, cyv, Wv, Hv, t, h, mat, jhit, rmin)
    _T("march")
    mode = {"day": 0, "night-strobe": 1}.get(light.mode, 2)
    sun = np.asarray(light.sun, np.float64)
    # obstacles whose shadow can fall in view: (x, y, r, top, reach)
    sh = []
    horiz = math.hypot(sun[0], sun[1])
    if mode == 0 and horiz > 1e-6:
        tan_e = sun[2] / horiz
        for o in world.obstacles:
            r = 0.5 * min(o.length_m, o.width_m) if o.shape != "vehicle" else 0.42 * o.width_m + 0.3
            top = o.z0 + o.height_m
            reach = (top - (o.z0 - 0.3)) / tan_e + r
            if math.hypot(o.x - C[0], o.y - C[1]) - reach - r > t_max:
                continue
            sh.append((o.x, o.y, r, top, reach))
    sh = np.array(sh, np.float64).reshape(-1, 5)
    light_p = np.array([light.strobe_power, light.cloud, light.dusk, light.wind_mps[0],
                        light.wind_mps[1], world.time_s, CLOUD_CELL_M], np.float64)
    img = np.empty((Wv, Hv, 3), np.float32)             # transposed: [column, row]
    dshape = (Wv, Hv) if need_depth else (1, 1)
    tv = np.empty(dshape, np.float32)
    mv = np.empty(dshape, np.float32)
    lum = np.empty(dshape, np.float32)
    fr.shade(kp["kind"], kp["G"], kp["gp"], kp["tp"], kp["bp"], kp["tile77"], obs, kp["salt"], C,
             f2x, f2y, r2x, r2y, fx, fy, cxv, cyv, Wv, Hv, t, h, mat, jhit, mode, sun, light_p,
             kp["grass"], kp["gravel"], kp["sizes"], kp["offsets"], kp["tiles"],
             np.asarray(world.sky_bgr, np.float64), np.asarray(world.horizon_bgr, np.float64),
             img, tv, mv, lum, sh, Hr, float(W_), float(H_), bool(need_depth))
    _T("shade")
    Hm = np.array([[0, 1, 0], [1, 0, 0], [0, 0, 1.0]]) @ Hm     # the buffers are transposed
    dsize = (cam.width, cam.height)
    flags_lin = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    flags_nn = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    out = cv2.warpPerspective(img, Hm, dsize, flags=flags_lin, borderMode=cv2.BORDER_REPLICATE)
    if not need_depth:
        _T("warp")
        return View(out, None, None, None)
    tw = cv2.warpPerspective(tv, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    mw = cv2.warpPerspective(mv, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    lw = cv2.warpPerspective(lum, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    uu = (np.arange(cam.width, dtype=np.float32) - np.float32(cam.cx)) / np.float32(cam.fx)
    ww = (np.arange(cam.height, dtype=np.float32) - np.float32(cam.cy)) / np.float32(cam.fy)
    denom = np.float32(M[2, 0]) * uu[None, :] + np.float32(M[2, 1]) * ww[:, None] + np.float32(M[2, 2])
    z = tw / denom
    _T("warp")
    return View(out, z.astype(np.float32), mw.astype(np.int16), lw)


def render_view_numpy(world: World, light: Lighting, centre: np.ndarray, r_opt2world: np.ndarray,
                      cam: Intrinsics, t_max: float = 80.0, t_min: float = 0.3,
                      rel_step: float = 0.004, min_step: float = 0.01) -> View:
    """The whole-array numpy renderer (the reference the compiled loops follow)."""
    f32 = np.float32
    _T = _Timer()
    C = np.asarray(centre, np.float64)
    fwd = r_opt2world[:, 2]
    yaw = math.atan2(fwd[1], fwd[0])
    Rv = _level_basis(yaw)
    M = Rv.T @ r_opt2world                       # real optical -> virtual optical
    K = cam.matrix()
    Kinv = np.linalg.inv(K)
    # bounds of the real image in the virtual (level) image plane
    n = 24
    us = np.linspace(-0.5, cam.width - 0.5, n)
    vs = np.linspace(-0.5, cam.height - 0.5, n)
    border = np.concatenate([np.stack([us, np.full(n, vs[0])], 1), np.stack([us, np.full(n, vs[-1])], 1),
                             np.stack([np.full(n, us[0]), vs], 1), np.stack([np.full(n, us[-1]), vs], 1)])
    rays = M @ (Kinv @ np.vstack([border.T, np.ones(len(border))]))
    if np.any(rays[2] <= 0.05):
        raise ValueError("camera looks too far up or down for the level-camera renderer")
    pu = cam.fx * rays[0] / rays[2]
    pv = cam.fy * rays[1] / rays[2]
    u0, u1 = math.floor(pu.min()) - 2, math.ceil(pu.max()) + 2
    v0, v1 = math.floor(pv.min()) - 2, math.ceil(pv.max()) + 2
    Wv, Hv = u1 - u0 + 1, v1 - v0 + 1
    cxv, cyv = float(-u0), float(-v0)
    fx, fy = cam.fx, cam.fy

    # ---- the march: (columns, steps) grid of sample points --------------------------------
    t = march_steps(float(t_min), float(t_max), float(rel_step), float(min_step))
    S = t.shape[0]
    a = ((np.arange(Wv, dtype=np.float64) - cxv) / fx)
    f2 = np.array([math.cos(yaw), math.sin(yaw)])
    r2 = np.array([math.sin(yaw), -math.cos(yaw)])
    dx = (f2[0] + a * r2[0]).astype(f32)
    dy = (f2[1] + a * r2[1]).astype(f32)
    X = f32(C[0]) + dx[:, None] * t[None, :]
    Y = f32(C[1]) + dy[:, None] * t[None, :]
    _T("0")
    h, mat = world.terrain(X, Y)
    h = np.ascontiguousarray(h, dtype=f32)
    for k, o in enumerate(world.obstacles):
        q = np.array([o.x - C[0], o.y - C[1]])
        qf, qr = float(q @ f2), float(q @ r2)
        R = o.radius
        if qf + R < t_min or math.hypot(qf, qr) - R > t_max:
            continue
        nrm = np.sqrt(1 + a * a)
        near = np.abs(qr - a * qf) <= R * nrm
        if not near.any():
            continue
        cols = np.nonzero(near)[0]
        c0, c1 = cols[0], cols[-1] + 1
        tc = (qf + a[c0:c1] * qr) / (1 + a[c0:c1] ** 2)
        lo = float((tc - R / nrm[c0:c1]).min())
        hi = float((tc + R / nrm[c0:c1]).max())
        j0 = int(np.searchsorted(t, lo, "left"))
        j1 = int(np.searchsorted(t, hi, "right"))
        if j1 <= j0:
            continue
        xb, yb = X[c0:c1, j0:j1], Y[c0:c1, j0:j1]
        hoff = o.height(xb, yb)
        ho = hoff + f32(o.z0)
        hb = h[c0:c1, j0:j1]
        up = (hoff > 0) & (ho >= hb)
        hb[up] = ho[up]
        mat[c0:c1, j0:j1][up] = MAT_OBSTACLE + k

    _T("1")
    rows = f32(cyv) - f32(fy) * (h - f32(C[2])) / t[None, :]
    cm = np.minimum.accumulate(rows, axis=1)
    # pixel row r sees the first sample with cm <= r: j(r) = #{j : ceil(cm_j) > r}
    cmi = np.clip(np.ceil(cm), 0, Hv).astype(np.int64)
    hist = np.bincount((np.arange(Wv, dtype=np.int64)[:, None] * (Hv + 1) + cmi).ravel(),
                       minlength=Wv * (Hv + 1)).reshape(Wv, Hv + 1)
    jhit = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]      # (Wv, Hv): count of cmi > r
    # transpose to image layout (Hv, Wv)
    jhit = np.ascontiguousarray(jhit.T)
    _T("2")
    hitm = jhit < S
    vv, cc = np.nonzero(hitm)
    jj = jhit[vv, cc]
    jp = np.maximum(jj - 1, 0)
    tj = t[jj]
    tp = t[jp]
    hflat = h.ravel()
    base = cc * S
    hj = hflat[base + jj]
    hp = hflat[base + jp]
    slope = (vv.astype(f32) - f32(cyv)) / f32(fy)             # ray z = Cz - slope * t
    zr_j = f32(C[2]) - slope * tj
    zr_p = f32(C[2]) - slope * tp
    side = (zr_p < hj - (f32(0.01) + f32(0.002) * tj)) & (jj > 0)
    fj = hj - zr_j
    fp = hp - zr_p
    den = fj - fp
    frac = np.where(np.abs(den) > 1e-6, -fp / np.where(np.abs(den) > 1e-6, den, 1), 1.0)
    frac = np.clip(frac, 0, 1)
    frac = np.where(side, f32(0.5), frac).astype(f32)
    frac = np.where(jj == 0, f32(0.0), frac)
    th = tp + frac * (tj - tp)
    px = f32(C[0]) + dx[cc] * th
    py = f32(C[1]) + dy[cc] * th
    pz = f32(C[2]) - slope * th
    pm = mat.ravel()[base + jj]

    _T("3")
    # ---- appearance at the hit points ------------------------------------------------------
    footprint = th * np.sqrt(1 + a[cc].astype(f32) ** 2 + slope * slope) / f32(fx)
    _T("4")
    alb = world.albedo(px, py, pz, pm, footprint)
    # normals: top surfaces from the height grid, sides horizontal
    nx = np.zeros(px.shape, f32)
    ny = np.zeros(px.shape, f32)
    nz = np.ones(px.shape, f32)
    top = ~side & (jj > 0)
    if top.any():
        ct, jt = cc[top], jj[top]
        dt = t[jt] - t[jt - 1]
        hT = hj[top]
        dhA = (hT - hp[top]) / dt
        cn = np.minimum(ct + 1, Wv - 1)
        cn = np.where(cn == ct, ct - 1, cn)
        dhB = (hflat[cn * S + jt] - hT) * (cn - ct) / (t[jt] / f32(fx))
        at = a[ct].astype(f32)
        gr = dhB
        gf = dhA - at * gr
        gx = gf * f32(f2[0]) + gr * f32(r2[0])
        gy = gf * f32(f2[1]) + gr * f32(r2[1])
        # clamp: grid differences across a tuft edge are not a surface slope
        g = np.sqrt(gx * gx + gy * gy)
        s = np.minimum(f32(1.0), f32(3.0) / np.maximum(g, f32(1e-6)))
        nx[top], ny[top] = -gx * s, -gy * s
    if side.any():
        si = np.nonzero(side)[0]
        # default: facing the camera, tilted by a hash so stubble sides are not flat
        ddx, ddy = -dx[cc[si]], -dy[cc[si]]
        dn = np.sqrt(ddx * ddx + ddy * ddy)
        sx, sy = ddx / dn, ddy / dn
        ang = (np.sin(px[si] * 91.7 + py[si] * 53.3) * 0.8).astype(f32)
        ca, sa = np.cos(ang), np.sin(ang)
        sx, sy = sx * ca - sy * sa, sx * sa + sy * ca
        sm = pm[si]
        for k, o in enumerate(world.obstacles):
            m = sm == MAT_OBSTACLE + k
            if m.any():
                ox, oy = o.side_normal(px[si][m], py[si][m])
                sx[m], sy[m] = ox, oy
        nx[si], ny[si], nz[si] = sx, sy, f32(0.0)
    _T("5")
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nn, ny / nn, nz / nn

    if light.mode == "day":
        sun = np.asarray(light.sun, f32)
        lam = np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
        lit = _shadows(world, sun, px, py, pz, pm)
        if light.cloud > 0 or light.dusk > 0:
            lit = lit * _cloud_light(world, light, px, py)
            direct = (f32(0.75) * lam * lit)[:, None] * _dusk_tint(light.dusk)[None, :]
            rad = alb * (f32(0.42 + 0.08 * light.cloud) * f32(1 - 0.5 * light.dusk) + direct)
        else:
            shade = f32(0.42) + f32(0.75) * lam * lit
            rad = alb * shade[:, None]
    elif light.mode == "night-strobe":
        lx, ly, lz = f32(C[0]) - px, f32(C[1]) - py, f32(C[2]) - pz
        r2_ = lx * lx + ly * ly + lz * lz
        rr = np.sqrt(r2_)
        lam = np.maximum((nx * lx + ny * ly + nz * lz) / rr, f32(0.08))
        rad = alb * (f32(light.strobe_power) * lam / r2_)[:, None]
        rad = rad / (1 + rad) * f32(1.25)                       # soft saturation of the near field
    else:  # greenhouse: diffuse light through the cover
        shade = f32(0.6) + f32(0.4) * nz + f32(0.15) * np.abs(nx)
        rad = alb * shade[:, None]

    _T("6")
    img = np.empty((Hv, Wv, 3), f32)
    if light.mode == "night-strobe":
        img[:] = 0.0
    else:
        # sky: horizon colour blending into the sky colour with elevation
        el = np.clip((cyv - np.arange(Hv, dtype=f32)) / f32(fy), 0, None)
        w = np.clip(el / 0.35, 0, 1)[:, None]
        sky = (np.asarray(world.horizon_bgr, f32)[None, :] * (1 - w) +
               np.asarray(world.sky_bgr, f32)[None, :] * w)
        img[:] = sky[:, None, :]
    img[hitm] = rad                     # boolean order == np.nonzero order (row-major)
    tv = np.zeros((Hv, Wv), f32)
    tv[hitm] = th
    mv = np.full((Hv, Wv), MAT_SKY, np.float32)
    mv[hitm] = pm
    lum = np.zeros((Hv, Wv), f32)
    lum[hitm] = alb @ np.array([0.114, 0.587, 0.299], f32)

    _T("7")
    # ---- warp to the real camera -----------------------------------------------------------
    Kv = np.array([[fx, 0, cxv], [0, fy, cyv], [0, 0, 1.0]])
    Hm = Kv @ M @ Kinv                                  # real pixel -> virtual pixel
    dsize = (cam.width, cam.height)
    flags_lin = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    flags_nn = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    out = cv2.warpPerspective(img, Hm, dsize, flags=flags_lin, borderMode=cv2.BORDER_REPLICATE)
    tw = cv2.warpPerspective(tv, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    mw = cv2.warpPerspective(mv, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    lw = cv2.warpPerspective(lum, Hm, dsize, flags=flags_nn, borderMode=cv2.BORDER_REPLICATE)
    _T("8")
    uu = (np.arange(cam.width, dtype=f32) - f32(cam.cx)) / f32(cam.fx)
    ww = (np.arange(cam.height, dtype=f32) - f32(cam.cy)) / f32(cam.fy)
    denom = f32(M[2, 0]) * uu[None, :] + f32(M[2, 1]) * ww[:, None] + f32(M[2, 2])
    z = tw / denom
    _T("end")
    return View(out, z.astype(f32), mw.astype(np.int16), lw)


CLOUD_CELL_M = 35.0        # size of the cloud shadows' pattern


def _cloud_light(world: World, light: Lighting, px, py) -> np.ndarray:
    """The share of direct sun that gets through the clouds at ground points: drifting cloud
    shadows (value noise moved by the wind with the world's clock) thinned by the cover."""
    from .world import value_noise
    f32 = np.float32
    if light.cloud <= 0:
        return np.ones(px.shape, f32)
    t = f32(world.time_s)
    n = value_noise(px - f32(light.wind_mps[0]) * t, py - f32(light.wind_mps[1]) * t,
                    CLOUD_CELL_M, world._salt ^ 0xC10D)
    shadow = np.clip((n - f32(1.0 - light.cloud)) * f32(5.0), 0, 1)
    return (f32(1.0) - f32(0.85) * shadow).astype(f32)


def _dusk_tint(dusk: float) -> np.ndarray:
    """BGR multiplier of the direct sun: dimmer and warmer towards dusk."""
    return np.array([1 - 0.75 * dusk, 1 - 0.5 * dusk, 1 - 0.3 * dusk], np.float32)


def _shadows(world: World, sun: np.ndarray, px, py, pz, pm) -> np.ndarray:
    """1 where the sun reaches a point, 0 in an obstacle's shadow (obstacles as upright
    cylinders of their footprint's size; stubble self-shadowing is left out)."""
    lit = np.ones(px.shape, np.float32)
    if not world.obstacles:
        return lit
    horiz = math.hypot(sun[0], sun[1])
    if horiz < 1e-6:
        return lit
    ux, uy = sun[0] / horiz, sun[1] / horiz
    tan_e = sun[2] / horiz
    ground = pm < MAT_OBSTACLE
    for k, o in enumerate(world.obstacles):
        r = 0.5 * min(o.length_m, o.width_m) if o.shape != "vehicle" else 0.42 * o.width_m + 0.3
        top = o.z0 + o.height_m
        reach = (top - (o.z0 - 0.3)) / tan_e + r
        # cheap bounding test first
        ddx = np.float32(o.x) - px
        ddy = np.float32(o.y) - py
        s = ddx * np.float32(ux) + ddy * np.float32(uy)
        perp = np.abs(ddx * np.float32(uy) - ddy * np.float32(ux))
        m = ground & (perp < r) & (s > -r) & (s < reach)
        if not m.any():
            continue
        s_in = np.maximum(s[m] - np.sqrt(np.maximum(r * r - perp[m] ** 2, 0)), 0)
        shadow = pz[m] + s_in * np.float32(tan_e) < np.float32(top)
        lm = lit[m]
        lm[shadow] = 0.0
        lit[m] = lm
    return lit


# ---------------------------------------------------------------------------------------------
# sensor models
# ---------------------------------------------------------------------------------------------
_NOISE_POOL: dict = {}


def _noise(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """(h, w, 3) float32 unit Gaussian noise: a window at a random offset of a fixed, seeded pool
    (generating 4 M normals per image costs more than the rest of the exposure)."""
    key = (h, w)
    pool = _NOISE_POOL.get(key)
    if pool is None:
        pool = np.random.default_rng(12345).standard_normal((h + 97, w + 89, 3), dtype=np.float32)
        _NOISE_POOL[key] = pool
    dy, dx = int(rng.integers(0, 97)), int(rng.integers(0, 89))
    n = pool[dy:dy + h, dx:dx + w]
    return n[:, :, ::-1] if rng.integers(0, 2) else n


def expose(radiance: np.ndarray, rng: np.random.Generator, mode: str) -> np.ndarray:
    """Radiance -> 8-bit BGR with sensor noise (more at night: gain up, shot noise)."""
    if ENGINE == "numba":
        from . import fastrender as fr
        h, w = radiance.shape[:2]
        key = (h, w)
        pool = _NOISE_POOL.get(key)
        if pool is None:
            pool = np.random.default_rng(12345).standard_normal((h + 97, w + 89, 3),
                                                                dtype=np.float32)
            _NOISE_POOL[key] = pool
        dy, dx = int(rng.integers(0, 97)), int(rng.integers(0, 89))
        flip = bool(rng.integers(0, 2))
        if flip:
            # the channel-reversed pool as its own contiguous array (cached), so the kernel
            # reads every row straight through and vectorises (0.75 instead of 5.3 ms a
            # 640x512 image, the same bytes)
            fkey = (h, w, "flipped")
            pf = _NOISE_POOL.get(fkey)
            if pf is None:
                pf = np.ascontiguousarray(pool[:, :, ::-1])
                _NOISE_POOL[fkey] = pf
            pool = pf
        out = np.empty((h, w, 3), np.uint8)
        fr.expose(np.ascontiguousarray(radiance, np.float32), pool, dy, dx,
                  mode == "night-strobe", out)
        return out
    x = radiance * np.float32(255.0)
    h, w = x.shape[:2]
    if mode == "night-strobe":
        sigma = np.float32(4.0) + np.sqrt(np.maximum(x, 0)) * np.float32(0.6)
    else:
        sigma = np.float32(1.2) + np.sqrt(np.maximum(x, 0)) * np.float32(0.12)
    x += sigma * _noise(rng, h, w)
    x += np.float32(0.5)
    return np.clip(x, 0, 255).astype(np.uint8)


def kinect_depth(view: View, world: World, rng: np.random.Generator, min_range: float,
                 max_range: float, fx: float) -> np.ndarray:
    """Kinect-class z-depth: noise growing with z², disparity-like quantisation, holes (0) at
    depth discontinuities, on dark and shiny surfaces, and outside the working range."""
    if ENGINE == "numba":
        return _kinect_depth_fast(view, world, rng, min_range, max_range, fx)
    z = view.zdepth.astype(np.float32).copy()
    valid = (z >= min_range) & (z <= max_range)
    # quantisation of a structured-light disparity (1/8 px of a 7.5 cm baseline)
    bf = np.float32(0.075 * fx * 8)
    zq = np.where(valid, bf / np.round(bf / np.maximum(z, 1e-3)), 0).astype(np.float32)
    zq += rng.standard_normal(z.shape, dtype=np.float32) * np.float32(1.5e-3) * zq * zq
    # discontinuities: neighbours differing by more than a few % of the depth
    zmax = cv2.dilate(z, np.ones((3, 3), np.uint8))
    zmin = cv2.erode(z, np.ones((3, 3), np.uint8))
    edge = (zmax - zmin) > np.float32(0.04) * np.maximum(zmin, 0.5)
    # the projector-camera shadow is wider on one side: grow the edge mask to the left
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 5), np.uint8), anchor=(3, 1)) > 0
    dark = view.albedo_lum < np.float32(0.06)
    shiny = world.is_shiny(view.mat)
    speckle = rng.random(z.shape, dtype=np.float32)
    holes = edge | shiny | (dark & (speckle < 0.8)) | (speckle < 0.002)
    zq[holes | ~valid] = 0.0
    return zq


_DEPTH_POOL: dict = {}


def _kinect_depth_fast(view, world, rng, min_range, max_range, fx):
    """kinect_depth with the per-pixel work compiled and the noise read from seeded pools at a
    random window (as the colour noise is)."""
    from . import fastrender as fr
    z = np.ascontiguousarray(view.zdepth, np.float32)
    h, w = z.shape
    pools = _DEPTH_POOL.get((h, w))
    if pools is None:
        g = np.random.default_rng(54321)
        pools = (g.standard_normal((h + 61, w + 67), dtype=np.float32),
                 g.random((h + 61, w + 67), dtype=np.float32))
        _DEPTH_POOL[(h, w)] = pools
    dy, dx = int(rng.integers(0, 61)), int(rng.integers(0, 67))
    zmax = cv2.dilate(z, np.ones((3, 3), np.uint8))
    zmin = cv2.erode(z, np.ones((3, 3), np.uint8))
    edge = (zmax - zmin) > np.float32(0.04) * np.maximum(zmin, 0.5)
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 5), np.uint8), anchor=(3, 1))
    shiny = np.zeros(MAT_OBSTACLE + len(world.obstacles) + 1, np.bool_)
    for k, o in enumerate(world.obstacles):
        if o.shiny:
            shiny[MAT_OBSTACLE + k + 1] = True
    out = np.empty((h, w), np.float32)
    fr.kinect(z, np.ascontiguousarray(view.albedo_lum, np.float32),
              np.ascontiguousarray(view.mat, np.int16), edge, shiny, pools[0], pools[1], dy, dx,
              float(np.float32(0.075 * fx * 8)), float(min_range), float(max_range), out)
    return out


@lru_cache(maxsize=16)
def _laser_steps(range_max: float, step_min: float, rel_step: float,
                 step_max: float) -> np.ndarray:
    """The laser's sample depths (float32; read-only, cached: the schedule was rebuilt in a
    Python loop of ~1600 steps for every scan, ~5 ms of a 640x512 cycle)."""
    if not step_max:
        t = march_steps(0.05, range_max, rel_step, step_min).copy()
    else:
        # cap the step far out (the generic schedule grows without limit)
        ts = [0.05]
        while ts[-1] < range_max:
            ts.append(ts[-1] + min(max(step_min, rel_step * ts[-1]), step_max))
        t = np.array(ts[:-1], np.float32)
    t.setflags(write=False)
    return t


def cast_laser(world: World, origin: np.ndarray, dirs: np.ndarray, range_max: float,
               step_min: float = 0.01, rel_step: float = 0.004, step_max: float = 0.04) -> np.ndarray:
    """Ranges (NaN = no return) of beams from ``origin`` along unit ``dirs`` (N, 3), world."""
    f32 = np.float32
    t = _laser_steps(float(range_max), float(step_min), float(rel_step), float(step_max))
    N = dirs.shape[0]
    O = np.asarray(origin, np.float64)
    if ENGINE == "numba" and world.extent is not None:
        from . import fastrender as fr
        kp = world.kernel_params()
        out = np.empty(N, np.float32)
        fr.laser(kp["kind"], kp["G"], kp["gp"], kp["tp"], kp["bp"], kp["tile77"],
                 float(world.max_terrain_m), world.obstacle_rows(), O,
                 np.ascontiguousarray(dirs, np.float64), t.astype(np.float64), float(range_max),
                 kp["Gc"], float(kp["top_m"]), out)
        return out
    zr = (f32(O[2]) + dirs[:, 2:3].astype(f32) * t[None, :])
    # terrain can only be touched where the beam is below the highest terrain
    cand = zr <= f32(world.max_terrain_m)
    hit_t = np.full(N, np.inf, np.float64)
    if cand.any():
        bi, si = np.nonzero(cand)
        x = f32(O[0]) + dirs[bi, 0].astype(f32) * t[si]
        y = f32(O[1]) + dirs[bi, 1].astype(f32) * t[si]
        h, _ = world.terrain(x, y)
        hit = h >= zr[bi, si]
        if hit.any():
            # first hit per beam: si grows within a beam (np.nonzero is row-major)
            hb, hs = bi[hit], si[hit]
            first = np.ones(hb.shape, bool)
            first[1:] = hb[1:] != hb[:-1]
            hit_t[hb[first]] = t[hs[first]]
    # obstacles: exact 2-D ray/footprint test by marching only the beams that pass near
    for o in world.obstacles:
        qx, qy = o.x - O[0], o.y - O[1]
        dxy = np.hypot(dirs[:, 0], dirs[:, 1])
        ux, uy = dirs[:, 0] / np.maximum(dxy, 1e-9), dirs[:, 1] / np.maximum(dxy, 1e-9)
        along = qx * ux + qy * uy
        perp = np.abs(qx * uy - qy * ux)
        R = o.radius
        near = (perp <= R) & (along + R > 0) & (along - R < range_max)
        if not near.any():
            continue
        for b in np.nonzero(near)[0]:
            s0 = max(along[b] - R, 0.0)
            s1 = along[b] + R
            ss = np.arange(s0, s1, 0.005, dtype=np.float64)
            tt = ss / dxy[b]
            px, py, pz = O[0] + dirs[b, 0] * tt, O[1] + dirs[b, 1] * tt, O[2] + dirs[b, 2] * tt
            ho = o.height(px.astype(f32), py.astype(f32))
            inside = (ho > 0) & (pz <= ho + o.z0) & (pz >= o.z0 - 0.5)
            if inside.any():
                tb = float(tt[np.argmax(inside)])
                if tb < hit_t[b]:
                    hit_t[b] = tb
    out = np.where(hit_t <= range_max, hit_t, np.nan).astype(np.float32)
    return out
