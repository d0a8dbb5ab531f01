"""The simulated world: a deterministic 3-D height field with an albedo function.

Everything is evaluated analytically and vectorised at sample points (no giant arrays):

- ground: a sum of seeded sinusoids (a few cm to ~0.2 m over metres);
- stubble tufts (stubble world): rows along x every 0.75 m, a tuft every ``TUFT_SPACING_M`` along
  the row, position/size/height from an integer hash of (row, index), a clump-shaped profile;
- bushes and leaves (greenhouse world): rows of pepper plants either side of a straight path;
- obstacles: vertical extrusions (cylinders, boxes, a stacked person) evaluated only where a
  caller's samples come near them (``Obstacle.block`` tells the renderer which samples those are).

World frame: x along the field rows, y left, z up, metres. Material codes per sample:
``MAT_GROUND``, ``MAT_STUBBLE``, ``MAT_BUSH``, ``MAT_LEAF``, and ``MAT_OBSTACLE + k`` for
obstacle k.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

MAT_SKY = -1
MAT_GROUND = 0
MAT_STUBBLE = 1
MAT_BUSH = 2
MAT_LEAF = 3
MAT_OBSTACLE = 16

ROW_SPACING_M = 0.75
GROUND_CELL_M = 0.2
TUFT_SPACING_M = 0.22
ASSETS = Path(__file__).resolve().parent / "assets"


# ---------------------------------------------------------------------------------------------
# hashing and noise (deterministic, integer based, platform independent)
# ---------------------------------------------------------------------------------------------
def _mix(h: np.ndarray) -> np.ndarray:
    """A 32-bit integer finaliser (murmur3 fmix32). uint32 in, uint32 out, wraps silently."""
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> np.uint32(13))
    h = h * np.uint32(0xC2B2AE35)
    h = h ^ (h >> np.uint32(16))
    return h


def hash2(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    """uint32 hash of two integer lattice coordinates and a salt."""
    a = np.asarray(i).astype(np.int64).astype(np.uint32)
    b = np.asarray(j).astype(np.int64).astype(np.uint32)
    h = a * np.uint32(0x9E3779B1) ^ (b * np.uint32(0x85EBCA77) + np.uint32(salt & 0xFFFFFFFF))
    return _mix(h)


def unit(h: np.ndarray, k: int = 0) -> np.ndarray:
    """float32 in [0, 1) from a hash (k picks an independent stream)."""
    if k:
        h = _mix(h + np.uint32(k * 0x27D4EB2F & 0xFFFFFFFF))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


_TILE = 512


@lru_cache(maxsize=64)
def _noise_tile(salt: int) -> np.ndarray:
    """A seeded 512x512 tile of uniform values (periodic lattice for value noise), padded by one
    row and column so bilinear neighbours need no wrap, flattened, and one value more (the
    tile's first) after the padded rows: the compiled noise (fastrender.value_noise) reads the
    lower row at +514 / +515 where this module's reference reads +513 / +514, which at the
    tile's last cell is one past the padded rows. Without that value it read whatever lay in
    memory after the array, and the same drive rendered differently from run to run (twenty-
    fourth session; the reads themselves are left as they are: every texture, test and shipped
    model was made with them)."""
    t = np.random.default_rng(salt & 0xFFFFFFFF).random((_TILE, _TILE), dtype=np.float32)
    flat = np.pad(t, ((0, 1), (0, 1)), mode="wrap").ravel()
    return np.append(flat, flat[:1])


def value_noise(x: np.ndarray, y: np.ndarray, cell_m: float, salt: int) -> np.ndarray:
    """Smooth value noise in [0, 1): seeded lattice values (period 512 cells), smoothstep-bilinear
    interpolated."""
    tile = _noise_tile(int(salt))
    fx = np.asarray(x, np.float32) / np.float32(cell_m)
    fy = np.asarray(y, np.float32) / np.float32(cell_m)
    ix = np.floor(fx)
    iy = np.floor(fy)
    tx = fx - ix
    ty = fy - iy
    tx = tx * tx * (3 - 2 * tx)
    ty = ty * ty * (3 - 2 * ty)
    i0 = (iy.astype(np.int64) & (_TILE - 1)) * (_TILE + 1) + (ix.astype(np.int64) & (_TILE - 1))
    v00 = tile[i0]
    v10 = tile[i0 + 1]
    v01 = tile[i0 + _TILE + 1]
    v11 = tile[i0 + _TILE + 2]
    a = v00 + (v10 - v00) * tx
    b = v01 + (v11 - v01) * tx
    return (a + (b - a) * ty).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# textures (real photographs, grey, with a mip pyramid)
# ---------------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def texture_pyramid(name: str) -> tuple[np.ndarray, ...]:
    img = cv2.imread(str(ASSETS / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(ASSETS / f"{name}.png")
    t = img.astype(np.float32) / 255.0
    t = t / max(float(t.mean()), 1e-3)         # mean 1: a multiplicative albedo modulation
    levels = [t]
    while levels[-1].shape[0] > 8:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


@lru_cache(maxsize=None)
def _flat_pyramid(name: str):
    """All mip levels of a (square, power-of-two) texture in one flat array + per-level offsets."""
    pyr = texture_pyramid(name)
    sizes = np.array([p.shape[0] for p in pyr], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes * sizes)[:-1]]).astype(np.int64)
    return np.concatenate([p.ravel() for p in pyr]), sizes, offsets


def sample_texture(name: str, u_m: np.ndarray, v_m: np.ndarray, metres_per_texel: float,
                   footprint_m: np.ndarray | float | None = None) -> np.ndarray:
    """Tile texture ``name`` over the plane, nearest texel at the mip level that matches the
    pixel footprint (so far-away ground averages instead of aliasing into noise)."""
    flat, sizes, offsets = _flat_pyramid(name)
    u = np.asarray(u_m, dtype=np.float32) / np.float32(metres_per_texel)
    v = np.asarray(v_m, dtype=np.float32) / np.float32(metres_per_texel)
    if footprint_m is None:
        lev = np.zeros(u.shape, np.int64)
    else:
        ratio = np.maximum(np.asarray(footprint_m, np.float32) / np.float32(metres_per_texel),
                           np.float32(1e-6))
        lev = np.clip(np.floor(np.log2(ratio) + np.float32(0.5)), 0, len(sizes) - 1)
        lev = np.broadcast_to(lev.astype(np.int64), u.shape)
    scale = np.ldexp(np.float32(1.0), -lev).astype(np.float32)
    n = sizes[lev]
    iu = np.floor(u * scale).astype(np.int64) & (n - 1)
    iv = np.floor(v * scale).astype(np.int64) & (n - 1)
    return flat[offsets[lev] + iv * n + iu]


# ---------------------------------------------------------------------------------------------
# obstacles
# ---------------------------------------------------------------------------------------------
@dataclass
class Obstacle:
    """A solid on the ground: a vertical extrusion of its footprint with a height profile.

    ``shape``: "cylinder" (length = width = diameter), "box", "person", "person-crouching",
    "vehicle". ``colour`` is BGR in [0, 1]; ``shiny``/``dark`` give RGB-D holes.
    """

    id: str
    cls: str
    shape: str
    x: float
    y: float
    yaw_deg: float
    length_m: float
    width_m: float
    height_m: float
    colour: tuple[float, float, float]
    colour2: tuple[float, float, float] = (0.2, 0.2, 0.2)   # second colour (pants, windows, hoops)
    texture: str | None = None        # "stubble" for the look-alike
    shiny: bool = False
    z0: float = 0.0                   # ground height at the footprint centre (set by the world)
    # scene bookkeeping (scenes.py): where it was put and how it stands
    tone: str = ""                    # "hi-vis" | "field-coloured" | "own" | "other" | "animal"
    placement: str = ""               # "in-path" | "beside" | "between-lanes" | "headland" | "crossing" | "at-boot"
    pose: str = ""                    # "standing" | "crouching" | "lying" ("" for things)
    # a walker (person or animal crossing): it stands at (x, y) until the vehicle's route
    # distance reaches ``walk_trigger_s``, then walks at (vx_mps, vy_mps) for ``walk_time_s``,
    # then stands again. vx = vy = 0: it never moves.
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    walk_trigger_s: float = 0.0
    walk_time_s: float = 0.0

    def __post_init__(self):
        self.x_start, self.y_start = float(self.x), float(self.y)
        self.walk_t0_s: float | None = None

    @property
    def moving(self) -> bool:
        """A walker (it may be standing still just now)."""
        return bool(self.vx_mps or self.vy_mps) and self.walk_time_s > 0

    def velocity_now(self, time_s: float) -> tuple[float, float]:
        """World (vx, vy) at time_s: its walking velocity while it walks, else 0."""
        if not self.moving or self.walk_t0_s is None:
            return 0.0, 0.0
        if 0.0 <= time_s - self.walk_t0_s < self.walk_time_s:
            return self.vx_mps, self.vy_mps
        return 0.0, 0.0

    @property
    def radius(self) -> float:
        """Radius of a circle around the footprint (for culling)."""
        return 0.5 * math.hypot(self.length_m, self.width_m) + 0.02

    def footprint_points(self, n: int = 11) -> np.ndarray:
        """(N, 2) world points covering the footprint (an n x n grid, kept where it stands)."""
        u = np.linspace(-0.5 * self.length_m, 0.5 * self.length_m, n)
        v = np.linspace(-0.5 * self.width_m, 0.5 * self.width_m, n)
        uu, vv = np.meshgrid(u, v)
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        x = (self.x + uu * c - vv * s).ravel()
        y = (self.y + uu * s + vv * c).ravel()
        inside = self.height(x.astype(np.float32), y.astype(np.float32)) > 0
        return np.stack([x[inside], y[inside]], 1)

    def local(self, x, y):
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        dx = x - np.float32(self.x)
        dy = y - np.float32(self.y)
        return (dx * np.float32(c) + dy * np.float32(s)), (-dx * np.float32(s) + dy * np.float32(c))

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Top height above z0 (0 outside the footprint)."""
        u, v = self.local(x, y)
        L, W, H = self.length_m, self.width_m, self.height_m
        f32 = np.float32
        if self.shape == "cylinder":
            r2 = (u * u + v * v) / f32((0.5 * L) ** 2)
            return np.where(r2 <= 1.0, f32(H), f32(0.0))
        if self.shape == "box":
            inside = (np.abs(u) <= f32(0.5 * L)) & (np.abs(v) <= f32(0.5 * W))
            return np.where(inside, f32(H), f32(0.0))
        if self.shape == "vehicle":
            inside = (np.abs(u) <= f32(0.5 * L)) & (np.abs(v) <= f32(0.5 * W))
            # cab between 0.05 L and 0.45 L from the front (u > 0 is the front), bonnet and tray
            cab = (u < f32(0.22 * L)) & (u > f32(-0.18 * L)) & (np.abs(v) <= f32(0.46 * W))
            h = np.where(cab, f32(H), f32(0.6 * H))
            return np.where(inside, h, f32(0.0))
        if self.shape == "dome":
            # a lying person, an animal: an elliptic footprint with a half-ellipsoid top
            e = (u / f32(0.5 * L)) ** 2 + (v / f32(0.5 * W)) ** 2
            return np.where(e <= 1.0, f32(H) * np.sqrt(np.maximum(f32(1.0) - e, f32(0.0)))
                            + f32(0.25 * H), f32(0.0)).astype(f32) * f32(0.8)
        if self.shape in ("person", "person-crouching"):
            # stacked ellipses: body/shoulders, then the head
            e_body = (u / f32(0.5 * L)) ** 2 + (v / f32(0.5 * W)) ** 2
            e_head = (u / f32(0.11)) ** 2 + (v / f32(0.10)) ** 2
            body_h = H - 0.27 if self.shape == "person" else H - 0.24
            h = np.where(e_body <= 1.0, f32(body_h), f32(0.0))
            # legs/hips narrower than shoulders: cut the ellipse corners below the shoulders
            return np.where(e_head <= 1.0, f32(H), h)
        raise ValueError(self.shape)

    def side_normal(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outward horizontal unit normal (world) of the side surface nearest (x, y)."""
        u, v = self.local(x, y)
        if self.shape in ("box", "vehicle"):
            au = np.abs(u) / np.float32(0.5 * self.length_m)
            av = np.abs(v) / np.float32(0.5 * self.width_m)
            nu = np.where(au >= av, np.sign(u), 0.0).astype(np.float32)
            nv = np.where(au < av, np.sign(v), 0.0).astype(np.float32)
        else:
            n = np.sqrt(u * u + v * v) + np.float32(1e-6)
            nu, nv = u / n, v / n
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        return nu * np.float32(c) - nv * np.float32(s), nu * np.float32(s) + nv * np.float32(c)

    def albedo(self, x, y, z, footprint) -> np.ndarray:
        """BGR albedo in [0, 1] at surface points (z is world height)."""
        zr = (np.asarray(z, np.float32) - np.float32(self.z0))
        n = zr.shape[0]
        c1 = np.array(self.colour, np.float32)
        c2 = np.array(self.colour2, np.float32)
        col = np.broadcast_to(c1, (n, 3)).copy()
        H = self.height_m
        if self.shape == "person":
            col[zr < 0.85] = c2                                  # trousers
            col[zr > H - 0.27] = (0.45, 0.55, 0.75)              # head (skin)
            col[zr > H - 0.08] = (0.12, 0.12, 0.15)              # hair / hat
        elif self.shape == "person-crouching":
            col[zr < 0.45] = c2
            col[zr > H - 0.24] = (0.45, 0.55, 0.75)
        elif self.shape == "vehicle":
            u, v = self.local(x, y)
            cab = (u < 0.22 * self.length_m) & (u > -0.18 * self.length_m)
            col[cab & (zr > 0.62 * H) & (zr < 0.95 * H)] = c2     # windows
            col[zr < 0.4] = (0.08, 0.08, 0.08)                    # wheels / shadow under body
        elif self.shape == "dome":
            col[zr < 0.3 * H] = c2                               # legs / underside
        elif self.cls in ("drum", "barrel", "look-alike-drum"):
            hoop = (np.abs(zr - H / 3) < 0.025) | (np.abs(zr - 2 * H / 3) < 0.025)
            col[hoop] = c2 if self.texture is None else c1 * 0.8
        elif self.cls in ("crate", "look-alike-crate", "box"):
            # slats / handles: a darker band
            band = (np.abs(zr - 0.75 * H) < 0.03)
            col[band] = c2
        if self.texture == "stubble":
            t = sample_texture("grass", (np.asarray(x) + np.asarray(y)) * 1.0, zr * 0.25,
                               0.0025, footprint)
            col *= (0.55 + 0.45 * t)[:, None]
        else:
            t = sample_texture("gravel", np.asarray(x) + np.asarray(y), zr, 0.004, footprint)
            col *= (0.9 + 0.1 * t)[:, None]
        return np.clip(col, 0.0, 1.5)


# ---------------------------------------------------------------------------------------------
# worlds
# ---------------------------------------------------------------------------------------------
@dataclass
class World:
    """A deterministic world. ``kind`` is "stubble" or "greenhouse"."""

    kind: str
    seed: int
    obstacles: list[Obstacle] = field(default_factory=list)
    waves: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    # (kx, ky, phase, amplitude) rows for the ground undulation
    row_offset_m: float = ROW_SPACING_M / 2
    path_half_width_m: float = 0.6           # greenhouse
    bush_period_m: float = 2.2               # greenhouse: path + bush row
    sky_bgr: tuple[float, float, float] = (0.95, 0.80, 0.62)
    horizon_bgr: tuple[float, float, float] = (0.93, 0.90, 0.85)
    max_terrain_m: float = 0.0               # upper bound of ground + stubble/bush height
    # contour banks: (nx, ny, offset, height, sigma) rows: a ridge of height ``height`` and
    # Gaussian half-width ``sigma`` along the line nx*x + ny*y = offset (n a unit vector)
    banks: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    # the stubble (defaults: the stubble-day field)
    row_spacing_m: float = ROW_SPACING_M
    tuft_spacing_m: float = TUFT_SPACING_M
    stubble_height: float = 1.0              # scale of the tufts' heights
    stubble_gap: float = 0.1                 # fraction of tuft places left empty
    straw_bgr: tuple[float, float, float] = (0.40, 0.63, 0.78)
    soil_bgr: tuple[float, float, float] = (0.33, 0.40, 0.50)
    litter_bgr: tuple[float, float, float] = (0.42, 0.62, 0.74)
    litter: float = 0.0                      # more (>0) or less (<0) straw litter on the soil
    bush_x_range: tuple[float, float] | None = None   # greenhouse: bushes only for x in range
    time_s: float = 0.0                      # the world's clock (walkers, cloud shadows)
    # (x0, y0, x1, y1): the ground is the analytic undulation sampled on a GROUND_CELL_M grid
    # over this box and interpolated bilinearly (the renderer's compiled loops read the same
    # grid, so camera, laser, vehicle and truth share one ground). None: analytic everywhere.
    extent: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        self._salt = (self.seed * 2654435761 + 12345) & 0xFFFFFFFF
        amp = np.abs(self.waves[:, 3]).sum() if len(self.waves) else 0.0
        amp += float(np.abs(self.banks[:, 3]).max()) if len(self.banks) else 0.0
        top = 0.55 * max(self.stubble_height, 1.0) if self.kind == "stubble" else 1.35
        self.max_terrain_m = float(amp + top)
        self.ground_max_m = float(amp)
        for o in self.obstacles:
            o.z0 = float(self.ground(np.float32(o.x), np.float32(o.y)))

    # ---- time ------------------------------------------------------------------------------
    def advance(self, time_s: float, route_s: float) -> list[int]:
        """Set the world's clock; walkers whose trigger the vehicle's route distance has passed
        walk. Returns the indices of the obstacles that moved."""
        self.time_s = float(time_s)
        moved = []
        for k, o in enumerate(self.obstacles):
            if not o.moving:
                continue
            if o.walk_t0_s is None:
                if route_s < o.walk_trigger_s:
                    continue
                o.walk_t0_s = self.time_s
            tw = min(max(self.time_s - o.walk_t0_s, 0.0), o.walk_time_s)
            x, y = o.x_start + o.vx_mps * tw, o.y_start + o.vy_mps * tw
            if (x, y) != (o.x, o.y):
                o.x, o.y = x, y
                o.z0 = float(self.ground(np.float32(x), np.float32(y)))
                moved.append(k)
        return moved

    # ---- geometry --------------------------------------------------------------------------
    def ground(self, x, y):
        """Ground height at points (the grid's bilinear interpolation, see ``extent``)."""
        if self.extent is None:
            return self.ground_analytic(x, y)
        G, gp = self.ground_grid()
        fx = (np.asarray(x, np.float64) - gp[0]) * gp[2]
        fy = (np.asarray(y, np.float64) - gp[1]) * gp[2]
        nx, ny = int(gp[3]), int(gp[4])
        fx = np.clip(fx, 0.0, nx - 1.000001)
        fy = np.clip(fy, 0.0, ny - 1.000001)
        ix = fx.astype(np.int64)
        iy = fy.astype(np.int64)
        tx, ty = fx - ix, fy - iy
        i0 = iy * nx + ix
        a = G[i0] + (G[i0 + 1] - G[i0]) * tx
        b = G[i0 + nx] + (G[i0 + nx + 1] - G[i0 + nx]) * tx
        return (a + (b - a) * ty).astype(np.float32)

    def ground_grid(self):
        """(flat float64 grid, (x0, y0, 1/cell, nx, ny)) of the ground over ``extent``."""
        g = getattr(self, "_ground_grid", None)
        if g is None:
            x0, y0, x1, y1 = self.extent
            nx = int(math.ceil((x1 - x0) / GROUND_CELL_M)) + 2
            ny = int(math.ceil((y1 - y0) / GROUND_CELL_M)) + 2
            xs = x0 + np.arange(nx) * GROUND_CELL_M
            ys = y0 + np.arange(ny) * GROUND_CELL_M
            X, Y = np.meshgrid(xs, ys)
            G = self.ground_analytic(X, Y).astype(np.float64).ravel()
            g = (G, np.array([x0, y0, 1.0 / GROUND_CELL_M, nx, ny], np.float64))
            self._ground_grid = g
        return g

    def ground_coarse_max(self, k: int = 5) -> np.ndarray:
        """(ceil(ny / k), ceil(nx / k)) float64: the highest ground-grid node of each k x k block
        of grid cells, its far edge included, so the bilinear ground anywhere in the block is
        at most this (the laser's kernel skips beam samples above it + the tallest tuft)."""
        G, gp = self.ground_grid()
        nx, ny = int(gp[3]), int(gp[4])
        g = G.reshape(ny, nx)
        cy, cx = -(-ny // k), -(-nx // k)
        pad = np.full((cy * k + 1, cx * k + 1), -np.inf)
        pad[:ny, :nx] = g
        out = np.full((cy, cx), -np.inf)
        for dy in range(k + 1):
            for dx in range(k + 1):
                out = np.maximum(out, pad[dy:dy + cy * k:k, dx:dx + cx * k:k])
        return out

    def ground_analytic(self, x, y):
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        z = np.zeros(np.broadcast(x, y).shape, np.float32)
        for kx, ky, ph, a in self.waves:
            z += np.float32(a) * np.sin(x * np.float32(kx) + y * np.float32(ky) + np.float32(ph))
        for nx, ny, off, hb, sg in self.banks:
            d = (x * np.float32(nx) + y * np.float32(ny) - np.float32(off)) / np.float32(sg)
            z += np.float32(hb) * np.exp(-d * d)
        return z

    def _tufts(self, x, y):
        """Stubble tuft height above the ground (0 between tufts)."""
        f32 = np.float32
        rs, ts = f32(self.row_spacing_m), f32(self.tuft_spacing_m)
        k = np.floor((y - f32(self.row_offset_m)) / rs + f32(0.5))
        j = np.floor(x / ts)
        h = hash2(k, j, self._salt ^ 0x51)
        cx = (j + f32(0.5)) * ts + (unit(h, 1) - f32(0.5)) * f32(0.05)
        cy = k * rs + f32(self.row_offset_m) + (unit(h, 2) - f32(0.5)) * f32(0.08)
        r = f32(0.045) + unit(h, 3) * f32(0.04)
        u4 = unit(h, 4)
        height = f32(0.14) + f32(0.26) * unit(h) + np.where(u4 > f32(0.92), f32(0.12), f32(0.0))
        if self.stubble_height != 1.0:
            height = height * f32(self.stubble_height)
        height = np.where(u4 < f32(self.stubble_gap), f32(0.0), height)   # gaps in the row
        d2 = ((x - cx) ** 2 + (y - cy) ** 2) / (r * r)
        prof = np.clip(f32(1.0) - d2, f32(0.0), f32(1.0))
        # stalks: every 2 cm cell of the clump has its own height -> a ragged, stalky top
        rag = unit(hash2(np.floor(x * f32(50.0)), np.floor(y * f32(50.0)), self._salt ^ 0x5A))
        return height * np.sqrt(np.sqrt(prof)) * (f32(0.55) + f32(0.45) * rag)

    def _bushes(self, x, y):
        """Greenhouse: pepper-bush rows either side of each path; (height, is_leaf_litter)."""
        f32 = np.float32
        P = f32(self.bush_period_m)
        hw = f32(self.path_half_width_m)
        # distance into the bush row from the nearest path edge; rows centred at hw + 0.5 + kP
        yy = y - (hw + f32(0.5))
        kk = np.floor(yy / P + f32(0.5))
        dy = yy - kk * P                                   # -1.1 .. 1.1, bush |dy| < 0.5
        j = np.floor(x / f32(0.45))
        hb = hash2(kk, j, self._salt ^ 0xB5)
        plant_h = f32(0.85) + f32(0.25) * unit(hb)
        cx = (j + f32(0.5)) * f32(0.45) + (unit(hb, 1) - f32(0.5)) * f32(0.1)
        leafy = value_noise(x, y + f32(3.1) * x * f32(0.0), 0.09, self._salt ^ 0x77)
        wid = f32(0.5) + f32(0.1) * (leafy - f32(0.5))
        e = (dy / wid) ** 2 + ((x - cx) / f32(0.42)) ** 2 * f32(0.35)
        prof = np.clip(f32(1.0) - e, f32(0.0), f32(1.0))
        hbush = plant_h * np.sqrt(prof) * (f32(0.8) + f32(0.35) * leafy)
        # low leaves overhanging the path: patches within 0.35 m of the bush edge, on the path side
        jl = np.floor(x / f32(0.6))
        hl = hash2(kk, jl * 2 + (dy > 0), self._salt ^ 0x1EAF)
        reach = f32(0.12) + f32(0.25) * unit(hl, 1)
        cxl = (jl + f32(0.5)) * f32(0.6)
        into_path = np.abs(dy) - f32(0.5)                   # >0 outside the bush, towards the path
        leaf_on = (unit(hl) > f32(0.45)) & (into_path > 0) & (into_path < reach) & \
                  (np.abs(x - cxl) < f32(0.22))
        hleaf = np.where(leaf_on, (f32(0.04) + f32(0.14) * leafy) *
                         (f32(1.0) - into_path / reach), f32(0.0))
        if self.bush_x_range is not None:
            inside = (x >= f32(self.bush_x_range[0])) & (x <= f32(self.bush_x_range[1]))
            hbush = np.where(inside, hbush, f32(0.0))
            hleaf = np.where(inside, hleaf, f32(0.0))
        return hbush, hleaf

    def terrain(self, x, y):
        """Ground plus stubble / bushes, no obstacles: (height, material)."""
        g = self.ground(x, y)
        if self.kind == "stubble":
            t = self._tufts(x, y)
            mat = np.where(t > 0.0, MAT_STUBBLE, MAT_GROUND).astype(np.int16)
            return g + t, mat
        hb, hl = self._bushes(x, y)
        mat = np.where(hb > 0.0, MAT_BUSH, np.where(hl > 0.0, MAT_LEAF, MAT_GROUND)).astype(np.int16)
        return g + np.maximum(hb, hl), mat

    def obstacle_heights(self, x, y, h, mat, only=None):
        """Raise h/mat in place where an obstacle stands (all points; for small point sets)."""
        for k, o in enumerate(self.obstacles):
            if only is not None and k not in only:
                continue
            m = ((x - np.float32(o.x)) ** 2 + (y - np.float32(o.y)) ** 2) <= np.float32(o.radius ** 2)
            if not m.any():
                continue
            ho = o.height(x[m], y[m]) + np.float32(o.z0)
            inside = o.height(x[m], y[m]) > 0
            hm = h[m]
            up = inside & (ho >= hm)
            hm[up] = ho[up]
            h[m] = hm
            mm = mat[m]
            mm[up] = MAT_OBSTACLE + k
            mat[m] = mm
        return h, mat

    def height(self, x, y, stubble: bool = True):
        """Full height field (ground + stubble/bushes + obstacles) at points: (height, material)."""
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        if stubble:
            h, mat = self.terrain(x, y)
        else:
            h = self.ground(x, y)
            mat = np.zeros(h.shape, np.int16)
        return self.obstacle_heights(x, y, h.copy(), mat.copy())

    # ---- appearance -------------------------------------------------------------------------
    def albedo(self, x, y, z, mat, footprint) -> np.ndarray:
        """BGR albedo in [0, ~1.2] at surface points. All arrays 1-D of the same length."""
        n = x.shape[0]
        out = np.zeros((n, 3), np.float32)
        f32 = np.float32
        m = mat == MAT_GROUND
        if m.any():
            xm, ym, fm = x[m], y[m], footprint[m]
            patch = value_noise(xm, ym, 3.0, self._salt ^ 0x9)
            fine = value_noise(xm, ym, 0.35, self._salt ^ 0xA)
            grav = sample_texture("gravel", xm, ym, 0.004, fm)
            if self.kind == "stubble":
                straw = sample_texture("grass", ym * 0.7 + 3.3, xm * 0.7, 0.003, fm)
                soil = np.array(self.soil_bgr, f32)               # BGR grey-brown soil
                litter = np.array(self.litter_bgr, f32)           # pale straw litter
                w = np.clip((straw - 0.95) * 1.6 + (patch - 0.5) * 0.8 + f32(self.litter),
                            0, 1)[:, None]
                c = soil * (1 - w) + litter * w
                c = c * (0.75 + 0.25 * grav)[:, None] * (0.85 + 0.3 * fine)[:, None]
            else:
                soil = np.array([0.40, 0.45, 0.54], f32)          # brown ground (paper Table 1)
                c = soil * (0.7 + 0.3 * grav)[:, None] * (0.85 + 0.3 * patch)[:, None]
            out[m] = c
        m = mat == MAT_STUBBLE
        if m.any():
            xm, ym, zm, fm = x[m], y[m], z[m], footprint[m]
            g = self.ground(xm, ym)
            rel = np.clip((zm - g) / (0.4 * self.stubble_height), 0, 1)
            streak = sample_texture("grass", (xm - ym) * 0.9, (zm - g) * 0.12, 0.002, fm)
            var = value_noise(xm, ym, 1.5, self._salt ^ 0xB)
            straw = np.array(self.straw_bgr, f32)                 # BGR straw (sorghum stubble)
            c = straw * (0.55 + 0.45 * rel)[:, None] * (0.6 + 0.4 * streak)[:, None]
            c = c * (0.85 + 0.3 * var)[:, None]
            out[m] = c
        m = (mat == MAT_BUSH) | (mat == MAT_LEAF)
        if m.any():
            xm, ym, zm, fm = x[m], y[m], z[m], footprint[m]
            leaf = value_noise(xm + zm * 0.7, ym - zm * 0.5, 0.05, self._salt ^ 0xC)
            tex = sample_texture("grass", xm * 0.8 + ym, zm * 0.8 + ym * 0.3, 0.002, fm)
            green = np.array([0.17, 0.25, 0.17], f32)             # paper Table 1, BGR
            c = green * (0.6 + 0.8 * leaf)[:, None] * (0.7 + 0.3 * tex)[:, None]
            # red peppers hanging in the bushes at 0.25-0.9 m
            cell = 0.14
            ix = np.floor(xm / cell)
            iz = np.floor(zm / cell)
            iy = np.floor(ym / cell)
            hp = hash2(ix * 7919 + iy, iz, self._salt ^ 0xD)
            px = (ix + 0.5) * cell + (unit(hp, 1) - 0.5) * 0.05
            py = (iy + 0.5) * cell + (unit(hp, 3) - 0.5) * 0.05
            pz = (iz + 0.5) * cell + (unit(hp, 2) - 0.5) * 0.05
            d2 = (xm - px) ** 2 + (ym - py) ** 2 + ((zm - pz) * 0.8) ** 2
            pep = (unit(hp) > 0.5) & (d2 < 0.045 ** 2) & (zm > 0.25) & (zm < 0.95) & \
                  (mat[m] == MAT_BUSH)
            c[pep] = np.array([0.16, 0.10, 0.55], f32)
            out[m] = c
        for k, o in enumerate(self.obstacles):
            m = mat == MAT_OBSTACLE + k
            if m.any():
                out[m] = o.albedo(x[m], y[m], z[m], footprint[m])
        return out

    # ---- the compiled renderer's view of the world (drivers/sim/fastrender.py) ---------------
    def kernel_params(self) -> dict:
        """Arrays the compiled loops read (cached; obstacle rows are rebuilt per call since
        walkers move)."""
        kp = getattr(self, "_kp", None)
        if kp is None:
            G, gp = self.ground_grid()
            s = self._salt
            tp = np.array([self.row_offset_m, self.row_spacing_m, self.tuft_spacing_m,
                           s ^ 0x51, s ^ 0x5A, self.stubble_height, self.stubble_gap,
                           *self.straw_bgr, *self.soil_bgr, *self.litter_bgr, self.litter],
                          np.float64)
            xr = self.bush_x_range or (-1e9, 1e9)
            bp = np.array([self.path_half_width_m, self.bush_period_m, s ^ 0xB5, s ^ 0x1EAF,
                           xr[0], xr[1]], np.float64)
            tiles = np.stack([_noise_tile(s ^ k) for k in (0x9, 0xA, 0xB, 0xC, 0xC10D)])
            grass, sizes, offsets = _flat_pyramid("grass")
            gravel, sizes2, offsets2 = _flat_pyramid("gravel")
            assert np.array_equal(sizes, sizes2) and np.array_equal(offsets, offsets2)
            kp = {"kind": 0 if self.kind == "stubble" else 1, "G": G, "gp": gp, "tp": tp,
                  "bp": bp, "tile77": _noise_tile(s ^ 0x77), "tiles": tiles,
                  "grass": grass, "gravel": gravel, "sizes": sizes, "offsets": offsets,
                  "top_m": 0.53 * self.stubble_height if self.kind == "stubble" else 1.27,
                  "salt": s, "Gc": self.ground_coarse_max()}
            self._kp = kp
        return kp

    def obstacle_rows(self, idx=None) -> np.ndarray:
        """(n, 19) float64 rows of the obstacles (all, or those in ``idx``) for the kernels."""
        shapes = {"cylinder": 0, "box": 1, "vehicle": 2, "person": 3, "person-crouching": 4,
                  "dome": 5}
        rows = []
        for k in (range(len(self.obstacles)) if idx is None else idx):
            o = self.obstacles[k]
            c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
            cls = 1 if o.cls in ("drum", "barrel", "look-alike-drum") else \
                2 if o.cls in ("crate", "look-alike-crate", "box") else 0
            rows.append([o.x, o.y, c, s, o.length_m, o.width_m, o.height_m, o.z0,
                         shapes[o.shape], o.radius, 1.0 if o.texture == "stubble" else 0.0,
                         *o.colour, *o.colour2, cls, k])
        return np.array(rows, np.float64).reshape(-1, 19)

    def is_shiny(self, mat: np.ndarray) -> np.ndarray:
        shiny = np.zeros(mat.shape, bool)
        for k, o in enumerate(self.obstacles):
            if o.shiny:
                shiny |= mat == MAT_OBSTACLE + k
        return shiny


def make_waves(rng: np.random.Generator, amplitude_m: float, n: int = 6,
               wavelengths=(4.0, 30.0)) -> np.ndarray:
    """Seeded ground undulation: n sinusoids with wavelengths in a range, amplitudes summing to
    about ``amplitude_m``."""
    rows = []
    lam = np.exp(rng.uniform(np.log(wavelengths[0]), np.log(wavelengths[1]), n))
    amps = rng.uniform(0.5, 1.0, n) * (lam / lam.max()) ** 0.5
    amps = amps / amps.sum() * amplitude_m
    for i in range(n):
        th = rng.uniform(0, 2 * np.pi)
        k = 2 * np.pi / lam[i]
        rows.append((k * np.cos(th), k * np.sin(th), rng.uniform(0, 2 * np.pi), amps[i]))
    return np.array(rows, np.float32)
