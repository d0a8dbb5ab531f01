"""Obstacle candidates, tracks in the world frame, and the evidence on each track.

One cycle (:meth:`Tracker.update`):

1. **Candidates.** A pipeline that fills ``Detections.candidates`` hands them over as they are.
   A pipeline that gives only points (today's laser, stereo, stereo-novelty, rgbd) has its points
   binned into the fusion grid's cells and clustered here: 8-connected components of the hit
   cells after joining cells closer than ``cluster_gap_m`` (one labelling over every such
   pipeline, so laser and stereo hits on one pole make one candidate with both sources). Each
   candidate keeps, per source, how many of its cells that source hit. Candidates from different
   front ends whose footprints touch are merged.
2. **World frame.** The vehicle's pose is integrated from its speed and yaw rate (as the fusion
   grid moves its evidence; no visual odometry). Candidates are put into that frame, so a post
   stays where it is while the vehicle drives past it.
3. **Association.** Each track is predicted with a constant-velocity Kalman filter (state x, y,
   vx, vy over ground); candidates are assigned to tracks by minimum total distance
   (``scipy.optimize.linear_sum_assignment``) within a gate of ``gate_m`` beyond the two
   footprints. An unassigned candidate starts a tentative track.
4. **Evidence.** Per track and per source, log-odds: each frame a source that saw the track adds
   ``weight[source] x strength`` (strength = 1 - exp(-cells / support_cells) x the candidate's
   confidence), capped at ``weight x source_cap_frames`` so one source can only say so much; a
   frame without a hit takes ``miss_logodds`` from every source. The track's evidence is the sum
   over sources: two weak cues that agree add up, one noisy cue alone stays under its cap.
5. **Confirmation.** A track is confirmed when its evidence reaches ``confirm_logodds`` and it
   has been seen in enough frames: ``confirm_frames_min`` when it is near (``near_m``) or large
   (``large_m``), up to ``confirm_frames_max`` when it is far and small, and (after
   ``speed_check_frames`` hits) it stays where it was: over ground no faster than
   ``max_speed_mps`` and, while the vehicle moves, not moving along with the vehicle (within
   ``comoving_mps``: a stereo artefact or the vehicle's own shadow). Confirmed on its first
   frame: a laser return cluster (``laser_fast``: it counts at full strength), and a candidate
   with a cell in the stop zone (given by the decision core) and geometry or laser strength at
   least ``stop_zone_strength``. A confirmed track is kept
   while unseen for ``coast_s`` (occlusion), a tentative one for ``tentative_coast_s``; a
   confirmed track whose evidence falls under ``release_logodds`` ends; with
   ``coast_fused_s`` a still track the laser and a camera cue both saw is held that long
   unseen whatever its evidence. With ``blind`` (the decision core's ``[grid] hold_blind``) a
   confirmed track unseen this frame whose place no camera observes (too near, under the
   view) is **held**: kept, and kept confirmed, whatever its evidence, until a camera can see
   its place again or it leaves the region (``TrackView.held``).

Pure code: arrays in, tracks out; no I/O.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from appliance.config import GridConfig, TrackingConfig
from appliance.perception.base import Candidate, Detections
from appliance.zones import footprints_meet, to_path_frame
from hal.types import VehicleState

SOURCES = ("laser", "geometry", "novelty", "cue", "colour", "texture")

# what the points of a pipeline that gives no candidates stand for
PIPELINE_SOURCES: dict[str, tuple[str, ...]] = {
    "laser": ("laser",),
    "stereo": ("geometry",),
    "stereo-novelty": ("geometry", "novelty"),
    "rgbd": ("geometry",),
}


def pipeline_sources(name: str, det: Detections) -> tuple[str, ...]:
    """The cues behind a point-only pipeline's points. RGB-D names the groups it raised this
    frame (colour, texture, learned cue; geometry for raised parts and holes) from its debug
    counts: a frame-level attribution, not per point."""
    if name == "rgbd":
        d = det.debug or {}
        src = []
        if d.get("groups_raised") or d.get("groups_holes"):
            src.append("geometry")
        if d.get("groups_colour"):
            src.append("colour")
        if d.get("groups_texture"):
            src.append("texture")
        if d.get("groups_learned"):
            src.append("cue")
        return tuple(src) or ("geometry",)
    if name == "stereo-novelty":
        d = det.debug or {}
        cue = d.get("cue_cells") or {}
        return ("geometry", "novelty") + (("cue",) if any(cue.values()) else ())
    return PIPELINE_SOURCES.get(name, ("geometry",))


# ---------------------------------------------------------------------------------------------
# candidates
# ---------------------------------------------------------------------------------------------
@dataclass
class Measurement:
    """One candidate of this frame, in the vehicle frame, with what the tracker needs beside
    the :class:`Candidate`: per-source strength in [0, 1] and its cells (for the output)."""

    x_m: float
    y_m: float
    length_m: float
    width_m: float
    height_m: float
    points: int
    confidence: float
    strength: dict[str, float]
    cells_xy: np.ndarray
    pipelines: tuple[str, ...] = ()

    @property
    def sources(self) -> tuple[str, ...]:
        return tuple(s for s in SOURCES if self.strength.get(s, 0.0) > 0) + tuple(
            sorted(s for s in self.strength if s not in SOURCES and self.strength[s] > 0))

    def box(self) -> tuple[float, float, float, float]:
        return (self.x_m - self.length_m / 2, self.x_m + self.length_m / 2,
                self.y_m - self.width_m / 2, self.y_m + self.width_m / 2)


def _rect_cells(x0, x1, y0, y1, cell_m) -> np.ndarray:
    xs = np.arange(math.floor(x0 / cell_m), math.floor(x1 / cell_m) + 1) * cell_m + cell_m / 2
    ys = np.arange(math.floor(y0 / cell_m), math.floor(y1 / cell_m) + 1) * cell_m + cell_m / 2
    if len(xs) * len(ys) > 10000:           # a nonsense footprint: its centre only
        return np.array([[(x0 + x1) / 2, (y0 + y1) / 2]])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def cluster_points(points: dict[str, tuple[np.ndarray, tuple[str, ...]]], grid: GridConfig,
                   cfg: TrackingConfig) -> list[Measurement]:
    """Cluster the points of point-only pipelines into candidates: ``points`` maps a pipeline
    name to (points_xy (N, 2), its sources). One labelling over all of them."""
    cell = grid.cell_m
    nx = int(round((grid.x_max_m - grid.x_min_m) / cell))
    ny = int(round((grid.y_max_m - grid.y_min_m) / cell))
    names = list(points)
    keys, owners = [], []
    for k, name in enumerate(names):
        p = np.asarray(points[name][0], dtype=np.float64).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if not len(p):
            continue
        ix = np.floor((p[:, 0] - grid.x_min_m) / cell).astype(np.int64)
        iy = np.floor((p[:, 1] - grid.y_min_m) / cell).astype(np.int64)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        key = np.unique(ix[ok] * ny + iy[ok])
        if not len(key):        # every point off the grid (found by tests/test_properties.py:
            continue            # the empty labelling below raised ValueError)
        keys.append(key)
        owners.append(np.full(len(key), k, np.int64))
    if not keys:
        return []
    key_all = np.concatenate(keys)
    own_all = np.concatenate(owners)
    ucells, inv = np.unique(key_all, return_inverse=True)
    cx, cy = ucells // ny, ucells % ny
    # crop to the hit cells' bounding box (plus the join margin) before labelling
    g = int(math.ceil(cfg.cluster_gap_m / cell - 1e-9))
    x0, y0 = int(cx.min()), int(cy.min())
    h, w = int(cx.max()) - x0 + 1 + 2 * g, int(cy.max()) - y0 + 1 + 2 * g
    mask = np.zeros((h, w), np.uint8)
    mask[cx - x0 + g, cy - y0 + g] = 1
    if g > 0:   # each cell grows g cells towards +x, +y: cells with <= g empty cells between join
        mask = cv2.dilate(mask, np.ones((g + 1, g + 1), np.uint8), anchor=(0, 0))
    _, labels = cv2.connectedComponents(mask, connectivity=8)
    lab = labels[cx - x0 + g, cy - y0 + g]
    ulab, cl = np.unique(lab, return_inverse=True)
    n = len(ulab)
    xs = grid.x_min_m + (cx + 0.5) * cell
    ys = grid.y_min_m + (cy + 0.5) * cell
    count = np.bincount(cl, minlength=n)
    order = np.argsort(cl, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(count)])
    # per cluster per pipeline: cells that pipeline hit
    per_pipe = np.zeros((n, len(names)), np.int64)
    np.add.at(per_pipe, (cl[inv], own_all), 1)
    out = []
    for c in range(n):
        if count[c] < cfg.min_cells:
            continue
        idx = order[bounds[c]:bounds[c + 1]]
        px, py = xs[idx], ys[idx]
        strength: dict[str, float] = {}
        used = []
        for k, name in enumerate(names):
            m = per_pipe[c, k]
            if not m:
                continue
            used.append(name)
            s = 1.0 - math.exp(-m / cfg.support_cells)
            for src in points[name][1]:
                strength[src] = max(strength.get(src, 0.0), s)
        out.append(Measurement(
            x_m=float((px.min() + px.max()) / 2), y_m=float((py.min() + py.max()) / 2),
            length_m=float(px.max() - px.min() + cell), width_m=float(py.max() - py.min() + cell),
            height_m=0.0, points=int(count[c]),
            confidence=float(1.0 - math.exp(-count[c] / cfg.support_cells)),
            strength=strength, cells_xy=np.stack([px, py], axis=1), pipelines=tuple(used)))
    return out


_OFF = 1 << 20                     # cell indices -2^20 .. 2^20 (100 km at 0.1 m)


def _unique_cells(points_xy: np.ndarray, cell_m: float) -> np.ndarray:
    """The centres of the cells the points fall in, each once, sorted by x then y: what
    ``np.unique(centres, axis=0)`` gives, from one integer key per cell (np.unique on rows
    cost ~0.1 ms a candidate, 2-3 ms a cycle for the movers' tracker)."""
    ij = np.floor(np.asarray(points_xy, np.float64) / cell_m).astype(np.int64) + _OFF
    key = np.unique((ij[:, 0] << 21) | ij[:, 1])
    i, j = (key >> 21) - _OFF, (key & ((1 << 21) - 1)) - _OFF
    return (np.stack([i, j], axis=1).astype(np.float64) + 0.5) * cell_m


def from_candidate(c: Candidate, cell_m: float, points_xy: np.ndarray | None = None
                   ) -> Measurement | None:
    """A front end's candidate as a measurement. ``points_xy``: the pipeline's points (only
    those in occupied cells with ``input = "occupied"``); the candidate's cells are the cells of
    those inside its footprint (None when there are none: not supported this cycle). Without
    points, its footprint's cells."""
    conf = float(min(max(c.confidence, 0.0), 1.0))
    x0, x1 = c.x_m - c.length_m / 2, c.x_m + c.length_m / 2
    y0, y1 = c.y_m - c.width_m / 2, c.y_m + c.width_m / 2
    if points_xy is None:
        cells = _rect_cells(x0, x1, y0, y1, cell_m)
    else:
        p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        h = cell_m / 2
        inside = ((p[:, 0] >= x0 - h) & (p[:, 0] <= x1 + h) & (p[:, 1] >= y0 - h)
                  & (p[:, 1] <= y1 + h))
        if not inside.any():
            return None
        cells = _unique_cells(p[inside], cell_m)
    return Measurement(x_m=float(c.x_m), y_m=float(c.y_m), length_m=float(max(c.length_m, cell_m)),
                       width_m=float(max(c.width_m, cell_m)), height_m=float(c.height_m),
                       points=int(c.points), confidence=conf,
                       strength={s: conf for s in c.sources},
                       cells_xy=cells, pipelines=(c.pipeline,))


def merge_touching(ms: list[Measurement], gap_m: float) -> list[Measurement]:
    """Merge measurements whose footprints (grown by ``gap_m``) overlap: one object seen by
    several front ends."""
    if len(ms) < 2:
        return ms
    b = np.array([m.box() for m in ms])
    ov = ((b[:, None, 0] - gap_m <= b[None, :, 1]) & (b[None, :, 0] - gap_m <= b[:, None, 1])
          & (b[:, None, 2] - gap_m <= b[None, :, 3]) & (b[None, :, 2] - gap_m <= b[:, None, 3]))
    n = len(ms)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    ii, jj = np.nonzero(np.triu(ov, 1))
    if not len(ii):
        return ms
    for i, j in zip(ii.tolist(), jj.tolist()):
        ri, rj = find(i), find(j)
        if ri != rj:
            parent[rj] = ri
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    out = []
    for idx in groups.values():
        if len(idx) == 1:
            out.append(ms[idx[0]])
            continue
        bb = b[idx]
        x0, x1, y0, y1 = bb[:, 0].min(), bb[:, 1].max(), bb[:, 2].min(), bb[:, 3].max()
        strength: dict[str, float] = {}
        for i in idx:
            for s, v in ms[i].strength.items():
                strength[s] = max(strength.get(s, 0.0), v)
        out.append(Measurement(
            x_m=float((x0 + x1) / 2), y_m=float((y0 + y1) / 2), length_m=float(x1 - x0),
            width_m=float(y1 - y0), height_m=max(ms[i].height_m for i in idx),
            points=sum(ms[i].points for i in idx),
            confidence=max(ms[i].confidence for i in idx), strength=strength,
            cells_xy=np.concatenate([ms[i].cells_xy for i in idx]),
            pipelines=tuple(dict.fromkeys(p for i in idx for p in ms[i].pipelines))))
    return out


def keep_in_mask(points_xy: np.ndarray, mask: np.ndarray, grid: GridConfig) -> np.ndarray:
    """The points whose fusion-grid cell is set in ``mask`` ([ix, iy], the grid's shape)."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if not len(p):
        return p
    ix = np.floor((p[:, 0] - grid.x_min_m) / grid.cell_m).astype(np.int64)
    iy = np.floor((p[:, 1] - grid.y_min_m) / grid.cell_m).astype(np.int64)
    ok = (ix >= 0) & (ix < mask.shape[0]) & (iy >= 0) & (iy < mask.shape[1])
    ok[ok] = mask[ix[ok], iy[ok]]
    return p[ok]


def measurements(detections: dict[str, Detections], grid: GridConfig,
                 cfg: TrackingConfig, occupied: np.ndarray | None = None) -> list[Measurement]:
    """This frame's candidates from every pipeline's detections (see the module doc).
    ``occupied``: the fusion grid's occupied mask; a point-only pipeline's points count only
    where the grid is occupied (``[tracking] input = "occupied"``)."""
    given: list[Measurement] = []
    pts: dict[str, tuple[np.ndarray, tuple[str, ...]]] = {}
    for name, det in detections.items():
        if det is None:
            continue
        xy = det.points_xy if occupied is None or not len(det.points_xy) else \
            keep_in_mask(det.points_xy, occupied, grid)
        if det.candidates:
            # the front end's grouping, sources and height; its cells from its points (the
            # grid's occupied ones with input = "occupied"), not its filled footprint
            own = xy if len(det.points_xy) else None     # candidates alone: footprints
            for c in det.candidates:
                m = from_candidate(c, grid.cell_m, own)
                if m is not None:
                    given.append(m)
        elif len(xy):
            pts[name] = (xy, pipeline_sources(name, det))
    ms = cluster_points(pts, grid, cfg) if pts else []
    if given:
        ms = merge_touching(ms + given, cfg.cluster_gap_m)
    return ms


# ---------------------------------------------------------------------------------------------
# tracks
# ---------------------------------------------------------------------------------------------
@dataclass
class Track:
    id: int
    state: np.ndarray             # world frame: x, y, vx, vy
    cov: np.ndarray
    length_m: float
    width_m: float
    height_m: float
    born_ns: int
    last_hit_ns: int
    hits: int = 1
    misses: int = 0               # frames in a row without a hit
    confirmed: bool = False
    confirmed_ns: int | None = None
    evidence: dict[str, float] = field(default_factory=dict)   # log-odds per source
    seen_by: set = field(default_factory=set)                  # sources ever seen
    cells_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # this frame, vehicle
    cells_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # last seen, world
    points: int = 0
    confidence_in: float = 0.0    # the newest candidate's confidence
    pipelines: tuple[str, ...] = ()
    strength_in: dict = field(default_factory=dict)   # the newest candidate's, per source
    run: int = 1                  # frames in a row with a hit (0 after a miss)
    # the last measured centres (world frame) with their stamps: (ns, x, y), newest last
    seen_at: deque = field(default_factory=lambda: deque(maxlen=Track.SEEN_AT_MAX))

    SEEN_AT_MAX = 10

    @property
    def logodds(self) -> float:
        return float(sum(self.evidence.values()))

    @property
    def probability(self) -> float:
        return 1.0 / (1.0 + math.exp(-self.logodds))

    @property
    def speed_mps(self) -> float:
        return float(math.hypot(self.state[2], self.state[3]))

    def sources(self) -> tuple[str, ...]:
        return tuple(s for s in SOURCES if self.evidence.get(s, 0.0) > 1e-9)


@dataclass(frozen=True)
class TrackView:
    """A track as the rest of the box sees it: vehicle frame, this cycle."""

    id: int
    x_m: float
    y_m: float
    length_m: float
    width_m: float
    height_m: float
    vx_mps: float                 # over ground, in the vehicle frame's axes
    vy_mps: float
    confidence: float             # the evidence as a probability
    sources: tuple[str, ...]
    confirmed: bool
    coasting: bool                # not seen this frame (held from earlier frames)
    hits: int
    age_s: float
    held: bool = False            # kept while out of the cameras' sight (``blind``)

    def to_dict(self) -> dict:
        return {"id": self.id, "x_m": round(self.x_m, 3), "y_m": round(self.y_m, 3),
                "length_m": round(self.length_m, 3), "width_m": round(self.width_m, 3),
                "height_m": round(self.height_m, 3), "vx_mps": round(self.vx_mps, 3),
                "vy_mps": round(self.vy_mps, 3), "confidence": round(self.confidence, 4),
                "sources": list(self.sources), "confirmed": self.confirmed,
                "coasting": self.coasting, "held": self.held, "hits": self.hits,
                "age_s": round(self.age_s, 2),
                "distance_m": round(math.hypot(self.x_m, self.y_m), 2)}


class Tracker:
    def __init__(self, cfg: TrackingConfig | None = None, grid: GridConfig | None = None):
        self.cfg = cfg or TrackingConfig()
        self.grid = grid or GridConfig()
        self.tracks: list[Track] = []
        self.pose = np.zeros(3)            # world x, y, heading of the vehicle
        self._last_ns: int | None = None
        self._next_id = 1
        self._vehicle_v = np.zeros(2)      # the vehicle's velocity over ground, world frame
        self.stamp_ns = 0
        self.last_measurements: list[Measurement] = []
        self.held_ids: set[int] = set()      # confirmed tracks held out of the cameras' sight

    def reset(self) -> None:
        self.tracks.clear()
        self.held_ids = set()
        self._last_ns = None

    # -- frames ----------------------------------------------------------------------------
    def _move(self, dt: float, vehicle: VehicleState | None) -> None:
        if vehicle is None:
            self._vehicle_v[:] = 0
            return
        x, y, th = self.pose
        dth = vehicle.yaw_rate_radps * dt
        mid = th + dth / 2
        d = vehicle.speed_mps * dt
        if not (math.isfinite(d) and math.isfinite(dth)):
            # as the grid does (fusion.Grid._ego_motion): the links refuse non-finite values
            # first; should one slip through, the world frame stays where it was (a NaN pose
            # would make every track NaN, and a NaN range an exception in frames_needed)
            return
        self.pose = np.array([x + d * math.cos(mid), y + d * math.sin(mid), th + dth])
        h = self.pose[2]
        self._vehicle_v = vehicle.speed_mps * np.array([math.cos(h), math.sin(h)])

    def to_world(self, xy: np.ndarray) -> np.ndarray:
        x, y, th = self.pose
        c, s = math.cos(th), math.sin(th)
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.stack([x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]], 1)

    def to_vehicle(self, xy: np.ndarray) -> np.ndarray:
        x, y, th = self.pose
        c, s = math.cos(th), math.sin(th)
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        dx, dy = xy[:, 0] - x, xy[:, 1] - y
        return np.stack([c * dx + s * dy, -s * dx + c * dy], 1)

    def rotate_to_vehicle(self, v: np.ndarray) -> np.ndarray:
        th = self.pose[2]
        c, s = math.cos(th), math.sin(th)
        return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1]])

    # -- Kalman ----------------------------------------------------------------------------
    def _predict(self, t: Track, dt: float) -> None:
        if dt <= 0:
            return
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        q = self.cfg.accel_noise_mps2 ** 2
        g = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        t.state = f @ t.state
        t.cov = f @ t.cov @ f.T + q * (g @ g.T)

    def _correct(self, t: Track, z: np.ndarray, extent: float) -> float:
        h = np.zeros((2, 4))
        h[0, 0] = h[1, 1] = 1
        r = (self.cfg.meas_noise_m ** 2 + (0.25 * extent) ** 2) * np.eye(2)
        innov = z - t.state[:2]
        s = h @ t.cov @ h.T + r
        k = t.cov @ h.T @ np.linalg.inv(s)
        t.state = t.state + k @ innov
        t.cov = (np.eye(4) - k @ h) @ t.cov
        return float(np.hypot(*innov))

    def _new_track(self, m: Measurement, z: np.ndarray, now_ns: int) -> Track:
        r = self.cfg.meas_noise_m ** 2 + (0.25 * max(m.length_m, m.width_m)) ** 2
        cov = np.diag([r, r, 1.0, 1.0])          # velocity unknown: (1 m/s)^2
        t = Track(id=self._next_id, state=np.array([z[0], z[1], 0.0, 0.0]), cov=cov,
                  length_m=m.length_m, width_m=m.width_m, height_m=m.height_m,
                  born_ns=now_ns, last_hit_ns=now_ns)
        self._next_id += 1
        t.seen_at.append((now_ns, float(z[0]), float(z[1])))
        self._observe(t, m)
        return t

    # -- evidence --------------------------------------------------------------------------
    def _observe(self, t: Track, m: Measurement) -> None:
        w = self.cfg.weights
        cap = self.cfg.source_cap_frames
        strength = dict(m.strength)
        if self.cfg.laser_fast and strength.get("laser", 0.0) > 0:
            strength["laser"] = 1.0       # a return cluster is a measured surface
        t.strength_in = strength
        for s, v in strength.items():
            ws = float(getattr(w, s, 0.0))
            if ws <= 0 or v <= 0:
                continue
            t.evidence[s] = min(ws * cap, t.evidence.get(s, 0.0) + ws * v)
            t.seen_by.add(s)
        t.cells_xy = m.cells_xy
        t.cells_world = self.to_world(m.cells_xy) - t.state[:2]   # about the track's centre
        t.points = m.points
        t.confidence_in = m.confidence
        t.pipelines = m.pipelines

    def _miss(self, t: Track) -> None:
        for s in list(t.evidence):
            t.evidence[s] = max(0.0, t.evidence[s] - self.cfg.miss_logodds)
        t.cells_xy = np.zeros((0, 2))

    def frames_needed(self, range_m: float, size_m: float) -> int:
        """Frames a candidate must be seen in before it can be confirmed: the minimum near or
        large, up to the maximum far and small (the mean of the two fractions)."""
        c = self.cfg
        f_far = min(max((range_m - c.near_m) / (c.far_m - c.near_m), 0.0), 1.0)
        f_small = min(max((c.large_m - size_m) / (c.large_m - c.small_m), 0.0), 1.0)
        f = (f_far + f_small) / 2
        return int(round(c.confirm_frames_min + (c.confirm_frames_max - c.confirm_frames_min) * f))

    def _still(self, t: Track) -> bool:
        """Stays where it was as the vehicle moves (after speed_check_frames hits)."""
        c = self.cfg
        if t.hits < c.speed_check_frames:
            return True
        v = t.state[2:]
        if float(np.hypot(*v)) > c.max_speed_mps:
            return False
        vv = self._vehicle_v
        if float(np.hypot(*vv)) > 2 * c.comoving_mps and float(np.hypot(*(v - vv))) < c.comoving_mps:
            return False
        return True

    # -- one cycle -------------------------------------------------------------------------
    def update(self, detections: dict[str, Detections], vehicle: VehicleState | None,
               now_ns: int, occupied: np.ndarray | None = None,
               stop_zone: tuple[float, float, float, float] | None = None,
               blind=None) -> list[TrackView]:
        ms = measurements(detections, self.grid, self.cfg, occupied)
        return self.update_measurements(ms, vehicle, now_ns, stop_zone, blind)

    def _fast(self, t: Track, stop_zone) -> bool:
        """Confirmed on this frame's candidate alone: a laser return cluster (laser_fast), or
        a cell (any part of it) in the stop zone with strong geometry or laser evidence
        (stop_zone_strength)."""
        c = self.cfg
        if c.laser_fast and t.strength_in.get("laser", 0.0) > 0:
            return True
        if c.stop_zone_strength > 0 and stop_zone is not None and len(t.cells_xy):
            s = max(t.strength_in.get("geometry", 0.0), t.strength_in.get("laser", 0.0))
            x0, x1, hw, kappa = stop_zone        # kappa: the zones bent along a turn
            rect = {"x_min_m": x0, "x_max_m": x1, "half_width_m": hw}
            cell = self.grid.cell_m         # any part of a cell in the stop zone (zones.py)
            if s >= c.stop_zone_strength - 1e-9 and bool(
                    footprints_meet(to_path_frame(t.cells_xy, kappa, x0), cell, cell,
                                    rect).any()):
                return True
        return False

    def update_measurements(self, ms: list[Measurement], vehicle: VehicleState | None,
                            now_ns: int,
                            stop_zone: tuple[float, float, float, float] | None = None,
                            blind=None) -> list[TrackView]:
        """One frame. ``blind``: vehicle-frame points (N, 2) -> which of them lie where no
        camera observes them now (a confirmed track unseen there is held); None: no hold.
        With ``[grid] hold_blind_laser`` false a track no source but the laser ever saw is
        not held."""
        c = self.cfg
        dt = 0.0 if self._last_ns is None else (now_ns - self._last_ns) / 1e9
        self._last_ns = now_ns
        self.stamp_ns = now_ns
        if dt > 2.0 or dt < 0:           # a gap: old tracks mean nothing
            self.tracks.clear()
            dt = 0.0
        self._move(dt, vehicle)
        self.last_measurements = ms
        for t in self.tracks:
            self._predict(t, dt)
        zs = self.to_world(np.array([[m.x_m, m.y_m] for m in ms])) if ms else np.zeros((0, 2))
        matched_t: dict[int, int] = {}
        if self.tracks and ms:
            tp = np.array([t.state[:2] for t in self.tracks])
            d = np.hypot(tp[:, None, 0] - zs[None, :, 0], tp[:, None, 1] - zs[None, :, 1])
            text = np.array([max(t.length_m, t.width_m) for t in self.tracks]) / 2
            mext = np.array([max(m.length_m, m.width_m) for m in ms]) / 2
            gate = c.gate_m + text[:, None] + mext[None, :]
            big = 1e6
            cost = np.where(d <= gate, d, big)
            rows, cols = linear_sum_assignment(cost)
            for r_, c_ in zip(rows.tolist(), cols.tolist()):
                if cost[r_, c_] < big:
                    matched_t[r_] = c_
        used = set(matched_t.values())
        for i, t in enumerate(self.tracks):
            j = matched_t.get(i)
            if j is None:
                t.misses += 1
                t.run = 0
                self._miss(t)
                continue
            m = ms[j]
            self._correct(t, zs[j], max(m.length_m, m.width_m))
            a = 0.5
            t.length_m = (1 - a) * t.length_m + a * m.length_m
            t.width_m = (1 - a) * t.width_m + a * m.width_m
            t.height_m = max(m.height_m, 0.8 * t.height_m)
            t.hits += 1
            t.run += 1
            t.seen_at.append((now_ns, float(zs[j][0]), float(zs[j][1])))
            t.misses = 0
            t.last_hit_ns = now_ns
            self._observe(t, m)
        for j, m in enumerate(ms):
            if j not in used:
                self.tracks.append(self._new_track(m, zs[j], now_ns))
        # confirmation and ending
        keep = []
        self.held_ids = set()
        unseen_now = [t for t in self.tracks if t.confirmed and t.last_hit_ns != now_ns
                      and (self.grid.hold_blind_laser or t.seen_by - {"laser"})]
        if blind is not None and unseen_now:
            out = blind(self.to_vehicle(np.array([t.state[:2] for t in unseen_now])))
            self.held_ids = {t.id for t, b in zip(unseen_now, out) if b}
        for t in self.tracks:
            unseen = (now_ns - t.last_hit_ns) / 1e9
            if t.id in self.held_ids:                 # out of the cameras' sight: held
                keep.append(t)
                continue
            if t.confirmed:
                fused = (c.coast_fused_s > 0 and "laser" in t.seen_by
                         and len(t.seen_by - {"laser"}) > 0 and self._still(t)
                         and unseen <= c.coast_fused_s + 1e-9)
                if not fused and (unseen > c.coast_s + 1e-9 or (
                        t.misses and t.logodds < c.release_logodds)):
                    continue
                if not self._still(t):
                    t.confirmed = False
            else:
                if unseen > c.tentative_coast_s + 1e-9:
                    continue
                pv = self.to_vehicle(t.state[None, :2])[0]
                need = self.frames_needed(float(np.hypot(*pv)), max(t.length_m, t.width_m))
                if t.misses == 0 and self._still(t) and (
                        (t.logodds >= c.confirm_logodds - 1e-9 and t.hits >= need)
                        or self._fast(t, stop_zone)):
                    t.confirmed = True
                    t.confirmed_ns = now_ns
            keep.append(t)
        if len(keep) > c.max_tracks:     # keep the confirmed, then the best supported
            keep.sort(key=lambda t: (not t.confirmed, -t.logodds, -t.hits))
            keep = keep[:c.max_tracks]
        self.tracks = keep
        return self.views()

    def motion_fit(self, t: Track) -> tuple[float, float, float, float, int]:
        """A straight line at constant speed through the track's last measured centres of its
        present run of hits (world frame): (vx, vy, rms of the residuals in m, span in s, n).
        A thing that walks fits it to a few centimetres; a track that hops between stubble
        tufts, or whose candidate's extent jumps, does not. Fewer than 3 centres: zeros."""
        pts = list(t.seen_at)[-t.run:] if t.run > 0 else []
        n = len(pts)
        if n < 3:
            return 0.0, 0.0, 0.0, 0.0, n
        a = np.array(pts, dtype=np.float64)
        ts = (a[:, 0] - a[-1, 0]) / 1e9
        tm = ts - ts.mean()
        den = float((tm * tm).sum())
        if den <= 0:
            return 0.0, 0.0, 0.0, 0.0, n
        vx = float((tm * (a[:, 1] - a[:, 1].mean())).sum() / den)
        vy = float((tm * (a[:, 2] - a[:, 2].mean())).sum() / den)
        rx = a[:, 1] - (a[:, 1].mean() + vx * tm)
        ry = a[:, 2] - (a[:, 2].mean() + vy * tm)
        rms = float(np.sqrt(np.mean(rx * rx + ry * ry)))
        v = self.rotate_to_vehicle(np.array([vx, vy]))
        return float(v[0]), float(v[1]), rms, float(ts[-1] - ts[0]), n

    def views(self, confirmed_only: bool = False) -> list[TrackView]:
        out = []
        for t in self.tracks:
            if confirmed_only and not t.confirmed:
                continue
            p = self.to_vehicle(t.state[None, :2])[0]
            v = self.rotate_to_vehicle(t.state[2:])
            out.append(TrackView(
                id=t.id, x_m=float(p[0]), y_m=float(p[1]), length_m=float(t.length_m),
                width_m=float(t.width_m), height_m=float(t.height_m), vx_mps=float(v[0]),
                vy_mps=float(v[1]), confidence=t.probability, sources=t.sources(),
                confirmed=t.confirmed, coasting=t.last_hit_ns != self.stamp_ns,
                hits=t.hits, age_s=(self.stamp_ns - t.born_ns) / 1e9,
                held=t.id in self.held_ids))
        return out

    def cells_by_track(self) -> dict[int, np.ndarray]:
        """Each confirmed track's cells this cycle (vehicle frame), as confirmed_cells()."""
        return {t.id: self._cells(t) for t in self.tracks if t.confirmed}

    def confirmed_cells(self) -> np.ndarray:
        """The box's obstacle output as cells (vehicle frame): the cells of every confirmed
        track's candidate this frame; for a confirmed track held unseen, its footprint."""
        parts = [self._cells(t) for t in self.tracks if t.confirmed]
        if not parts:
            return np.zeros((0, 2))
        return np.concatenate(parts)

    def _cells(self, t: Track) -> np.ndarray:
        cell = self.grid.cell_m
        if len(t.cells_xy) and t.last_hit_ns == self.stamp_ns:
            return np.asarray(t.cells_xy, dtype=np.float64)
        if len(t.cells_world):   # held unseen: its last cells, where it is now
            c = self.to_vehicle(t.cells_world + t.state[:2])
            return (np.floor(c / cell) + 0.5) * cell
        p = self.to_vehicle(t.state[None, :2])[0]
        return _rect_cells(p[0] - t.length_m / 2, p[0] + t.length_m / 2 - 1e-9,
                           p[1] - t.width_m / 2, p[1] + t.width_m / 2 - 1e-9, cell)
