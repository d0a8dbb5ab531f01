"""The renderer's inner loops compiled with numba (the same algorithm as render.py's numpy code,
per column and per pixel instead of whole arrays, with work skipped where it cannot show).

- the march (per virtual column, front to back): terrain height at each sample (ground from the
  world's ground grid, stubble tufts or bushes by the same integer hashes as world.py), obstacles
  where their interval of samples lies, the row each sample projects to, the running minimum of
  those rows (the y-buffer) and, for each pixel row, the first sample that covers it. A sample
  whose highest possible top (ground + the tallest tuft/bush) projects below the running minimum
  cannot be seen: its stubble is not evaluated at all.
- the hit (per pixel): the crossing between the sample before and the sample that covers the
  row, interpolated as render.py does (side hits at mid-step), the normal from the height
  differences, the albedo by material (textures with mip levels, value noise, peppers,
  obstacle colours), the lighting (sun + obstacle shadows + cloud shadows, strobe, diffuse).
- the laser (per beam): first terrain hit with an early exit, obstacles marched only where the
  beam passes near them.
- the exposure: radiance to 8-bit with the noise pool.

Everything here is a pure function of arrays the world hands over (``world.kernel_params()``);
world.py stays the one definition of the scene (its numpy functions give the same heights).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

M32 = 0xFFFFFFFF
# fast-math without "no NaNs / no infs": NaN marks a sample the march did not evaluate
FM = {"arcp", "contract", "afn", "reassoc", "nsz"}
NO_HIT = 1 << 30
# the per-pixel / per-sample kernels run without numba's reference counting (NRT): with it, every
# inlined helper that takes an array increfs and decrefs it (an atomic op and a call each) on
# every call, which cost ~45 % of the shading's time (perf, 2026-12-02). They allocate nothing;
# their callers (with NRT) allocate the scratch arrays.
NO_NRT = dict(cache=True, error_model="numpy", fastmath=FM, _nrt=False)

# obstacle parameter rows (float64): see world.World.kernel_params
OX, OY, OC, OS, OL, OW, OH, OZ0, OSHAPE, OR, OTEX, OC1B, OC1G, OC1R, OC2B, OC2G, OC2R, OCLS = range(18)
SH_CYL, SH_BOX, SH_VEH, SH_PERSON, SH_CROUCH, SH_DOME = range(6)
CL_OTHER, CL_DRUM, CL_CRATE = range(3)


# ---------------------------------------------------------------------------------------------
# hashing / noise / textures (bit-identical to world.py's integer hashes)
# ---------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def mix32(h):
    h &= M32
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & M32
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & M32
    h ^= h >> 16
    return h


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def hash2(i, j, salt):
    a = np.int64(i) & M32
    b = np.int64(j) & M32
    h = ((a * 0x9E3779B1) & M32) ^ ((b * 0x85EBCA77 + salt) & M32)
    return mix32(h)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def unit(h, k):
    if k:
        h = mix32(h + ((k * 0x27D4EB2F) & M32))
    return (h >> 8) * (1.0 / (1 << 24))


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def value_noise(tile, x, y, cell):
    fx = x / cell
    fy = y / cell
    ix = math.floor(fx)
    iy = math.floor(fy)
    tx = fx - ix
    ty = fy - iy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    i0 = (iy & 511) * 513 + (ix & 511)
    v00 = tile[i0]
    v10 = tile[i0 + 1]
    v01 = tile[i0 + 514]
    v11 = tile[i0 + 515]
    a = v00 + (v10 - v00) * tx
    b = v01 + (v11 - v01) * tx
    return a + (b - a) * ty


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def value_noise_k(tiles, k, x, y, cell):
    """value_noise on tile ``tiles[k]``, read in place (no row view: see obstacle_height)."""
    fx = x / cell
    fy = y / cell
    ix = math.floor(fx)
    iy = math.floor(fy)
    tx = fx - ix
    ty = fy - iy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    i0 = (iy & 511) * 513 + (ix & 511)
    v00 = tiles[k, i0]
    v10 = tiles[k, i0 + 1]
    v01 = tiles[k, i0 + 514]
    v11 = tiles[k, i0 + 515]
    a = v00 + (v10 - v00) * tx
    b = v01 + (v11 - v01) * tx
    return a + (b - a) * ty


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def texture(flat, sizes, offsets, u_m, v_m, mpt, footprint):
    """Nearest texel at the mip level of the footprint (world.sample_texture): level
    floor(log2(footprint / mpt) + 0.5), i.e. the number of thresholds sqrt(2) * 2^k * mpt the
    footprint exceeds, counted with the texel scale halved on the way (no frexp, no division:
    ``mpt`` is a literal at every call, so the start values fold to constants)."""
    nl = sizes.shape[0] - 1
    lev = 0
    th = 1.4142135 * mpt
    sc = 1.0 / mpt
    while lev < nl and footprint > th:
        lev += 1
        th *= 2.0
        sc *= 0.5
    n = sizes[lev]
    iu = int(math.floor(u_m * sc)) & (n - 1)
    iv = int(math.floor(v_m * sc)) & (n - 1)
    return flat[offsets[lev] + iv * n + iu]


# ---------------------------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def grid_pos(gp, x, y):
    """(x, y) as fractional node coordinates of the ground grid gp = (x0, y0, 1/cell, nx, ny),
    clamped inside it: (fx, fy, nx)."""
    fx = (x - gp[0]) * gp[2]
    fy = (y - gp[1]) * gp[2]
    nx = int(gp[3])
    ny = int(gp[4])
    if fx < 0.0:
        fx = 0.0
    elif fx > nx - 1.000001:
        fx = nx - 1.000001
    if fy < 0.0:
        fy = 0.0
    elif fy > ny - 1.000001:
        fy = ny - 1.000001
    return fx, fy, nx


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def ground(G, gp, x, y):
    """Bilinear ground grid: gp = (x0, y0, 1/cell, nx, ny)."""
    fx, fy, nx = grid_pos(gp, x, y)
    ix = int(fx)
    iy = int(fy)
    tx = fx - ix
    ty = fy - iy
    i0 = iy * nx + ix
    a = G[i0] + (G[i0 + 1] - G[i0]) * tx
    b = G[i0 + nx] + (G[i0 + nx + 1] - G[i0 + nx]) * tx
    return a + (b - a) * ty


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def tuft_cell(tp, kf, jf, cy0):
    """The tuft of row kf, place jf: (hash, centre x, centre y, radius)."""
    ts = tp[2]
    h = hash2(kf, jf, np.int64(tp[3]))
    cx = (jf + 0.5) * ts + (unit(h, 1) - 0.5) * 0.05
    cy = cy0 + (unit(h, 2) - 0.5) * 0.08
    r = 0.045 + unit(h, 3) * 0.04
    return h, cx, cy, r


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def tuft_top(tp, h, x, y, d2):
    """The tuft's height at a point inside its disc (d2 < 1); 0 where the row has a gap."""
    u4 = unit(h, 4)
    if u4 < tp[6]:
        return 0.0
    height = 0.14 + 0.26 * unit(h, 0)
    if u4 > 0.92:
        height += 0.12
    height *= tp[5]
    rag = unit(hash2(math.floor(x * 50.0), math.floor(y * 50.0), np.int64(tp[4])), 0)
    return height * math.sqrt(math.sqrt(1.0 - d2)) * (0.55 + 0.45 * rag)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def tuft(tp, x, y):
    """Stubble tuft height above the ground (world._tufts). tp = (row_off, row_spacing,
    tuft_spacing, salt51, salt5A, height_scale, gap)."""
    row_off, rs, ts = tp[0], tp[1], tp[2]
    kf = math.floor((y - row_off) / rs + 0.5)
    cy0 = kf * rs + row_off
    if abs(y - cy0) > 0.1265:                    # jitter 0.04 + largest radius 0.085
        return 0.0
    jf = math.floor(x / ts)
    h, cx, cy, r = tuft_cell(tp, kf, jf, cy0)
    d2 = ((x - cx) ** 2 + (y - cy) ** 2) / (r * r)
    if d2 >= 1.0:
        return 0.0
    return tuft_top(tp, h, x, y, d2)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def bushes(bp, tile77, x, y):
    """Greenhouse (world._bushes): (bush height, leaf height). bp = (path_half_width, period,
    saltB5, salt1EAF, x_lo, x_hi)."""
    hw, P = bp[0], bp[1]
    if x < bp[4] or x > bp[5]:
        return 0.0, 0.0
    yy = y - (hw + 0.5)
    kk = math.floor(yy / P + 0.5)
    dy = yy - kk * P
    j = math.floor(x / 0.45)
    hb = hash2(kk, j, np.int64(bp[2]))
    plant_h = 0.85 + 0.25 * unit(hb, 0)
    cx = (j + 0.5) * 0.45 + (unit(hb, 1) - 0.5) * 0.1
    leafy = value_noise(tile77, x, y, 0.09)
    wid = 0.5 + 0.1 * (leafy - 0.5)
    e = (dy / wid) ** 2 + ((x - cx) / 0.42) ** 2 * 0.35
    prof = 1.0 - e
    hbush = 0.0
    if prof > 0.0:
        hbush = plant_h * math.sqrt(min(prof, 1.0)) * (0.8 + 0.35 * leafy)
    into_path = abs(dy) - 0.5
    hleaf = 0.0
    if into_path > 0.0 and into_path < 0.37:
        jl = math.floor(x / 0.6)
        side = 1 if dy > 0 else 0
        hl = hash2(kk, jl * 2 + side, np.int64(bp[3]))
        reach = 0.12 + 0.25 * unit(hl, 1)
        cxl = (jl + 0.5) * 0.6
        if unit(hl, 0) > 0.45 and into_path < reach and abs(x - cxl) < 0.22:
            hleaf = (0.04 + 0.14 * leafy) * (1.0 - into_path / reach)
    return hbush, hleaf


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def terrain(kind, G, gp, tp, bp, tile77, x, y):
    """(height, material) of ground + stubble/bushes; material 0 ground, 1 stubble, 2 bush,
    3 leaf."""
    g = ground(G, gp, x, y)
    if kind == 0:
        t = tuft(tp, x, y)
        if t > 0.0:
            return g + t, 1
        return g, 0
    hb, hl = bushes(bp, tile77, x, y)
    if hb > 0.0:
        return g + max(hb, hl), 2
    if hl > 0.0:
        return g + hl, 3
    return g, 0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def obstacle_height(obs, k, x, y):
    """Top height above z0 of obstacle row k (0 outside its footprint). Rows are read in place:
    a row view (``obs[k]``) would cost an atomic reference-count increment and decrement of the
    array per call (numba's NRT), which in the per-pixel loops cost more than the arithmetic."""
    dx = x - obs[k, OX]
    dy = y - obs[k, OY]
    u = dx * obs[k, OC] + dy * obs[k, OS]
    v = -dx * obs[k, OS] + dy * obs[k, OC]
    L, W, H = obs[k, OL], obs[k, OW], obs[k, OH]
    sh = int(obs[k, OSHAPE])
    if sh == SH_CYL:
        return H if (u * u + v * v) / ((0.5 * L) ** 2) <= 1.0 else 0.0
    if sh == SH_BOX:
        return H if abs(u) <= 0.5 * L and abs(v) <= 0.5 * W else 0.0
    if sh == SH_VEH:
        if abs(u) <= 0.5 * L and abs(v) <= 0.5 * W:
            if u < 0.22 * L and u > -0.18 * L and abs(v) <= 0.46 * W:
                return H
            return 0.6 * H
        return 0.0
    if sh == SH_PERSON or sh == SH_CROUCH:
        if (u / 0.11) ** 2 + (v / 0.10) ** 2 <= 1.0:
            return H
        if (u / (0.5 * L)) ** 2 + (v / (0.5 * W)) ** 2 <= 1.0:
            return H - (0.27 if sh == SH_PERSON else 0.24)
        return 0.0
    # dome
    e = (u / (0.5 * L)) ** 2 + (v / (0.5 * W)) ** 2
    if e <= 1.0:
        return (H * math.sqrt(max(1.0 - e, 0.0)) + 0.25 * H) * 0.8
    return 0.0


# ---------------------------------------------------------------------------------------------
# the camera
# ---------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy", fastmath=FM)
def march(kind, G, gp, tp, bp, tile77, top_m, obs, ocols, C, f2x, f2y, r2x, r2y, fx, fy, cxv,
          cyv, Wv, Hv, t, h_out, m_out, jhit, rmin):
    """_march with its scratch array."""
    ks = np.empty(max(obs.shape[0], 1), np.int64)
    ift = np.empty(t.shape[0])                     # fy / t: a multiplication per sample
    for j in range(t.shape[0]):
        ift[j] = fy / t[j]
    _march(kind, G, gp, tp, bp, tile77, top_m, obs, ocols, C, f2x, f2y, r2x, r2y, fx, fy, cxv,
           cyv, Wv, Hv, t, h_out, m_out, jhit, rmin, ks, ift)


@njit(**NO_NRT)
def _march(kind, G, gp, tp, bp, tile77, top_m, obs, ocols, C, f2x, f2y, r2x, r2y, fx, fy, cxv,
           cyv, Wv, Hv, t, h_out, m_out, jhit, rmin, ks, ift):
    """Per column: heights/materials at the samples (NaN where not evaluated: cannot be seen,
    or every needed row is already covered) and jhit[r, c] = the first sample that covers
    pixel row r (len(t): none, sky). rmin[c]: the topmost row of column c the real camera
    needs (the march of a column ends once it is covered)."""
    S = t.shape[0]
    no = obs.shape[0]
    row_off, rs, ts = tp[0], tp[1], tp[2]
    ck = np.int64(-(1 << 62))                      # the cached tuft cell (row, place)
    cj = np.int64(-(1 << 62))
    ch = np.int64(0)
    ccx, ccy, cr = 0.0, 0.0, 1.0
    for c in range(Wv):
        a = (c - cxv) / fx
        dxc = f2x + a * r2x
        dyc = f2y + a * r2y
        nk = 0
        for k in range(no):
            if ocols[k, c, 1] > ocols[k, c, 0]:
                ks[nk] = k
                nk += 1
        cm = 1e30
        prev = Hv                                  # rows >= prev are filled
        stop = max(rmin[c], 0)
        for r in range(Hv):
            jhit[c, r] = S
        jend = S
        if stop >= Hv:                             # the real camera needs none of it
            jend = 0
        for j in range(jend):
            tj = t[j]
            x = C[0] + dxc * tj
            y = C[1] + dyc * tj
            hobs = -1e30
            mobs = 0
            for i in range(nk):
                k = ks[i]
                if ocols[k, c, 0] <= j < ocols[k, c, 1]:
                    hoff = obstacle_height(obs, k, x, y)
                    if hoff > 0.0:
                        ho = hoff + obs[k, OZ0]
                        if ho > hobs:
                            hobs = ho
                            mobs = 16 + int(obs[k, OCLS + 1])
            g = ground(G, gp, x, y)
            bound = max(g + top_m, hobs)
            rowb = cyv - (bound - C[2]) * ift[j]
            if j > 0 and (rowb >= cm or rowb >= Hv):   # hidden, or below the image
                h_out[c, j] = np.nan               # cannot be seen
                m_out[c, j] = 0
                continue
            if kind == 0:
                # tuft(tp, x, y) with the last tuft's cell kept: consecutive samples of a
                # column often fall on the same tuft place (same arithmetic, fewer hashes)
                kf = math.floor((y - row_off) / rs + 0.5)
                cy0 = kf * rs + row_off
                tt = 0.0
                if abs(y - cy0) <= 0.1265:
                    jf = math.floor(x / ts)
                    if kf != ck or jf != cj:
                        ch, ccx, ccy, cr = tuft_cell(tp, kf, jf, cy0)
                        ck = kf
                        cj = jf
                    d2 = ((x - ccx) ** 2 + (y - ccy) ** 2) / (cr * cr)
                    if d2 < 1.0:
                        tt = tuft_top(tp, ch, x, y, d2)
                hh = g + tt
                mm = 1 if tt > 0.0 else 0
            else:
                hh, mm = terrain(kind, G, gp, tp, bp, tile77, x, y)
            if hobs >= hh:
                hh = hobs
                mm = mobs
            h_out[c, j] = hh
            m_out[c, j] = mm
            row = cyv - (hh - C[2]) * ift[j]
            if row < cm:
                cm = row
                q = math.ceil(cm)
                if q < 0:
                    q = 0
                if q < prev:
                    for r in range(q, prev):
                        jhit[c, r] = j
                    prev = q
                    if prev <= stop:
                        jend = j + 1
                        break
        for j2 in range(jend, S):
            h_out[c, j2] = np.nan
            m_out[c, j2] = 0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def _h_at(kind, G, gp, tp, bp, tile77, h, c, j, C, dxc, dyc, t):
    v = h[c, j]
    if v == v:
        return v
    hh, _ = terrain(kind, G, gp, tp, bp, tile77, C[0] + dxc * t[j], C[1] + dyc * t[j])
    return hh


@njit(cache=True, error_model="numpy", fastmath=FM)
def shade(kind, G, gp, tp, bp, tile77, obs, salt, C, f2x, f2y, r2x, r2y, fx, fy, cxv, cyv,
          Wv, Hv, t, h, mat, jhit, mode, sun, light_p, tex_grass, tex_gravel, sizes, offsets,
          tiles, sky_bgr, hor_bgr, img, tv, mv, lum, sh_obs, Hr, Wr, Hr_, need_depth):
    """_shade with its scratch arrays."""
    n = max(sh_obs.shape[0], 1)
    _shade(kind, G, gp, tp, bp, tile77, obs, salt, C, f2x, f2y, r2x, r2y, fx, fy, cxv, cyv,
           Wv, Hv, t, h, mat, jhit, mode, sun, light_p, tex_grass, tex_gravel, sizes, offsets,
           tiles, sky_bgr, hor_bgr, img, tv, mv, lum, sh_obs, Hr, Wr, Hr_, need_depth,
           np.empty((Hv, 3)), np.empty(n, np.int64), np.empty(n), np.empty(n))


@njit(**NO_NRT)
def _shade(kind, G, gp, tp, bp, tile77, obs, salt, C, f2x, f2y, r2x, r2y, fx, fy, cxv, cyv,
           Wv, Hv, t, h, mat, jhit, mode, sun, light_p, tex_grass, tex_gravel, sizes, offsets,
           tiles, sky_bgr, hor_bgr, img, tv, mv, lum, sh_obs, Hr, Wr, Hr_, need_depth,
           sky, cks, ctlo, cthi):
    """Per pixel: hit point, normal, albedo, light. ``tiles``: value-noise tiles by salt index
    (0: 0x9, 1: 0xA, 2: 0xB, 3: 0xC, 4: cloud); light_p = (strobe_power, cloud, dusk, wind_x,
    wind_y, time_s, cloud_cell_m)."""
    S = t.shape[0]
    no = obs.shape[0]
    litter_w = tp[16]
    hscale = tp[5]
    dusk = light_p[2]
    cloud = light_p[1]
    amb = (0.42 + 0.08 * cloud) * (1.0 - 0.5 * dusk)
    tint0 = 1 - 0.75 * dusk
    tint1 = 1 - 0.5 * dusk
    tint2 = 1 - 0.3 * dusk
    for r in range(Hv):
        el = (cyv - r) / fy
        if el < 0:
            el = 0.0
        w = min(el / 0.35, 1.0)
        for q in range(3):
            sky[r, q] = 0.0 if mode == 1 else hor_bgr[q] * (1 - w) + sky_bgr[q] * w
    # the sun's direction in the ground plane (obstacle shadows)
    nsh = sh_obs.shape[0]
    s_ux, s_uy, s_tan = 0.0, 0.0, 0.0
    s_horiz = math.sqrt(sun[0] * sun[0] + sun[1] * sun[1])
    if s_horiz < 1e-6:
        nsh = 0                                    # sun overhead: render._shadows lights all
    else:
        s_ux, s_uy, s_tan = sun[0] / s_horiz, sun[1] / s_horiz, sun[2] / s_horiz
    # cks, ctlo, cthi: this column's shadow casters and their intervals of t
    # column-major (virtual column c outer): the march's arrays are read along a column and the
    # outputs are stored transposed, [c, r] (the warp swaps the axes back)
    for c in range(Wv):
        # rows of this column the real camera samples: the pixel's real image point
        # (uq, vq) = (A + B r, D + E r) / (F + G r) inside [-2.5, W + 1.5] x [-2.5, H + 1.5]; a
        # line through a convex box, so an interval of rows, solved here once per column
        # (with w > 0 along the column; otherwise the test per pixel as before)
        A_ = Hr[0, 0] * c + Hr[0, 2]
        B_ = Hr[0, 1]
        D_ = Hr[1, 0] * c + Hr[1, 2]
        E_ = Hr[1, 1]
        F_ = Hr[2, 0] * c + Hr[2, 2]
        G_ = Hr[2, 1]
        per_pixel = not (F_ > 0.0 and F_ + G_ * (Hv - 1) > 0.0)
        rlo, rhi = 0.0, Hv - 1.0
        if not per_pixel:
            # lo * w <= num <= hi * w for (num, lo, hi) = (u, -2.5, W+1.5), (v, -2.5, H+1.5)
            for q in range(4):
                if q == 0:
                    k0, k1 = A_ + 2.5 * F_, B_ + 2.5 * G_          # u + 2.5 w >= 0
                elif q == 1:
                    k0, k1 = (Wr + 1.5) * F_ - A_, (Wr + 1.5) * G_ - B_
                elif q == 2:
                    k0, k1 = D_ + 2.5 * F_, E_ + 2.5 * G_
                else:
                    k0, k1 = (Hr_ + 1.5) * F_ - D_, (Hr_ + 1.5) * G_ - E_
                # k0 + k1 r >= 0
                if k1 > 0.0:
                    rlo = max(rlo, -k0 / k1)
                elif k1 < 0.0:
                    rhi = min(rhi, -k0 / k1)
                elif k0 < 0.0:
                    rlo, rhi = 1.0, 0.0
        r_first = int(math.ceil(rlo)) if rlo <= rhi else Hv
        r_last = int(math.floor(rhi)) if rlo <= rhi else -1
        a = (c - cxv) / fx
        dxc = f2x + a * r2x
        dyc = f2y + a * r2y
        # obstacle shadows that can fall on this column: the forward depths t over which the
        # column's ground line crosses each caster's shadow rectangle (s in (-r, reach) along
        # the sun, |perp| < r); the exact test (shadow()) runs only on those, per pixel
        nck = 0
        if mode == 0:
            b_s = dxc * s_ux + dyc * s_uy
            b_p = dxc * s_uy - dyc * s_ux
            for k in range(nsh):
                ddx0 = sh_obs[k, 0] - C[0]
                ddy0 = sh_obs[k, 1] - C[1]
                s0 = ddx0 * s_ux + ddy0 * s_uy
                p0 = ddx0 * s_uy - ddy0 * s_ux
                rk = sh_obs[k, 2]
                tl, th_ = -1e30, 1e30
                # s0 - t bs in (-r, reach)
                if abs(b_s) > 1e-12:
                    ta = (s0 + rk) / b_s
                    tb = (s0 - sh_obs[k, 4]) / b_s
                    tl, th_ = max(tl, min(ta, tb)), min(th_, max(ta, tb))
                elif not (-rk < s0 < sh_obs[k, 4]):
                    continue
                # p0 - t bp in (-r, r)
                if abs(b_p) > 1e-12:
                    ta = (p0 + rk) / b_p
                    tb = (p0 - rk) / b_p
                    tl, th_ = max(tl, min(ta, tb)), min(th_, max(ta, tb))
                elif not (abs(p0) < rk):
                    continue
                eps = 1e-6 * (1.0 + abs(tl) + abs(th_))
                if th_ + eps < tl - eps or th_ + eps < 0.0:
                    continue
                cks[nck] = k
                ctlo[nck] = tl - eps
                cthi[nck] = th_ + eps
                nck += 1
        for r in range(Hv):
            j = jhit[c, r]
            if per_pixel:
                wq = F_ + G_ * r
                uq = (A_ + B_ * r) / wq
                vq = (D_ + E_ * r) / wq
                if uq < -2.5 or vq < -2.5 or uq > Wr + 1.5 or vq > Hr_ + 1.5:
                    j = S                          # the real camera never samples it
            elif r < r_first or r > r_last:
                j = S
            if j >= S:
                img[c, r, 0] = sky[r, 0]
                img[c, r, 1] = sky[r, 1]
                img[c, r, 2] = sky[r, 2]
                if need_depth:
                    tv[c, r] = 0.0
                    mv[c, r] = -1.0
                    lum[c, r] = 0.0
                continue
            jp = j - 1 if j > 0 else 0
            tj = t[j]
            tp_ = t[jp]
            hj = h[c, j]
            hp = _h_at(kind, G, gp, tp, bp, tile77, h, c, jp, C, dxc, dyc, t)
            slope = (r - cyv) / fy
            zr_j = C[2] - slope * tj
            zr_p = C[2] - slope * tp_
            side = (zr_p < hj - (0.01 + 0.002 * tj)) and j > 0
            fj = hj - zr_j
            fp = hp - zr_p
            den = fj - fp
            frac = -fp / den if abs(den) > 1e-6 else 1.0
            frac = min(max(frac, 0.0), 1.0)
            if side:
                frac = 0.5
            if j == 0:
                frac = 0.0
            th = tp_ + frac * (tj - tp_)
            px = C[0] + dxc * th
            py = C[1] + dyc * th
            pz = C[2] - slope * th
            pm = mat[c, j]
            foot = th * math.sqrt(1 + a * a + slope * slope) / fx
            # ---- normal
            nx, ny, nz = 0.0, 0.0, 1.0
            if not side and j > 0:
                dt = tj - t[j - 1]
                dhA = (hj - hp) / dt
                cn = c + 1 if c + 1 < Wv else c - 1
                an = (cn - cxv) / fx
                hn = _h_at(kind, G, gp, tp, bp, tile77, h, cn, j, C, f2x + an * r2x,
                           f2y + an * r2y, t)
                dhB = (hn - hj) * (cn - c) / (tj / fx)
                gr = dhB
                gf = dhA - a * gr
                gx = gf * f2x + gr * r2x
                gy = gf * f2y + gr * r2y
                g2 = gx * gx + gy * gy
                if g2 <= 9.0:                      # min(1, 3 / |g|) = 1: no sqrt, no division
                    nx, ny = -gx, -gy
                else:
                    s = 3.0 / math.sqrt(g2)
                    nx, ny = -gx * s, -gy * s
            elif side:
                ddx, ddy = -dxc, -dyc
                dn = math.sqrt(ddx * ddx + ddy * ddy)
                sx, sy = ddx / dn, ddy / dn
                if pm >= 16:
                    ko = _obs_index(obs, pm)
                    ux = px - obs[ko, OX]
                    uy = py - obs[ko, OY]
                    u = ux * obs[ko, OC] + uy * obs[ko, OS]
                    v = -ux * obs[ko, OS] + uy * obs[ko, OC]
                    shp = int(obs[ko, OSHAPE])
                    if shp == SH_BOX or shp == SH_VEH:
                        au = abs(u) / (0.5 * obs[ko, OL])
                        av = abs(v) / (0.5 * obs[ko, OW])
                        nu = (1.0 if u > 0 else -1.0) if au >= av else 0.0
                        nv = (1.0 if v > 0 else -1.0) if au < av else 0.0
                    else:
                        nn_ = math.sqrt(u * u + v * v) + 1e-6
                        nu, nv = u / nn_, v / nn_
                    sx = nu * obs[ko, OC] - nv * obs[ko, OS]
                    sy = nu * obs[ko, OS] + nv * obs[ko, OC]
                else:
                    ang = fsin(px * 91.7 + py * 53.3) * 0.8
                    a2 = ang * ang
                    ca = 1.0 - a2 * (0.5 - a2 * (1.0 / 24 - a2 * (1.0 / 720)))
                    sa = ang * (1.0 - a2 * (1.0 / 6 - a2 * (1.0 / 120 - a2 * (1.0 / 5040))))
                    sx, sy = sx * ca - sy * sa, sx * sa + sy * ca
                nx, ny, nz = sx, sy, 0.0
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx / nn, ny / nn, nz / nn
            # ---- albedo
            b0, b1, b2 = albedo(kind, G, gp, tp, bp, tile77, obs, salt, px, py, pz, pm, foot,
                                tex_grass, tex_gravel, sizes, offsets, tiles, litter_w, hscale)
            # ---- light
            if mode == 0:
                lam = max(nx * sun[0] + ny * sun[1] + nz * sun[2], 0.0)
                lit = 1.0
                if pm < 16:
                    for i in range(nck):
                        if ctlo[i] <= th <= cthi[i]:
                            if not shadow_one(sh_obs, cks[i], s_ux, s_uy, s_tan, px, py, pz):
                                lit = 0.0
                                break
                if cloud > 0.0:
                    n_ = value_noise_k(tiles, 4, px - light_p[3] * light_p[5],
                                     py - light_p[4] * light_p[5], light_p[6])
                    shd = min(max((n_ - (1.0 - cloud)) * 5.0, 0.0), 1.0)
                    lit *= 1.0 - 0.85 * shd
                d = 0.75 * lam * lit
                if cloud > 0.0 or dusk > 0.0:
                    r0 = b0 * (amb + d * tint0)
                    r1 = b1 * (amb + d * tint1)
                    r2 = b2 * (amb + d * tint2)
                else:
                    sh_ = 0.42 + d
                    r0, r1, r2 = b0 * sh_, b1 * sh_, b2 * sh_
            elif mode == 1:
                lx, ly, lz = C[0] - px, C[1] - py, C[2] - pz
                rr2 = lx * lx + ly * ly + lz * lz
                rr = math.sqrt(rr2)
                lam = max((nx * lx + ny * ly + nz * lz) / rr, 0.08)
                k = light_p[0] * lam / rr2
                r0 = b0 * k
                r1 = b1 * k
                r2 = b2 * k
                r0 = r0 / (1 + r0) * 1.25
                r1 = r1 / (1 + r1) * 1.25
                r2 = r2 / (1 + r2) * 1.25
            else:
                sh_ = 0.6 + 0.4 * nz + 0.15 * abs(nx)
                r0, r1, r2 = b0 * sh_, b1 * sh_, b2 * sh_
            img[c, r, 0] = r0
            img[c, r, 1] = r1
            img[c, r, 2] = r2
            if need_depth:
                tv[c, r] = th
                mv[c, r] = pm
                lum[c, r] = b0 * 0.114 + b1 * 0.587 + b2 * 0.299


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def fsin(x):
    """sin(x) to ~1e-6 for any x (range reduction to [-pi, pi], then a polynomial)."""
    q = x * (1.0 / (2 * math.pi))
    q -= math.floor(q + 0.5)
    y = q * (2 * math.pi)                      # [-pi, pi]
    # fold to [-pi/2, pi/2]
    if y > 0.5 * math.pi:
        y = math.pi - y
    elif y < -0.5 * math.pi:
        y = -math.pi - y
    y2 = y * y
    return y * (1.0 - y2 * (1.0 / 6 - y2 * (1.0 / 120 - y2 * (1.0 / 5040 - y2 * (1.0 / 362880)))))


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def _obs_index(obs, pm):
    """Row of the obstacle whose material code is pm (obs[:, OCLS + 1] holds its world index)."""
    k = pm - 16
    for i in range(obs.shape[0]):
        if int(obs[i, OCLS + 1]) == k:
            return i
    return 0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def shadow(sh, sun, px, py, pz):
    """render._shadows for one ground point: sh rows = (x, y, r, top, reach)."""
    horiz = math.sqrt(sun[0] * sun[0] + sun[1] * sun[1])
    if horiz < 1e-6:
        return 1.0
    ux, uy = sun[0] / horiz, sun[1] / horiz
    tan_e = sun[2] / horiz
    for k in range(sh.shape[0]):
        ddx = sh[k, 0] - px
        ddy = sh[k, 1] - py
        s = ddx * ux + ddy * uy
        r = sh[k, 2]
        if s <= -r or s >= sh[k, 4]:
            continue
        perp = abs(ddx * uy - ddy * ux)
        if perp >= r:
            continue
        s_in = max(s - math.sqrt(max(r * r - perp * perp, 0.0)), 0.0)
        if pz + s_in * tan_e < sh[k, 3]:
            return 0.0
    return 1.0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def shadow_one(sh, k, ux, uy, tan_e, px, py, pz):
    """shadow()'s test for one caster k: False where its shadow falls on the point."""
    ddx = sh[k, 0] - px
    ddy = sh[k, 1] - py
    s = ddx * ux + ddy * uy
    r = sh[k, 2]
    if s <= -r or s >= sh[k, 4]:
        return True
    perp = abs(ddx * uy - ddy * ux)
    if perp >= r:
        return True
    s_in = max(s - math.sqrt(max(r * r - perp * perp, 0.0)), 0.0)
    return not (pz + s_in * tan_e < sh[k, 3])


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def albedo(kind, G, gp, tp, bp, tile77, obs, salt, x, y, z, pm, foot, tex_grass, tex_gravel,
           sizes, offsets, tiles, litter_w, hscale):
    """world.World.albedo for one point: BGR."""
    if pm == 0:
        patch = value_noise_k(tiles, 0, x, y, 3.0)
        fine = value_noise_k(tiles, 1, x, y, 0.35)
        grav = texture(tex_gravel, sizes, offsets, x, y, 0.004, foot)
        if kind == 0:
            st = texture(tex_grass, sizes, offsets, y * 0.7 + 3.3, x * 0.7, 0.003, foot)
            w = min(max((st - 0.95) * 1.6 + (patch - 0.5) * 0.8 + litter_w, 0.0), 1.0)
            k = (0.75 + 0.25 * grav) * (0.85 + 0.3 * fine)
            # tp[10:13] soil, tp[13:16] litter (BGR), read as scalars (no slice views)
            return ((tp[10] * (1 - w) + tp[13] * w) * k, (tp[11] * (1 - w) + tp[14] * w) * k,
                    (tp[12] * (1 - w) + tp[15] * w) * k)
        k = (0.7 + 0.3 * grav) * (0.85 + 0.3 * patch)
        return 0.40 * k, 0.45 * k, 0.54 * k
    if pm == 1:
        g = ground(G, gp, x, y)
        rel = min(max((z - g) / (0.4 * hscale), 0.0), 1.0)
        streak = texture(tex_grass, sizes, offsets, (x - y) * 0.9, (z - g) * 0.12, 0.002, foot)
        var = value_noise_k(tiles, 2, x, y, 1.5)
        k = (0.55 + 0.45 * rel) * (0.6 + 0.4 * streak) * (0.85 + 0.3 * var)
        return tp[7] * k, tp[8] * k, tp[9] * k     # straw BGR
    if pm == 2 or pm == 3:
        leaf = value_noise_k(tiles, 3, x + z * 0.7, y - z * 0.5, 0.05)
        tx = texture(tex_grass, sizes, offsets, x * 0.8 + y, z * 0.8 + y * 0.3, 0.002, foot)
        k = (0.6 + 0.8 * leaf) * (0.7 + 0.3 * tx)
        cell = 0.14
        ix = math.floor(x / cell)
        iz = math.floor(z / cell)
        iy = math.floor(y / cell)
        hp = hash2(ix * 7919 + iy, iz, salt ^ 0xD)
        ppx = (ix + 0.5) * cell + (unit(hp, 1) - 0.5) * 0.05
        ppy = (iy + 0.5) * cell + (unit(hp, 3) - 0.5) * 0.05
        ppz = (iz + 0.5) * cell + (unit(hp, 2) - 0.5) * 0.05
        d2 = (x - ppx) ** 2 + (y - ppy) ** 2 + ((z - ppz) * 0.8) ** 2
        if pm == 2 and unit(hp, 0) > 0.5 and d2 < 0.045 ** 2 and z > 0.25 and z < 0.95:
            return 0.16, 0.10, 0.55
        return 0.17 * k, 0.25 * k, 0.17 * k
    # an obstacle (world.Obstacle.albedo)
    ko = _obs_index(obs, pm)
    zr = z - obs[ko, OZ0]
    H = obs[ko, OH]
    c0, c1, c2 = obs[ko, OC1B], obs[ko, OC1G], obs[ko, OC1R]
    shp = int(obs[ko, OSHAPE])
    cls = int(obs[ko, OCLS])
    if shp == SH_PERSON:
        if zr < 0.85:
            c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
        if zr > H - 0.08:
            c0, c1, c2 = 0.12, 0.12, 0.15
        elif zr > H - 0.27:
            c0, c1, c2 = 0.45, 0.55, 0.75
    elif shp == SH_CROUCH:
        if zr < 0.45:
            c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
        if zr > H - 0.24:
            c0, c1, c2 = 0.45, 0.55, 0.75
    elif shp == SH_VEH:
        dx = x - obs[ko, OX]
        dy = y - obs[ko, OY]
        u = dx * obs[ko, OC] + dy * obs[ko, OS]
        cab = u < 0.22 * obs[ko, OL] and u > -0.18 * obs[ko, OL]
        if cab and zr > 0.62 * H and zr < 0.95 * H:
            c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
        if zr < 0.4:
            c0, c1, c2 = 0.08, 0.08, 0.08
    elif shp == SH_DOME:
        if zr < 0.3 * H:
            c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
    elif cls == CL_DRUM:
        if abs(zr - H / 3) < 0.025 or abs(zr - 2 * H / 3) < 0.025:
            if obs[ko, OTEX] > 0:
                c0, c1, c2 = c0 * 0.8, c1 * 0.8, c2 * 0.8
            else:
                c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
    elif cls == CL_CRATE:
        if abs(zr - 0.75 * H) < 0.03:
            c0, c1, c2 = obs[ko, OC2B], obs[ko, OC2G], obs[ko, OC2R]
    if obs[ko, OTEX] > 0:
        tt = texture(tex_grass, sizes, offsets, (x + y) * 1.0, zr * 0.25, 0.0025, foot)
        k = 0.55 + 0.45 * tt
    else:
        tt = texture(tex_gravel, sizes, offsets, x + y, zr, 0.004, foot)
        k = 0.9 + 0.1 * tt
    return min(max(c0 * k, 0.0), 1.5), min(max(c1 * k, 0.0), 1.5), min(max(c2 * k, 0.0), 1.5)


# ---------------------------------------------------------------------------------------------
# exposure, laser
# ---------------------------------------------------------------------------------------------
@njit(**NO_NRT)
def expose(rad, pool, dy, dx, night, out):
    """Radiance -> 8 bit with the noise pool's window at (dy, dx) (render.expose passes the
    channel-reversed pool when it flips). One flat loop over each row's W*3 values (LLVM
    vectorises it: ~7x faster than the per-channel loop with the flip in the index)."""
    H, W = rad.shape[0], rad.shape[1]
    if night:
        A = np.float32(4.0)
        B = np.float32(0.6)
    else:
        A = np.float32(1.2)
        B = np.float32(0.12)
    for r in range(H):
        rr = rad[r].reshape(W * 3)
        pr = pool[dy + r, dx:dx + W].reshape(W * 3)
        orow = out[r].reshape(W * 3)
        for i in range(W * 3):
            x = rr[i] * np.float32(255.0)
            sg = A + math.sqrt(max(x, 0.0)) * B
            v = x + sg * pr[i] + np.float32(0.5)
            v = min(max(v, 0.0), 255.0)
            orow[i] = np.uint8(v)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FM)
def coarse_max(Gc, gp, x, y):
    """The highest ground node around (x, y) on the coarse grid of COARSE x COARSE ground cells
    (world.ground_coarse_max): ground(x, y) <= this everywhere in that coarse cell."""
    fx, fy, _ = grid_pos(gp, x, y)
    return Gc[int(fy) // COARSE, int(fx) // COARSE]


COARSE = 5


@njit(**NO_NRT)
def laser(kind, G, gp, tp, bp, tile77, max_terrain, obs, O, dirs, t, range_max, Gc, top_m, out):
    """Per beam: the first sample at or under the terrain (a sample higher than the coarse
    grid's highest ground node + the tallest tuft/bush cannot touch it and is not evaluated),
    then the obstacles near the beam."""
    N = dirs.shape[0]
    S = t.shape[0]
    no = obs.shape[0]
    row_off, rs, ts = tp[0], tp[1], tp[2]
    ck = np.int64(-(1 << 62))                      # the cached tuft cell (as in _march)
    cj = np.int64(-(1 << 62))
    ch = np.int64(0)
    ccx, ccy, cr = 0.0, 0.0, 1.0
    for b in range(N):
        dxb, dyb, dzb = dirs[b, 0], dirs[b, 1], dirs[b, 2]
        best = np.inf
        for j in range(S):
            tj = t[j]
            z = O[2] + dzb * tj
            if z > max_terrain:
                if dzb >= 0:
                    break
                continue
            xb = O[0] + dxb * tj
            yb = O[1] + dyb * tj
            if z > coarse_max(Gc, gp, xb, yb) + top_m:
                continue
            if kind == 0:
                # terrain() = ground + tuft(), the tuft's cell kept between samples
                hh = ground(G, gp, xb, yb)
                kf = math.floor((yb - row_off) / rs + 0.5)
                cy0 = kf * rs + row_off
                if abs(yb - cy0) <= 0.1265:
                    jf = math.floor(xb / ts)
                    if kf != ck or jf != cj:
                        ch, ccx, ccy, cr = tuft_cell(tp, kf, jf, cy0)
                        ck = kf
                        cj = jf
                    d2 = ((xb - ccx) ** 2 + (yb - ccy) ** 2) / (cr * cr)
                    if d2 < 1.0:
                        hh += tuft_top(tp, ch, xb, yb, d2)
            else:
                hh, _ = terrain(kind, G, gp, tp, bp, tile77, xb, yb)
            if hh >= z:
                best = tj
                break
        dxy = math.sqrt(dxb * dxb + dyb * dyb)
        if dxy > 1e-9:
            ux, uy = dxb / dxy, dyb / dxy
            for k in range(no):
                qx, qy = obs[k, OX] - O[0], obs[k, OY] - O[1]
                along = qx * ux + qy * uy
                perp = abs(qx * uy - qy * ux)
                R = obs[k, OR]
                if perp > R or along + R <= 0 or along - R >= range_max:
                    continue
                s0 = max(along - R, 0.0)
                n = int(math.ceil((along + R - s0) / 0.005))
                for i in range(n):
                    ss = s0 + i * 0.005
                    tt = ss / dxy
                    if tt >= best:
                        break
                    px, py, pz = O[0] + dxb * tt, O[1] + dyb * tt, O[2] + dzb * tt
                    ho = obstacle_height(obs, k, px, py)
                    if ho > 0 and pz <= ho + obs[k, OZ0] and pz >= obs[k, OZ0] - 0.5:
                        best = tt
                        break
        out[b] = best if best <= range_max else np.nan


@njit(**NO_NRT)
def kinect(z, lum, mat, edge, shiny, pn, pu, dy, dx, bf, min_range, max_range, out):
    """render.kinect_depth's per-pixel part: quantised z-depth with noise, holes (0) on edges,
    shiny materials (``shiny[mat + 1]``), dark surfaces (80 %), 0.2 % speckle and out of
    range. pn/pu: pools of unit normals / uniforms read at a window (dy, dx)."""
    H, W = z.shape
    for r in range(H):
        for c in range(W):
            zz = z[r, c]
            if zz < min_range or zz > max_range or edge[r, c]:
                out[r, c] = 0.0
                continue
            m = mat[r, c]
            if m >= -1 and m + 1 < shiny.shape[0] and shiny[m + 1]:
                out[r, c] = 0.0
                continue
            sp = pu[dy + r, dx + c]
            if sp < 0.002 or (lum[r, c] < 0.06 and sp < 0.8):
                out[r, c] = 0.0
                continue
            q = bf / round(bf / max(zz, 1e-3))
            out[r, c] = q + pn[dy + r, dx + c] * 1.5e-3 * q * q
