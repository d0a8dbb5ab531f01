"""Vehicle-frame occupancy grid with temporal integration.

Each cycle the evidence grid is moved with the vehicle (speed and yaw rate over the time since
the last update), multiplied by ``decay``, and every cell hit by an obstacle point this cycle
gains 1. A cell is occupied when its evidence reaches ``occupied_at``: with the defaults
(decay 0.5, occupied_at 1.4) a cell must be hit in two cycles running (1 + 0.5), so a single
frame's speckle does not stop the vehicle — the papers decided on single frames; 1.0 restores
that. Over a 100 ms cycle that costs one cycle of latency for a real obstacle.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from appliance.config import GridConfig
from appliance.perception.candidates import on_footprints
from hal.types import VehicleState, move_with_vehicle  # noqa: F401 (re-exported)


def _cells(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of a 2-D bool mask (the same indices in the same order), through its
    flat indices: several times faster on the grid's 96 k cells."""
    ix, iy = np.divmod(np.flatnonzero(mask), mask.shape[1])
    return ix, iy


class GridFusion:
    def __init__(self, config: GridConfig | None = None):
        self.cfg = config or GridConfig()
        c = self.cfg
        self.nx = int(round((c.x_max_m - c.x_min_m) / c.cell_m))
        self.ny = int(round((c.y_max_m - c.y_min_m) / c.cell_m))
        self.evidence = np.zeros((self.nx, self.ny), np.float32)   # [ix, iy]
        # chains (``stop_chain``): per cell, how many cycles running an object was hit here
        # or within ``stop_chain_radius_m`` of where the chain was the cycle before
        self.chain = np.zeros((self.nx, self.ny), np.float32) if c.stop_chain > 0 else None
        # recurrence (``stop_recur``): occupied now (1) + decayed, spreading memory of occupied
        self.recur = np.zeros((self.nx, self.ny), np.float32) if c.stop_recur > 0 else None
        # a remembered value below half of (stop_recur - 1) can never again help a cell reach
        # stop_recur (memory only decays; a new occupied cycle adds 1): it is dropped, so the
        # spreading memory does not fill the grid with tiny values that every cycle's
        # ego-motion would move (3.3 ms a cycle of the loop's fusion stage, bench_loop)
        self._recur_floor = max(0.0, 0.5 * (c.stop_recur - 1.0))
        r = int(round(c.stop_chain_radius_m / c.cell_m))
        self._chain_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        self._last_ns: int | None = None

    def reset(self) -> None:
        self.evidence[:] = 0
        for g in (self.chain, self.recur):
            if g is not None:
                g[:] = 0
        self._last_ns = None

    # -- geometry ---------------------------------------------------------------------------
    def cell_index(self, pts_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = self.cfg
        ix = np.floor((pts_xy[:, 0] - c.x_min_m) / c.cell_m).astype(np.int64)
        iy = np.floor((pts_xy[:, 1] - c.y_min_m) / c.cell_m).astype(np.int64)
        ok = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        return ix, iy, ok

    def centres(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        c = self.cfg
        return np.stack([c.x_min_m + (ix + 0.5) * c.cell_m,
                         c.y_min_m + (iy + 0.5) * c.cell_m], axis=1).astype(np.float64)

    def _ego_motion(self, dt_s: float, vehicle: VehicleState | None) -> None:
        if vehicle is None or dt_s <= 0:
            return
        dx = vehicle.speed_mps * dt_s
        dth = vehicle.yaw_rate_radps * dt_s
        if not (math.isfinite(dx) and math.isfinite(dth)):
            # the links and the run-folder reader refuse non-finite values before they get
            # here; should one slip through, the grid keeps what it holds where it is (moving
            # it by NaN would wipe every cell: a CLEAR with obstacles ahead)
            return
        if abs(dx) < 1e-6 and abs(dth) < 1e-9:
            return
        # a point fixed in the world at p (old frame) is at R(-dth) (p - t) in the new frame
        c = self.cfg
        cos, sin = math.cos(-dth), math.sin(-dth)
        tx, ty = dx * math.cos(dth / 2), dx * math.sin(dth / 2)
        # in cell units: old index (i, j) -> metric -> new metric -> new index
        s = c.cell_m
        ox, oy = c.x_min_m, c.y_min_m
        # new = Rm @ (old_metric - t); old_metric = (i+.5)*s + o. Build map new_idx <- old_idx.
        a = np.array([[cos, -sin], [sin, cos]])
        # affine on (i, j): new_ij = A @ ij + b, in units of cells
        b_metric = a @ (np.array([ox + 0.5 * s, oy + 0.5 * s]) - np.array([tx, ty]))
        b = (b_metric - np.array([ox + 0.5 * s, oy + 0.5 * s])) / s
        # each cell with evidence goes to the cell its centre moves to (the larger value where
        # two land together). An inverse nearest-neighbour warp (cv2.warpAffine) samples the
        # old grid and skips cells: a lone cell vanished in a turn, and on a shift of exactly
        # half a cell every odd row did (OpenCV rounds ties to even). Found by
        # tests/test_properties.py
        self.evidence = self._move(self.evidence, a, b)
        if self.chain is not None:
            self.chain = self._move(self.chain, a, b)
        if self.recur is not None:
            self.recur = self._move(self.recur, a, b)

    def _move(self, grid: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # np.nonzero of the float grid is ~10x slower than flatnonzero of its != 0 (a
        # one-dimensional bool fast path): the same cells in the same order
        ix, iy = _cells(grid != 0)
        if not len(ix):
            return grid
        vals = grid[ix, iy]
        nij = a @ np.stack([ix, iy]).astype(np.float64) + b[:, None]
        ni = np.floor(nij[0] + 0.5)
        nj = np.floor(nij[1] + 0.5)
        ok = (ni >= 0) & (ni < self.nx) & (nj >= 0) & (nj < self.ny)
        out = np.zeros_like(grid)
        ii, jj, vv = ni[ok].astype(np.int64), nj[ok].astype(np.int64), vals[ok]
        lin = ii * grid.shape[1] + jj
        if len(lin) < 2 or bool(np.all(lin[1:] > lin[:-1])):
            # no two cells land together (driving straight: a shift keeps the cells' order):
            # a plain assignment is what maximum.at would give, without its cost
            out.ravel()[lin] = vv
        else:
            np.maximum.at(out, (ii, jj), vv)
        return out

    # -- update -----------------------------------------------------------------------------
    def update(self, points_xy: np.ndarray, vehicle: VehicleState | None,
               stamp_ns: int, confirmed_xy: np.ndarray | None = None) -> np.ndarray:
        """Integrate this cycle's points; return the occupied cell centres (M, 2).
        ``confirmed_xy``: points (among ``points_xy`` or not) whose cells are occupied at once
        (evidence raised to ``occupied_at``: :func:`confirmed_points`)."""
        dt = 0.0 if self._last_ns is None else (stamp_ns - self._last_ns) / 1e9
        self._last_ns = stamp_ns
        if dt > 2.0 or dt < 0:   # a gap (restart, stale sensors) or a clock step back: old
            # evidence means nothing (a step back kept evidence "from the future": found by
            # tests/test_properties.py; the tracker drops its tracks then too)
            self.evidence[:] = 0
            for g in (self.chain, self.recur):
                if g is not None:
                    g[:] = 0
        else:
            self._ego_motion(dt, vehicle)
        self.evidence *= self.cfg.decay
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        hit = np.zeros_like(self.evidence, dtype=bool)
        if len(pts):
            ix, iy, ok = self.cell_index(pts)
            hit[ix[ok], iy[ok]] = True
            self.evidence += hit
        if confirmed_xy is not None and len(confirmed_xy):
            ix, iy, ok = self.cell_index(np.asarray(confirmed_xy, np.float64).reshape(-1, 2))
            ix, iy = ix[ok], iy[ok]
            self.evidence[ix, iy] = np.maximum(self.evidence[ix, iy],
                                               np.float32(self.cfg.occupied_at))
            hit[ix, iy] = True
        if self.chain is not None:
            # a hit cell continues the longest chain that ended within the radius last cycle
            near = cv2.dilate(self.chain, self._chain_kernel)
            self.chain = np.where(hit, near + 1.0, 0.0).astype(np.float32)
        if self.recur is not None:
            occ = (self.evidence >= self.cfg.occupied_at - 1e-6).astype(np.float32)
            self.recur = (cv2.dilate(self.recur, self._chain_kernel) * self.cfg.stop_recur_decay
                          + occ)
            if self._recur_floor > 0:
                self.recur[self.recur < self._recur_floor] = 0.0
        return self.occupied()

    def recur_at(self, cells_xy: np.ndarray) -> np.ndarray:
        """The recurrence of the cells whose centres are ``cells_xy`` (0 off the grid or off)."""
        pts = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        out = np.zeros(len(pts), np.float32)
        if self.recur is None:
            return out
        ix, iy, ok = self.cell_index(pts)
        out[ok] = self.recur[ix[ok], iy[ok]]
        return out

    def hit_by(self, cells_xy: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
        """Per cell (centres ``cells_xy``): does one of ``points_xy`` fall in it?"""
        cells = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        out = np.zeros(len(cells), bool)
        if not len(cells) or not len(pts):
            return out
        px, py, pok = self.cell_index(pts)
        cx, cy, cok = self.cell_index(cells)
        hit = np.zeros((self.nx, self.ny), bool)
        hit[px[pok], py[pok]] = True
        out[cok] = hit[cx[cok], cy[cok]]
        return out

    def chain_at(self, cells_xy: np.ndarray) -> np.ndarray:
        """The chain length (cycles) of the cells whose centres are ``cells_xy`` (0 off the
        grid or with chains off)."""
        pts = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        out = np.zeros(len(pts), np.float32)
        if self.chain is None:
            return out
        ix, iy, ok = self.cell_index(pts)
        out[ok] = self.chain[ix[ok], iy[ok]]
        return out

    def occupied(self) -> np.ndarray:
        ix, iy = _cells(self.evidence >= self.cfg.occupied_at - 1e-6)
        return self.centres(ix, iy)

    def occupied_mask(self) -> np.ndarray:
        return self.evidence >= self.cfg.occupied_at - 1e-6

    def evidence_at(self, cells_xy: np.ndarray) -> np.ndarray:
        """The evidence of the cells whose centres are ``cells_xy`` (0 off the grid)."""
        pts = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        ix, iy, ok = self.cell_index(pts)
        out = np.zeros(len(pts), np.float32)
        out[ok] = self.evidence[ix[ok], iy[ok]]
        return out


def confirmed_points(detections: dict, g: GridConfig, front_x_m: float) -> np.ndarray | None:
    """``[grid] confirm_points``: the points that lie on the footprint (+ half a 0.1 m cell) of a
    candidate of at least ``g.confirm_points`` points made by one of ``g.confirm_pipelines``
    (alone, or inside ``fused``), carrying one of ``g.confirm_sources`` when that names any, and
    whose near edge (x - length / 2) is at least ``g.confirm_min_ahead_m`` ahead of the front
    at ``front_x_m`` (0: anywhere), from the detections that hold it -- what is near and large
    enough to be believed on one frame. None when off or none."""
    min_points, pipelines, sources = g.confirm_points, g.confirm_pipelines, g.confirm_sources
    if min_points <= 0:
        return None
    min_x_m = front_x_m + g.confirm_min_ahead_m if g.confirm_min_ahead_m > 0 else None
    out = []
    names = set(pipelines)
    for name, d in detections.items():
        if d is None or not len(d.points_xy) or not d.candidates:
            continue
        # a candidate names the pipeline that made it (inside "fused" too)
        big = [c for c in d.candidates if c.points >= min_points
               and (name in names or getattr(c, "pipeline", None) in names)
               and (not sources or any(src in sources for src in c.sources))
               and (min_x_m is None or c.x_m - c.length_m / 2 >= min_x_m)]
        if not big:
            continue
        xy = np.asarray(d.points_xy, np.float64).reshape(-1, 2)
        on = on_footprints(xy, big, 0.05)
        if on.any():
            out.append(xy[on])
    return np.concatenate(out) if out else None
