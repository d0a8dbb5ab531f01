"""Measure what a GL rasteriser (moderngl through Mesa's llvmpipe: no GPU here) would cost for the
simulator's camera views, on ONE core, beside today's numba renderer in the same run (issue #13).

    LP_NUM_THREADS=0 .venv/bin/python tools/bench_gl.py [--frames 6] [--cpu 1] [--lp-threads 0]
                                                        [--no-numba] [--json]

This is NOT a renderer of the simulator: it draws geometry of the same size as the sim's scene
"stubble-day" (seed 0) from the sim's own camera poses and intrinsics, to give an honest LOWER
BOUND of the cost of a GL version:

- ground: the world's own ground grid (world.ground_grid(), 0.2 m cells) as a triangle mesh,
  only the cells inside the cameras' view wedge out to the far range (perfect culling for free);
- stubble tufts: every tuft of the world's own hash (row 0.75 m, place 0.22 m, gaps, jitter,
  radius, height: world._tufts) in that wedge, instanced, each a 24-triangle dome (8 sides,
  2 rings) shaped like the tuft's profile. Left out: the ragged 2 cm stalk tops (the sim's
  per-sample "rag" term) -- a mesh with them would be far larger;
- obstacles: the world's obstacles as boxes (box, person, vehicle: their footprint box) and
  16-sided cylinders. Left out: the person/vehicle/dome shapes' detail;
- the fragment shader: albedo as fastrender.albedo() reads it (two value-noise octaves from the
  world's own noise tiles + two mip-mapped photo textures on the ground; one octave + one
  texture on stubble; a texture on obstacles), Lambert sun + ambient, the obstacles' shadows by
  the same analytic test as fastrender.shadow_one, exposure to 8 bit with a hashed noise in the
  shader. Left out: the sky gradient (a clear colour), cloud shadows, dusk tint, night strobe,
  the material image and albedo-luminance image the RGB-D path needs, the Kinect post-process.
- per view it reads back the 8-bit colour (RGBA) and an exact float32 z-depth image (a second
  R32F colour attachment the shader writes the optical z into), as numpy arrays.
- the geometry is built once (not streamed as the vehicle drives; a GL version would have to).

Variants (each timed for a 640x512 pair, a 1280x1024 pair, a 640x480 single view, and the
640x512 pair's geometry into an 80x64 viewport, where almost no fragments are left, i.e. the
vertex + set-up cost): ``full`` (the above), ``no_tufts`` (ground + obstacles), ``coarse``
(ground every 4th node = 0.8 m cells, 4-triangle tufts), ``floor`` (the coarse ground alone,
untextured: albedo a constant, Lambert + noise kept), ``bare`` (the coarse ground alone, a
constant colour + z: llvmpipe's cost of merely rasterising and writing the two images).

Figures: CPU ms (``time.process_time``: every thread of the process, so llvmpipe's own threads
cannot hide work) and wall ms per frame, p50 over ``--frames`` frames after a warm-up; the
process is pinned to one core (``--cpu``). ``LP_NUM_THREADS`` is set from ``--lp-threads``
before the GL context is made (0: llvmpipe rasterises on the calling thread).
The numba figures come from tools/bench_sim.py run as a subprocess in the same invocation.
Exits 2 with a one-line message when moderngl or a headless EGL context is missing
(``pip install .[gl]``; Mesa's EGL: libegl-mesa0 + libgl1-mesa-dri on Debian).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# One source, specialised per material with MODE (0 ground, 1 stubble tuft (instanced),
# 2 obstacle, 3 untextured ground, 4 bare: constant colour + z): a program each, as a GL renderer
# would have. (A single program branching on a uniform ran every branch: llvmpipe executes
# both sides of a branch under a mask, and the bare ground cost 3x what its own program costs.)
VS = """
uniform mat3 Rt;          // world -> optical
uniform vec3 Crel;        // camera centre relative to the geometry's origin
uniform vec4 K;           // fx, fy, cx + 0.5, cy + 0.5
uniform vec2 WH;
uniform vec2 NF;          // near, far
in vec3 in_pos;
in vec3 in_nrm;
#if MODE == 1
in vec4 in_inst;          // tuft: cx, cy, z ground, radius
in float in_h;            // tuft: height
out float v_g;
#endif
out vec3 v_pos;
out vec3 v_nrm;
out float v_z;
void main() {
#if MODE == 1
    vec3 p = vec3(in_inst.x + in_inst.w * in_pos.x, in_inst.y + in_inst.w * in_pos.y,
                  in_inst.z + in_h * in_pos.z);
    vec3 n = normalize(vec3(in_nrm.xy * in_h, in_nrm.z * in_inst.w));
    v_g = in_inst.z;
#else
    vec3 p = in_pos;
    vec3 n = in_nrm;
#endif
    vec3 q = Rt * (p - Crel);
    float z = q.z;
    float A = (NF.y + NF.x) / (NF.y - NF.x);
    float B = -2.0 * NF.y * NF.x / (NF.y - NF.x);
    gl_Position = vec4((K.x * q.x + K.z * z) * 2.0 / WH.x - z,
                       z - (K.y * q.y + K.w * z) * 2.0 / WH.y,
                       A * z + B, z);
    v_pos = p;
    v_nrm = n;
    v_z = z;
}
"""

FS = """
uniform sampler2D tile0;  // the world's value-noise tiles (513 x 513, read as fastrender does)
uniform sampler2D tile1;
uniform sampler2D tile2;
uniform sampler2D grass;  // the sim's photo textures, mip-mapped
uniform sampler2D gravel;
uniform vec2 origin;      // world x, y of the geometry's origin
uniform vec3 sun;
uniform vec3 ocolour;
uniform int nsh;
uniform vec4 sh[16];      // shadow casters: x, y (relative), r, top
uniform float shreach[16];
uniform vec3 straw;
uniform vec3 soil;
uniform vec3 litter;
uniform int seed;
in vec3 v_pos;
in vec3 v_nrm;
in float v_z;
#if MODE == 1
in float v_g;
#endif
layout(location = 0) out vec4 f_col;
layout(location = 1) out float f_z;

float vnoise(sampler2D t, vec2 xy, float cell) {
    vec2 f = xy / cell;
    vec2 i = floor(f);
    vec2 tt = f - i;
    tt = tt * tt * (3.0 - 2.0 * tt);
    ivec2 ii = ivec2(int(i.x) & 511, int(i.y) & 511);
    float v00 = texelFetch(t, ii, 0).r;
    float v10 = texelFetch(t, ii + ivec2(1, 0), 0).r;
    float v01 = texelFetch(t, ii + ivec2(0, 1), 0).r;
    float v11 = texelFetch(t, ii + ivec2(1, 1), 0).r;
    return mix(mix(v00, v10, tt.x), mix(v01, v11, tt.x), tt.y);
}
uint mix32(uint h) {
    h ^= h >> 16; h *= 0x85EBCA6Bu; h ^= h >> 13; h *= 0xC2B2AE35u; h ^= h >> 16; return h;
}
void main() {
#if MODE == 4
    f_col = vec4(0.5, 0.5, 0.5, 1.0);
    f_z = v_z;
#else
    vec2 w = v_pos.xy + origin;
    vec3 alb;
#if MODE == 0
    float patch = vnoise(tile0, w, 3.0);
    float fine = vnoise(tile1, w, 0.35);
    float grav = texture(gravel, w / (0.004 * 512.0)).r;
    float st = texture(grass, vec2(w.y * 0.7 + 3.3, w.x * 0.7) / (0.003 * 512.0)).r;
    float wl = clamp((st - 0.95) * 1.6 + (patch - 0.5) * 0.8, 0.0, 1.0);
    float k = (0.75 + 0.25 * grav) * (0.85 + 0.3 * fine);
    alb = mix(soil, litter, wl) * k;
#elif MODE == 1
    float rel = clamp((v_pos.z - v_g) / 0.4, 0.0, 1.0);
    float streak = texture(grass, vec2(w.x - w.y, (v_pos.z - v_g) * 0.12) / (0.002 * 512.0)).r;
    float var_ = vnoise(tile2, w, 1.5);
    alb = straw * (0.55 + 0.45 * rel) * (0.6 + 0.4 * streak) * (0.85 + 0.3 * var_);
#elif MODE == 3
    alb = soil;                                  // the floor variant: no texture at all
#else
    float tt = texture(gravel, vec2(w.x + w.y, v_pos.z) / (0.004 * 512.0)).r;
    alb = ocolour * (0.9 + 0.1 * tt);
#endif
    vec3 n = normalize(v_nrm);
    float lam = max(dot(n, sun), 0.0);
    float lit = 1.0;
#if MODE == 0 || MODE == 1 || MODE == 3
    float horiz = length(sun.xy);
    vec2 u = sun.xy / horiz;
    float tan_e = sun.z / horiz;
    for (int k = 0; k < nsh; k++) {
        vec2 d = sh[k].xy - v_pos.xy;
        float s = dot(d, u);
        float r = sh[k].z;
        if (s <= -r || s >= shreach[k]) continue;
        float perp = abs(d.x * u.y - d.y * u.x);
        if (perp >= r) continue;
        float s_in = max(s - sqrt(max(r * r - perp * perp, 0.0)), 0.0);
        if (v_pos.z + s_in * tan_e < sh[k].w) { lit = 0.0; break; }
    }
#endif
    vec3 rad = alb * (0.42 + 0.75 * lam * lit);
    // exposure with sensor noise (a hashed pseudo-Gaussian per pixel and channel)
    uvec2 pix = uvec2(gl_FragCoord.xy);
    uint h = mix32(pix.x * 0x9E3779B1u ^ (pix.y * 0x85EBCA77u + uint(seed)));
    vec3 g = vec3(float(h & 1023u), float((h >> 10) & 1023u), float((h >> 20) & 1023u));
    g = (g / 1023.0 - 0.5) * 3.46;               // unit variance (uniform)
    vec3 x = rad * 255.0;
    x += (1.2 + sqrt(max(x, 0.0)) * 0.12) * g;
    f_col = vec4(clamp(x / 255.0, 0.0, 1.0).bgr, 1.0);
    f_z = v_z;
#endif
}
"""


def _pos_nrm(prog):
    """The (format, names) of an x,y,z,nx,ny,nz vertex buffer for a program (a program that
    does not use the normal has lost that attribute: skip its bytes)."""
    if prog.get("in_nrm", None) is None:
        return ("3f 12x", "in_pos")
    return ("3f 3f", "in_pos", "in_nrm")


def make_program(ctx, mode: int):
    """The program of one material (MODE above)."""
    head = f"#version 330\n#define MODE {int(mode)}\n"
    return ctx.program(vertex_shader=head + VS, fragment_shader=head + FS)


def _set(prog, name, value=None, data=None):
    """Set a uniform the program has (the compiler drops the ones a material does not use)."""
    if prog.get(name, None) is None:
        return
    if data is not None:
        prog[name].write(data)
    else:
        prog[name].value = value


def _die(msg: str) -> int:
    print(f"bench_gl: {msg}", file=sys.stderr)
    return 2


# ---------------------------------------------------------------------------------------------
# geometry of the sim's scene (built once, relative to an origin near the cameras)
# ---------------------------------------------------------------------------------------------
def _wedge(px, py, C, yaw, half_deg, r_max, r_near=3.0):
    """Points (px, py) inside the view wedge of a camera at C looking along yaw."""
    dx, dy = px - C[0], py - C[1]
    fwd = dx * math.cos(yaw) + dy * math.sin(yaw)
    right = dx * math.sin(yaw) - dy * math.cos(yaw)
    ang = np.abs(np.arctan2(right, np.maximum(fwd, 1e-9)))
    d = np.hypot(dx, dy)
    return ((fwd > -1.0) & (ang <= math.radians(half_deg)) & (d <= r_max)) | (d <= r_near)


def ground_mesh(world, C, yaw, origin, half_deg, r_max, stride=1):
    """The world's ground grid (every ``stride``-th node) as (vertices x,y,z,nx,ny,nz, indices)
    of the cells inside the wedge."""
    G, gp = world.ground_grid()
    nx, ny = int(gp[3]), int(gp[4])
    g = G.reshape(ny, nx)
    cell = 1.0 / gp[2]
    # the wedge's bounding box in node indices
    corners = [(C[0], C[1])]
    for a in np.linspace(-half_deg, half_deg, 9):
        corners.append((C[0] + r_max * math.cos(yaw + math.radians(a)),
                        C[1] + r_max * math.sin(yaw + math.radians(a))))
    cx = np.array([c[0] for c in corners])
    cy = np.array([c[1] for c in corners])
    i0 = max(int((cx.min() - 4 - gp[0]) / cell), 0)
    i1 = min(int((cx.max() + 4 - gp[0]) / cell) + 1, nx - 1)
    j0 = max(int((cy.min() - 4 - gp[1]) / cell), 0)
    j1 = min(int((cy.max() + 4 - gp[1]) / cell) + 1, ny - 1)
    ii = np.arange(i0, i1 + 1, stride)
    jj = np.arange(j0, j1 + 1, stride)
    sub = g[np.ix_(jj, ii)]
    X, Y = np.meshgrid(gp[0] + ii * cell, gp[1] + jj * cell)
    # normals from central differences
    dzdx = np.gradient(sub, stride * cell, axis=1)
    dzdy = np.gradient(sub, stride * cell, axis=0)
    n = np.stack([-dzdx, -dzdy, np.ones_like(sub)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    V = np.concatenate([np.stack([X - origin[0], Y - origin[1], sub], -1), n], -1)
    V = V.reshape(-1, 6).astype(np.float32)
    H, W = sub.shape
    qi, qj = np.meshgrid(np.arange(W - 1), np.arange(H - 1))
    ccx = X[:-1, :-1] + 0.5 * stride * cell
    ccy = Y[:-1, :-1] + 0.5 * stride * cell
    keep = _wedge(ccx, ccy, C, yaw, half_deg, r_max + stride * cell)
    a = (qj * W + qi)[keep]
    b, c, d = a + 1, a + W + 1, a + W
    idx = np.stack([a, b, c, a, c, d], -1).astype(np.int32).ravel()     # CCW from above
    return V, idx


def tufts(world, C, yaw, origin, half_deg, r_max):
    """Every tuft of the world's hash in the wedge: (n, 5) float32 cx, cy, z ground, r, height."""
    from drivers.sim.world import hash2, unit
    f32 = np.float32
    rs, ts, ro = world.row_spacing_m, world.tuft_spacing_m, world.row_offset_m
    xs = C[0] + r_max * np.cos(yaw + np.radians(np.linspace(-half_deg, half_deg, 9)))
    ys = C[1] + r_max * np.sin(yaw + np.radians(np.linspace(-half_deg, half_deg, 9)))
    xlo, xhi = min(xs.min(), C[0]) - 4, max(xs.max(), C[0]) + 4
    ylo, yhi = min(ys.min(), C[1]) - 4, max(ys.max(), C[1]) + 4
    k = np.arange(math.floor((ylo - ro) / rs), math.ceil((yhi - ro) / rs) + 1)
    j = np.arange(math.floor(xlo / ts), math.ceil(xhi / ts) + 1)
    K, J = np.meshgrid(k.astype(f32), j.astype(f32), indexing="ij")
    K, J = K.ravel(), J.ravel()
    h = hash2(K, J, world._salt ^ 0x51)
    cx = (J + f32(0.5)) * f32(ts) + (unit(h, 1) - f32(0.5)) * f32(0.05)
    cy = K * f32(rs) + f32(ro) + (unit(h, 2) - f32(0.5)) * f32(0.08)
    r = f32(0.045) + unit(h, 3) * f32(0.04)
    u4 = unit(h, 4)
    height = (f32(0.14) + f32(0.26) * unit(h) + np.where(u4 > f32(0.92), f32(0.12), f32(0.0)))
    height = height * f32(world.stubble_height) * f32(0.775)   # mean of the ragged top (0.55..1)
    keep = (u4 >= f32(world.stubble_gap)) & _wedge(cx, cy, C, yaw, half_deg, r_max)
    cx, cy, r, height = cx[keep], cy[keep], r[keep], height[keep]
    zg = world.ground(cx, cy)
    return np.stack([cx - origin[0], cy - origin[1], zg, r, height], -1).astype(np.float32)


def tuft_mesh(sides=8, rings=2):
    """A unit dome (radius 1, height 1) in the tuft's profile (1 - d^2)^(1/4): apex + ``rings``
    rings (the last on the ground); (vertices x,y,z,nx,ny,nz, indices) CCW from outside."""
    if rings == 1:
        fr = [1.0]
    else:
        fr = list(np.linspace(0.7, 1.0, rings))
    verts = [(0.0, 0.0, 1.0, 0.0, 0.0, 1.0)]
    for d in fr:
        z = (max(1.0 - d * d, 0.0)) ** 0.25
        for s in range(sides):
            a = 2 * math.pi * s / sides
            # the profile's slope gives the normal's tilt (steep near the rim)
            tilt = 0.4 + 0.6 * d
            verts.append((d * math.cos(a), d * math.sin(a), z, tilt * math.cos(a),
                          tilt * math.sin(a), 1.0 - 0.8 * d))
    idx = []
    for s in range(sides):
        idx += [0, 1 + s, 1 + (s + 1) % sides]
    for ri in range(rings - 1):
        b0, b1 = 1 + ri * sides, 1 + (ri + 1) * sides
        for s in range(sides):
            s1 = (s + 1) % sides
            idx += [b0 + s, b1 + s, b1 + s1, b0 + s, b1 + s1, b0 + s1]
    return np.array(verts, np.float32), np.array(idx, np.int32)


def obstacle_meshes(world, origin):
    """[(vertices, indices, BGR colour)] of the obstacles: boxes and 16-sided cylinders."""
    out = []
    for o in world.obstacles:
        cyl = o.shape in ("cylinder", "dome")
        c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
        x0, y0, z0, z1 = o.x - origin[0], o.y - origin[1], o.z0, o.z0 + o.height_m
        V, I = [], []
        if cyl:
            n = 16
            R = 0.5 * o.length_m
            for i in range(n):
                a0, a1 = 2 * math.pi * i / n, 2 * math.pi * (i + 1) / n
                for (a, z) in ((a0, z0), (a1, z0), (a1, z1), (a0, z1)):
                    V.append((x0 + R * math.cos(a), y0 + R * math.sin(a), z,
                              math.cos(a), math.sin(a), 0.0))
                b = 4 * i
                I += [b, b + 1, b + 2, b, b + 2, b + 3]
            top = len(V)
            V.append((x0, y0, z1, 0, 0, 1))
            for i in range(n):
                a = 2 * math.pi * i / n
                V.append((x0 + R * math.cos(a), y0 + R * math.sin(a), z1, 0, 0, 1))
            for i in range(n):
                I += [top, top + 1 + i, top + 1 + (i + 1) % n]
        else:
            L, W = 0.5 * o.length_m, 0.5 * o.width_m
            pts = [(-L, -W), (L, -W), (L, W), (-L, W)]
            P = [(x0 + u * c - v * s, y0 + u * s + v * c) for u, v in pts]
            for i in range(4):
                (ax, ay), (bx, by) = P[i], P[(i + 1) % 4]
                nx_, ny_ = by - ay, -(bx - ax)
                nn = math.hypot(nx_, ny_)
                b = len(V)
                for (px, py, z) in ((ax, ay, z0), (bx, by, z0), (bx, by, z1), (ax, ay, z1)):
                    V.append((px, py, z, nx_ / nn, ny_ / nn, 0.0))
                I += [b, b + 1, b + 2, b, b + 2, b + 3]
            b = len(V)
            for (px, py) in P:
                V.append((px, py, z1, 0, 0, 1))
            I += [b, b + 1, b + 2, b, b + 2, b + 3]
        out.append((np.array(V, np.float32), np.array(I, np.int32),
                    tuple(float(x) for x in o.colour)))
    return out


# ---------------------------------------------------------------------------------------------
# the GL scene
# ---------------------------------------------------------------------------------------------
class GLScene:
    def __init__(self, ctx, field, ground_stride=1, tuft_sides=8, tuft_rings=2,
                 with_tufts=True, half_deg=36.0, r_max=82.0, ground_mode=0):
        import moderngl
        self.ctx = ctx
        self.ground_mode = ground_mode
        self.field = field
        w = field.world
        cal = field.stereo_calibration
        C, R, _ = field._sensor_pose(cal.mount)
        yaw = math.atan2(R[1, 2], R[0, 2])
        self.origin = np.array([C[0], C[1]], np.float64)
        self.progs = {m: make_program(ctx, m) for m in sorted({ground_mode, 1, 2})}
        Vg, Ig = ground_mesh(w, C, yaw, self.origin, half_deg, r_max, ground_stride)
        self.n_ground_tris = len(Ig) // 3
        pg = self.progs[ground_mode]
        self.vao_ground = ctx.vertex_array(pg, [(ctx.buffer(Vg.tobytes()), *_pos_nrm(pg))],
                                           index_buffer=ctx.buffer(Ig.tobytes()))
        self.n_tufts = 0
        self.n_tuft_tris = 0
        self.vao_tuft = None
        if with_tufts:
            T = tufts(w, C, yaw, self.origin, half_deg, r_max)
            T = T[np.argsort(np.hypot(T[:, 0] + self.origin[0] - C[0],
                                      T[:, 1] + self.origin[1] - C[1]))]
            Vt, It = tuft_mesh(tuft_sides, tuft_rings)
            self.n_tufts = len(T)
            self.n_tuft_tris = len(T) * len(It) // 3
            self.vao_tuft = ctx.vertex_array(
                self.progs[1], [(ctx.buffer(Vt.tobytes()), "3f 3f", "in_pos", "in_nrm"),
                            (ctx.buffer(np.ascontiguousarray(T[:, :4]).tobytes()), "4f/i",
                             "in_inst"),
                            (ctx.buffer(np.ascontiguousarray(T[:, 4]).tobytes()), "f/i", "in_h")],
                index_buffer=ctx.buffer(It.tobytes()))
        self.obs = []
        self.n_obs_tris = 0
        for V, I, col in obstacle_meshes(w, self.origin):
            vao = ctx.vertex_array(self.progs[2], [(ctx.buffer(V.tobytes()), "3f 3f", "in_pos",
                                                    "in_nrm")],
                                   index_buffer=ctx.buffer(I.tobytes()))
            self.obs.append((vao, col[::-1]))                        # BGR -> RGB
            self.n_obs_tris += len(I) // 3
        # the world's own noise tiles and photo textures
        kp = w.kernel_params()
        self.tex = []
        for unit_, k in ((0, 0), (1, 1), (2, 2)):
            t = np.ascontiguousarray(kp["tiles"][k][:513 * 513].reshape(513, 513), np.float32)
            tx = ctx.texture((513, 513), 1, t.tobytes(), dtype="f4")
            tx.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tx.use(unit_)
            self.tex.append(tx)
        from drivers.sim.world import texture_pyramid
        for unit_, name in ((3, "grass"), (4, "gravel")):
            t = np.ascontiguousarray(texture_pyramid(name)[0], np.float32)
            tx = ctx.texture(t.shape[::-1], 1, t.tobytes(), dtype="f4")
            tx.build_mipmaps()
            tx.filter = (moderngl.NEAREST_MIPMAP_NEAREST, moderngl.NEAREST)
            tx.repeat_x = tx.repeat_y = True
            tx.use(unit_)
            self.tex.append(tx)
        sun = np.asarray(field.lighting.sun, np.float64)
        # shadow casters as render._render_view_fast picks them (within range of the camera)
        horiz = math.hypot(sun[0], sun[1])
        tan_e = sun[2] / horiz
        sh, reach = [], []
        for o in w.obstacles:
            r = 0.5 * min(o.length_m, o.width_m) if o.shape != "vehicle" else 0.42 * o.width_m + 0.3
            top = o.z0 + o.height_m
            rc = (top - (o.z0 - 0.3)) / tan_e + r
            if math.hypot(o.x - C[0], o.y - C[1]) - rc - r > r_max or len(sh) == 16:
                continue
            sh.append((o.x - self.origin[0], o.y - self.origin[1], r, top))
            reach.append(rc)
        for p in self.progs.values():
            for name, u in (("tile0", 0), ("tile1", 1), ("tile2", 2), ("grass", 3),
                            ("gravel", 4)):
                _set(p, name, u)
            _set(p, "origin", tuple(self.origin))
            _set(p, "sun", tuple(sun))
            _set(p, "straw", tuple(w.straw_bgr[::-1]))
            _set(p, "soil", tuple(w.soil_bgr[::-1]))
            _set(p, "litter", tuple(w.litter_bgr[::-1]))
            _set(p, "nsh", len(sh))
            if sh:
                _set(p, "sh", data=np.array(sh + [(0, 0, 0, 0)] * (16 - len(sh)),
                                            np.float32).tobytes())
                _set(p, "shreach", data=np.array(reach + [0] * (16 - len(reach)),
                                                 np.float32).tobytes())
        self.fbos = {}

    def _fbo(self, W, H):
        f = self.fbos.get((W, H))
        if f is None:
            ctx = self.ctx
            f = ctx.framebuffer(color_attachments=[ctx.renderbuffer((W, H), 4),
                                                   ctx.renderbuffer((W, H), 1, dtype="f4")],
                                depth_attachment=ctx.depth_renderbuffer((W, H)))
            self.fbos[(W, H)] = f
        return f

    def render(self, C, R, cam, far, seed=0, viewport=None):
        """One view: draw, glFinish, read back colour (H, W, 4) uint8 and z (H, W) float32
        (top row first, as the sim's images)."""
        import moderngl
        ctx = self.ctx
        W, H = (viewport if viewport else (cam.width, cam.height))
        sc = W / cam.width
        fbo = self._fbo(W, H)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)     # z = 0 where nothing is hit (sky)
        ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        for p in self.progs.values():
            _set(p, "Rt", data=np.ascontiguousarray(R, np.float32).tobytes())  # col-major: R^T
            _set(p, "Crel", (C[0] - self.origin[0], C[1] - self.origin[1], C[2]))
            _set(p, "K", (cam.fx * sc, cam.fy * sc, (cam.cx + 0.5) * sc, (cam.cy + 0.5) * sc))
            _set(p, "WH", (W, H))
            _set(p, "NF", (0.2, far))
            _set(p, "seed", seed)
        # near to far as far as it is cheap (early depth test): obstacles, tufts (sorted by
        # distance when built), then the ground they stand on
        for vao, col in self.obs:
            _set(self.progs[2], "ocolour", col)
            vao.render()
        if self.vao_tuft is not None:
            self.vao_tuft.render(instances=self.n_tufts)
        self.vao_ground.render()
        ctx.finish()
        t_draw = time.process_time()
        col = np.frombuffer(fbo.read(components=4, attachment=0, dtype="f1"), np.uint8)
        col = col.reshape(H, W, 4)[::-1]
        z = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), np.float32)
        z = z.reshape(H, W)[::-1]
        return col, z, t_draw


# ---------------------------------------------------------------------------------------------
def bench_views(scene, field, cal_attr, frames, offsets, far, viewport=None, scale=None):
    """CPU/wall ms per frame (all ``offsets`` views) + the read-back share of the CPU."""
    cal = getattr(field, cal_attr)
    cam = cal.camera
    if scale is not None:
        from drivers.sim.field import stereo_calibration
        cal = stereo_calibration(scale)
        cam = cal.camera
    cpu, wall, rb = [], [], []
    for i in range(frames + 1):
        field.step(0.1)
        poses = [field._sensor_pose(cal.mount, off)[:2] for off in offsets]
        t0, w0 = time.process_time(), time.perf_counter()
        r_ms = 0.0
        for v, (C, R) in enumerate(poses):
            col, z, t_draw = scene.render(C, R, cam, far, seed=i * 2 + v, viewport=viewport)
            r_ms += (time.process_time() - t_draw) * 1e3
        c_ms, w_ms = (time.process_time() - t0) * 1e3, (time.perf_counter() - w0) * 1e3
        if i:                                            # frame 0: warm-up (shader compile)
            cpu.append(c_ms)
            wall.append(w_ms)
            rb.append(r_ms)
    return {"cpu_ms": round(statistics.median(cpu), 1), "best_cpu_ms": round(min(cpu), 1),
            "wall_ms": round(statistics.median(wall), 1),
            "readback_cpu_ms": round(statistics.median(rb), 1)}, (col, z)


def _commit() -> str:
    try:
        c = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                           capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--",
                                "drivers/sim", "tools/bench_gl.py"], capture_output=True,
                               text=True, timeout=10).stdout.strip()
        return c + ("+dirty" if dirty else "")
    except Exception:                                         # noqa: BLE001 - informational
        return "unknown"


def run_numba(frames: int, cpu: int) -> dict:
    cmd = [sys.executable, str(ROOT / "tools" / "bench_sim.py"), "--frames", str(frames),
           "--stages", "--cpu", str(cpu), "--json"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1:] or ["failed"]}
    return json.loads(out.stdout)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--cpu", type=int, default=1, help="pin to this core (-1: leave it)")
    ap.add_argument("--lp-threads", type=int, default=0,
                    help="LP_NUM_THREADS for llvmpipe (0: rasterise on the calling thread)")
    ap.add_argument("--no-numba", action="store_true", help="skip the numba renderer's run")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.frames < 1:
        return _die("--frames must be >= 1")
    os.environ["LP_NUM_THREADS"] = str(a.lp_threads)        # before the GL driver loads
    if a.cpu >= 0:
        try:
            os.sched_setaffinity(0, {a.cpu})
        except (OSError, AttributeError) as e:
            return _die(f"cannot pin to core {a.cpu} ({e}); use --cpu -1")
    try:
        import moderngl
    except ImportError:
        return _die("moderngl is not installed (pip install 'fieldguard[gl]'); nothing measured")
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as e:                                    # noqa: BLE001 - one line, exit 2
        return _die(f"no headless EGL context ({type(e).__name__}: "
                    f"{str(e).splitlines()[0] if str(e) else ''}); Mesa's EGL "
                    "(libegl-mesa0, libgl1-mesa-dri) is needed; nothing measured")
    load0 = os.getloadavg()[0]
    res: dict = {"gl_renderer": ctx.info["GL_RENDERER"], "gl_version": ctx.info["GL_VERSION"],
                 "lp_num_threads": a.lp_threads, "frames": a.frames,
                 "cpu_affinity": sorted(os.sched_getaffinity(0)),
                 "clock": "time.process_time (CPU of the whole process) and wall, p50 over frames"}
    if not a.no_numba:
        res["numba"] = run_numba(a.frames, a.cpu)
    from drivers.sim import SimField
    res["commit"] = _commit()
    base = 0.75
    f = SimField("stubble-day", seed=0, sensors=("stereo", "laser", "rgbd"), stereo_scale=0.5)
    pair = ((0.0, 0.0, 0.0), (0.0, -base, 0.0))
    rows = {}
    variants = [("full", dict()), ("no_tufts", dict(with_tufts=False)),
                ("coarse", dict(ground_stride=4, tuft_sides=4, tuft_rings=1)),
                ("floor", dict(ground_stride=4, with_tufts=False, ground_mode=3)),
                ("bare", dict(ground_stride=4, with_tufts=False, ground_mode=4))]
    for name, kw in variants:
        sc = GLScene(ctx, f, **kw)
        rows[name] = v = {"ground_tris": sc.n_ground_tris, "tufts": sc.n_tufts,
                          "tuft_tris": sc.n_tuft_tris, "obstacle_tris": sc.n_obs_tris}
        v["pair_640x512"], _ = bench_views(sc, f, "stereo_calibration", a.frames, pair, 80.0)
        v["pair_1280x1024"], _ = bench_views(sc, f, "stereo_calibration", a.frames, pair, 80.0,
                                             scale=1.0)
        v["rgbd_640x480"], (col, z) = bench_views(sc, f, "depth_calibration", a.frames,
                                                  ((0.0, 0.0, 0.0),), 60.0)
        # the same geometry into an 80x64 viewport: nearly no fragments -> the vertex/setup cost
        v["pair_80x64_vertex_bound"], _ = bench_views(sc, f, "stereo_calibration", a.frames,
                                                      pair, 80.0, viewport=(80, 64))
        if name == "full":
            hit = z > 0
            v["rgbd_check"] = {"covered_share": round(float(hit.mean()), 3),
                               "z_min": round(float(z[hit].min()), 2) if hit.any() else None,
                               "z_max": round(float(z[hit].max()), 2) if hit.any() else None}
        del sc
    res["gl"] = rows
    # the rest of a stereo cycle with today's code (numba laser + vehicle step), in this process
    lt = []
    f.render_laser(0, 0)
    for i in range(a.frames * 2):
        t0 = time.process_time()
        f.step(0.1)
        f.render_laser(i, i)
        lt.append((time.process_time() - t0) * 1e3)
    res["numba_laser_plus_step_cpu_ms"] = round(statistics.median(lt), 1)
    res["gl_pair_640x512_plus_laser_step_cpu_ms"] = round(
        rows["full"]["pair_640x512"]["cpu_ms"] + res["numba_laser_plus_step_cpu_ms"], 1)
    res["load_avg_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"GL: {res['gl_renderer']} | LP_NUM_THREADS={a.lp_threads} | cpu {res['cpu_affinity']}"
          f" | commit {res['commit']} | load {res['load_avg_1min']}")
    nb = res.get("numba", {})
    if nb and "error" not in nb:
        print(f"numba: pair+laser+step {nb['stereo_640x512_cpu_ms']} | pair "
              f"{nb['stereo_640x512_pair_only_cpu_ms']} | 1280 pair {nb['stereo_1280x1024_cpu_ms']}"
              f" | rgbd {nb['rgbd_640x480_cpu_ms']} (CPU ms p50)")
    for name, v in rows.items():
        print(f"{name}: ground {v['ground_tris']} tris, {v['tufts']} tufts ({v['tuft_tris']} tris),"
              f" obstacles {v['obstacle_tris']} tris")
        for k in ("pair_640x512", "pair_1280x1024", "rgbd_640x480", "pair_80x64_vertex_bound"):
            print(f"   {k:26s} cpu {v[k]['cpu_ms']:7.1f}  wall {v[k]['wall_ms']:7.1f}  "
                  f"(read-back {v[k]['readback_cpu_ms']})")
    print(f"GL pair 640x512 + numba laser + step: {res['gl_pair_640x512_plus_laser_step_cpu_ms']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
