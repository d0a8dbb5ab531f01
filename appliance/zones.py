"""Zones in front of the vehicle, and the obstacle picture the gate decides on.

The stop zone runs from the vehicle's front for the distance it needs to stop at its present
speed: reaction time x speed + speed^2 / (2 x deceleration) + a margin, never shorter than
``min_stop_m``. A slow-down zone lies beyond it. Cells inside exclusion boxes (the vehicle's own
implement) are never obstacles.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.config import ZonesConfig
from hal.types import ObstacleSector


@dataclass(frozen=True)
class ZoneVerdict:
    stop_len_m: float
    slow_len_m: float
    in_stop: int                 # occupied cells in the stop zone
    in_slow: int
    nearest_m: float | None      # nearest occupied cell ahead within the path, from the front
    sectors: tuple[ObstacleSector, ...]
    # the decision on tracks (appliance/decision.py) names what it stops for; None: cells
    stop_reason: str | None = None
    slow_reason: str | None = None
    track_ids: tuple[int, ...] = ()   # the tracks in (or predicted into) the stop/slow zones
    curvature_1pm: float = 0.0   # the zones bend along this arc ([zones] follow_turn; 0: straight)
    path: "PathBend | None" = None   # ... or along the planned path ([zones] follow_path)

    @property
    def bend(self) -> "float | PathBend":
        """What the zones were laid along: the planned path, else the arc (0: straight)."""
        return self.path if self.path is not None else self.curvature_1pm


def bend_of(res) -> "float | PathBend":
    """What the box laid its zones along in the cycle of ``res`` (anything with a
    ``verdict``, or None): an arc's curvature (0: straight; [zones] follow_turn) or the
    planned path (a PathBend; [zones] follow_path)."""
    return getattr(getattr(res, "verdict", None), "bend", 0.0)


def zone_rects(speed_mps: float, z: ZonesConfig) -> tuple[dict, dict]:
    """The stop and slow zones as vehicle-frame rectangles {x_min_m, x_max_m, half_width_m}
    (docs/run-format.md "The box's decisions")."""
    stop_len = stop_length(speed_mps, z)
    slow_len = stop_len + z.slow_extra_m
    f = z.front_x_m
    return ({"x_min_m": f, "x_max_m": f + stop_len, "half_width_m": z.half_width_m},
            {"x_min_m": f + stop_len, "x_max_m": f + slow_len, "half_width_m": z.half_width_m})


# a footprint must reach more than this into a zone to meet it: only touching its edge is
# not meeting it (the grid's cells share edges with a zone whose length is a multiple of the
# cell size, e.g. the 2.0 m stop zone at standstill, and rounding must not decide those)
MEET_TOL_M = 1e-9


def footprints_meet(centres_xy, length_m, width_m, rect: dict, yaw_rad=0.0) -> np.ndarray:
    """Per footprint: does any part of it lie in the zone rectangle ``rect`` ({x_min_m,
    x_max_m, half_width_m}, vehicle frame, as :func:`zone_rects` gives)? The one zone test of
    the box: a safety box stops for the near edge of a thing, not for its centre.

    A footprint is a rectangle ``length_m`` (along its heading) x ``width_m``, centred on its
    row of ``centres_xy`` (N, 2) and turned ``yaw_rad`` counter-clockwise from x: a grid cell
    is ``cell_m`` x ``cell_m`` at yaw 0, a track its length x width, a truth obstacle its
    turned footprint, a point 0 x 0. ``length_m``, ``width_m`` and ``yaw_rad`` are scalars or
    one per footprint. It meets the zone when the two rectangles overlap by more than
    ``MEET_TOL_M`` (separating axes: the zone's two and the footprint's two); one that only
    touches an edge does not (a cell's hits are in [edge, edge + cell), not on the edge).
    Pure: arrays in, a bool array out."""
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    hl = 0.5 * np.asarray(length_m, dtype=np.float64)
    hw = 0.5 * np.asarray(width_m, dtype=np.float64)
    yaw = np.asarray(yaw_rad, dtype=np.float64)
    cos, sin = np.cos(yaw), np.sin(yaw)
    ac, as_ = np.abs(cos), np.abs(sin)
    x0, x1 = float(rect["x_min_m"]), float(rect["x_max_m"])
    zl, zh = 0.5 * (x1 - x0), float(rect["half_width_m"])
    dx, dy = c[:, 0] - 0.5 * (x0 + x1), c[:, 1]
    # the zone's axes: the footprint's half extents along x and y
    meet = np.abs(dx) - (hl * ac + hw * as_) - zl < -MEET_TOL_M
    meet &= np.abs(dy) - (hl * as_ + hw * ac) - zh < -MEET_TOL_M
    if not np.any(sin):     # square to the zone (cells, tracks): its axes are the zone's
        return meet
    # the footprint's axes: the zone's half extents along them
    meet &= np.abs(dx * cos + dy * sin) - hl - (zl * ac + zh * as_) < -MEET_TOL_M
    meet &= np.abs(-dx * sin + dy * cos) - hw - (zl * as_ + zh * ac) < -MEET_TOL_M
    return meet


def footprint_meets(x_m: float, y_m: float, length_m: float, width_m: float, rect: dict,
                    yaw_rad: float = 0.0) -> bool:
    """:func:`footprints_meet` for one footprint."""
    return bool(footprints_meet(np.array([[x_m, y_m]]), length_m, width_m, rect, yaw_rad)[0])


def path_rect(z: ZonesConfig, reach_m: float = 1000.0) -> dict:
    """The vehicle's path ahead of its front (the zones' width, ``reach_m`` long)."""
    return {"x_min_m": z.front_x_m, "x_max_m": z.front_x_m + reach_m,
            "half_width_m": z.half_width_m}


# below this curvature (1/m, a radius over 1 km) the path is taken as straight
STRAIGHT_1PM = 1e-3


def _arc(curvature_1pm: float, front_x_m: float) -> tuple[float, float, float] | None:
    """(sign of the turn, the origin's turning radius, the front centre's radius), or None
    for a straight path."""
    k = float(curvature_1pm)
    if abs(k) < STRAIGHT_1PM:
        return None
    r0 = 1.0 / abs(k)
    return (1.0 if k > 0 else -1.0), r0, math.hypot(front_x_m, r0)


class PathBend:
    """The zones laid along the path the vehicle will drive (``[zones] follow_path``).

    ``path_xy`` is the planned path of the vehicle's origin (the point that drives it: the
    rear axle's middle), a polyline in the vehicle frame from at or near the origin, as an
    autopilot plans it (the simulator: its route); the vehicle's heading along it is the
    path's direction. The zones are what the vehicle's body sweeps as it drives on along it:
    the body is the rectangle from ``rear_m`` behind the origin to the front (``front_x_m``),
    ``half_width_m`` (the zones' half width, margin included) to each side (in a tight turn
    the tail swings out: training seed 28's crate, 1 cm from the sprayer's tail). A point is ``s`` metres into the
    zones when the body, driven ``s`` metres on along the path, first covers it; so in this
    frame ``x`` = ``front_x_m`` + that ``s`` and ``y`` its offset across the body then, and the
    zones are the straight rectangles again (stop: ``x`` up to the front + the stopping
    distance). A point the body never covers within ``reach_m`` is placed at its nearest
    approach (``x`` there, ``y`` = the half width + its distance from the body), outside every
    zone; one the body covers now (beside or under it) keeps its own coordinates (behind the
    front: in no zone, as with straight zones). On a straight path this is the straight zones
    exactly; in a turn the inner side of the body sweeps what lies beside it, and what lies
    straight ahead of the front but outside the turn is never reached.

    A path shorter than ``reach_m`` is carried on straight from its end. ``step_m``: the body
    is placed every this along the path (a distance in the zones is good to it)."""

    def __init__(self, path_xy, front_x_m: float, half_width_m: float, reach_m: float = 15.0,
                 step_m: float = 0.05, rear_m: float = 0.0):
        p = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(p)):
            raise ValueError("a planned path's points must be numbers")
        if len(p) >= 2:
            keep = np.concatenate([[True], np.hypot(*np.diff(p, axis=0).T) > 1e-6])
            p = p[keep]
        if len(p) < 2:
            raise ValueError("a planned path needs two distinct points")
        self.path_xy = p
        self.front_x_m, self.half_width_m = float(front_x_m), float(half_width_m)
        self.rear_m = max(0.0, float(rear_m))
        d = np.diff(p, axis=0)
        seg = np.hypot(d[:, 0], d[:, 1])
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        self.reach_m = max(float(reach_m), step_m)
        s = np.append(np.arange(0.0, self.reach_m, step_m), self.reach_m)
        # the poses: on the path up to its end, then straight on along its last heading
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        t = (s - cum[i]) / seg[i]
        self.s = s
        self.yaw = yaw[i]
        self.o = p[i] + t[:, None] * d[i]
        self.cos, self.sin = np.cos(self.yaw), np.sin(self.yaw)
        # the straight path from the origin: the straight zones themselves
        self.straight = bool(np.all(np.abs(p[:, 1]) <= 1e-9) and np.all(d[:, 0] > 0)
                             and abs(p[0, 0]) <= 1e-9)

    def _body(self, q: np.ndarray):
        """Each point in the body's frame at every pose: (x, y), each (N, poses)."""
        rx = q[:, 0:1] - self.o[None, :, 0]
        ry = q[:, 1:2] - self.o[None, :, 1]
        return rx * self.cos + ry * self.sin, -rx * self.sin + ry * self.cos

    def _sweep(self, xy):
        """(x, y in the zones' frame, the index of the pose that placed it, -1: its own) per
        point."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = q.copy()
        pose = np.full(len(q), -1)
        if self.straight or not len(q):
            return out, pose
        f, hw = self.front_x_m, self.half_width_m
        # the body cannot reach what is further from the origin than it ever gets
        far = np.hypot(q[:, 0], q[:, 1]) > self.reach_m + math.hypot(f, hw) + 1.0
        idx = np.flatnonzero(~far)
        if len(far) and far.any():
            out[far] = [f + self.reach_m + 100.0, hw + 100.0]
        if not len(idx):
            return out, pose
        bx, by = self._body(q[idx])
        gap = np.hypot(np.maximum(0.0, np.maximum(bx - f, -self.rear_m - bx)),
                       np.maximum(0.0, np.abs(by) - hw))
        covered = gap <= 0.0
        reached = covered.any(axis=1) & ~covered[:, 0]
        ahead = bx[:, 0] > f                # ahead of the front now
        # a point the body reaches: where it first covers it; one it does not: where the front
        # comes level with it (along a straight path, its own x) or, beyond the reach, where
        # the body comes nearest
        level = bx <= f
        k = np.where(reached, np.argmax(covered, axis=1),
                     np.where(level.any(axis=1), np.argmax(level, axis=1),
                              np.argmin(gap, axis=1)))
        r = np.arange(len(idx))
        # between the pose before and this one, where the front crossed it (a straight path:
        # exactly its own x)
        km = np.maximum(k - 1, 0)
        b0, b1 = bx[r, km], bx[r, k]
        frac = np.where((k > 0) & (b0 > b1), np.clip((b0 - f) / np.where(b0 > b1, b0 - b1, 1.0),
                                                     0.0, 1.0), 1.0)
        x = f + self.s[km] + frac * (self.s[k] - self.s[km])
        yk = by[r, k]
        y = np.where(reached, yk, np.where(yk < 0, -1.0, 1.0) * np.maximum(np.abs(yk), hw + 1e-6))
        sel = reached | (ahead & ~covered[:, 0])
        out[idx[sel], 0], out[idx[sel], 1] = x[sel], y[sel]
        pose[idx[sel]] = k[sel]
        return out, pose

    def to_frame(self, xy) -> np.ndarray:
        return self._sweep(xy)[0]

    def heading(self, xy, yaw_rad) -> np.ndarray:
        """Headings (vehicle frame) of things at ``xy`` relative to the body when it meets
        them (or comes nearest)."""
        _, pose = self._sweep(xy)
        yaw = np.broadcast_to(np.asarray(yaw_rad, dtype=np.float64), (len(pose),)).copy()
        moved = pose >= 0
        yaw[moved] -= self.yaw[pose[moved]]
        return yaw

    def from_frame(self, xy) -> np.ndarray:
        """Zones-frame points back in the vehicle frame, along the front's track (for drawing:
        the outline of a zone is the front's edge driven along the path)."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.straight:
            return q.copy()
        s = np.clip(q[:, 0] - self.front_x_m, 0.0, self.reach_m)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        o = self.o[i] + (s - self.s[i])[:, None] * np.stack([self.cos[i], self.sin[i]], 1)
        fx = np.minimum(q[:, 0], self.front_x_m)     # behind the front: the body's own frame
        return np.stack([o[:, 0] + fx * self.cos[i] - q[:, 1] * self.sin[i],
                         o[:, 1] + fx * self.sin[i] + q[:, 1] * self.cos[i]], axis=1)


def bend_fields(bend: "float | PathBend") -> dict:
    """A :class:`ZoneVerdict`'s ``curvature_1pm`` and ``path`` for zones laid along ``bend``."""
    if isinstance(bend, PathBend):
        return {"curvature_1pm": 0.0, "path": bend}
    return {"curvature_1pm": float(bend), "path": None}


def same_bend(a, b) -> bool:
    """Were two sets of zones laid along the same line?"""
    if isinstance(a, PathBend) or isinstance(b, PathBend):
        return a is b
    return abs(float(a) - float(b)) <= 1e-12


def to_path_frame(xy, curvature_1pm: "float | PathBend", front_x_m: float) -> np.ndarray:
    """Vehicle-frame points (N, 2) in the frame of the path the vehicle's front drives at a
    constant ``curvature_1pm`` (1/m, positive turning left: the vehicle frame's y is to the
    left, its origin the point that drives the path, as the sim's and a tractor's rear axle):
    ``x`` = ``front_x_m`` + the arc length from the front's centre along its circle, ``y`` =
    the offset from that circle (left positive). The zones' rectangles in this frame are the
    stop and slow zones bent along the turn (``[zones] follow_turn``); for a straight path it
    is the identity. The arc is followed for half a turn (a U-turn, the most a vehicle turns
    in one go): a point behind the front on its circle, or more than half a turn ahead of it,
    has ``x`` < ``front_x_m`` and is in no zone. A :class:`PathBend` instead of a curvature:
    the frame of the planned path (``[zones] follow_path``)."""
    if isinstance(curvature_1pm, PathBend):
        return curvature_1pm.to_frame(xy)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    arc = _arc(curvature_1pm, front_x_m)
    if arc is None or not len(p):
        return p
    sgn, r0, rf = arc                          # the turn's centre is (0, sgn r0)
    yl = sgn * p[:, 1]                         # as if turning left
    ang = np.arctan2(p[:, 0], r0 - yl)         # angle about the centre, origin at 0, forward +
    d = ang - math.atan2(front_x_m, r0)
    d = np.mod(d + math.pi, 2 * math.pi) - math.pi          # [-pi, pi): ahead is 0..pi
    rho = np.hypot(p[:, 0], r0 - yl)
    out = np.empty_like(p)
    out[:, 0] = front_x_m + rf * d
    out[:, 1] = sgn * (rf - rho)
    return out


def from_path_frame(xy, curvature_1pm: "float | PathBend", front_x_m: float) -> np.ndarray:
    """The inverse of :func:`to_path_frame`: path-frame points back in the vehicle frame."""
    if isinstance(curvature_1pm, PathBend):
        return curvature_1pm.from_frame(xy)
    q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    arc = _arc(curvature_1pm, front_x_m)
    if arc is None or not len(q):
        return q
    sgn, r0, rf = arc
    a = math.atan2(front_x_m, r0) + (q[:, 0] - front_x_m) / rf
    rho = rf - sgn * q[:, 1]
    return np.stack([rho * np.sin(a), sgn * (r0 - rho * np.cos(a))], axis=1)


def zone_outline(x_min_m: float, x_max_m: float, half_width_m: float,
                 curvature_1pm: "float | PathBend",
                 front_x_m: float, step_m: float = 0.1) -> np.ndarray:
    """A zone rectangle (path frame) as a closed outline in the vehicle frame, bent along the
    turn when there is one (for drawing: the snapshot, the console)."""
    arc = None if isinstance(curvature_1pm, PathBend) else _arc(curvature_1pm, front_x_m)
    if arc is not None:                        # the zones end after half a turn
        x_max_m = max(x_min_m, min(x_max_m, front_x_m + math.pi * arc[2]))
    n = max(2, int(math.ceil((x_max_m - x_min_m) / step_m)) + 1)
    xs = np.linspace(x_min_m, x_max_m, n)
    left = np.stack([xs, np.full(n, half_width_m)], axis=1)
    right = np.stack([xs[::-1], np.full(n, -half_width_m)], axis=1)
    return from_path_frame(np.concatenate([left, right]), curvature_1pm, front_x_m)


def heading_to_path_frame(xy, yaw_rad, curvature_1pm: "float | PathBend") -> np.ndarray:
    """Headings (rad, vehicle frame) of things at vehicle-frame points ``xy``, in the frame of
    :func:`to_path_frame`: less the turn of the path's tangent there."""
    if isinstance(curvature_1pm, PathBend):
        return curvature_1pm.heading(xy, yaw_rad)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.broadcast_to(np.asarray(yaw_rad, dtype=np.float64), (len(p),))
    arc = _arc(curvature_1pm, 0.0)
    if arc is None or not len(p):
        return np.array(yaw, dtype=np.float64)
    sgn, r0, _ = arc
    return yaw - sgn * np.arctan2(p[:, 0], r0 - sgn * p[:, 1])


def stop_length(speed_mps: float, z: ZonesConfig) -> float:
    v = max(0.0, speed_mps)
    return max(z.min_stop_m, v * z.reaction_time_s + v * v / (2 * z.decel_mps2) + z.margin_m)


def kept_mask(cells_xy: np.ndarray, z: ZonesConfig) -> np.ndarray:
    """Per cell: outside every exclusion box."""
    keep = np.ones(len(cells_xy), bool)
    for e in z.exclusion:
        inside = ((cells_xy[:, 0] >= e.x_min_m) & (cells_xy[:, 0] <= e.x_max_m)
                  & (cells_xy[:, 1] >= e.y_min_m) & (cells_xy[:, 1] <= e.y_max_m))
        keep &= ~inside
    return keep


def drop_excluded(cells_xy: np.ndarray, z: ZonesConfig) -> np.ndarray:
    if not len(z.exclusion) or not len(cells_xy):
        return cells_xy
    return cells_xy[kept_mask(cells_xy, z)]


def sectors(cells_xy: np.ndarray, n: int = 72, fov_deg: float = 180.0,
            max_m: float = 30.0) -> tuple[ObstacleSector, ...]:
    """Nearest occupied cell per angular sector ahead (for OBSTACLE_DISTANCE-style messages)."""
    inc = fov_deg / n
    edges = -fov_deg / 2 + inc * np.arange(n + 1)
    near = np.full(n, np.inf)
    if len(cells_xy):
        ang = np.degrees(np.arctan2(-cells_xy[:, 1], cells_xy[:, 0]))   # clockwise-positive, FRD
        dist = np.hypot(cells_xy[:, 0], cells_xy[:, 1])
        idx = np.floor((ang - edges[0]) / inc).astype(int)
        ok = (idx >= 0) & (idx < n) & (dist <= max_m)
        np.minimum.at(near, idx[ok], dist[ok])
    return tuple(ObstacleSector(float(edges[i]), float(edges[i + 1]),
                                None if not math.isfinite(near[i]) else float(near[i]))
                 for i in range(n))


def assess(cells_xy: np.ndarray, speed_mps: float, z: ZonesConfig,
           confirmed: np.ndarray | None = None, cell_m: float = 0.0,
           curvature_1pm: "float | PathBend" = 0.0,
           slow_ok: np.ndarray | None = None) -> ZoneVerdict:
    """The zone verdict on occupied cells. ``confirmed`` (one flag per cell, or None: all):
    only a confirmed cell in the stop zone makes a STOP; an unconfirmed one there is a SLOW
    (``[grid] stop_at``: a cell seen in too few cycles running to stop for). ``cell_m``: the
    cells' size; a cell is in a zone when any part of it is (:func:`footprints_meet`: its
    centre may be up to half a cell beyond the zone's far end, side or near end while what
    hit it is inside), so what the grid holds 4 cm beyond the stop zone's end is a STOP, not a
    SLOW one cycle too long. ``nearest_m``: the nearest such cell's centre from the front (0
    when its centre is behind the front). ``curvature_1pm``: the zones bend along that arc
    (:func:`to_path_frame`; distances are then along the arc), or a :class:`PathBend`: along
    the planned path. ``slow_ok`` (one flag per cell, or None: all): only a flagged cell in
    the slow zone beyond the stop zone makes a SLOW (``[grid] slow_recur``)."""
    cells = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
    if confirmed is not None or slow_ok is not None:
        keep = kept_mask(cells, z)
        n = len(cells)
        conf = (np.ones(n, bool) if confirmed is None
                else np.asarray(confirmed, bool).reshape(-1))[keep]
        sok = None if slow_ok is None else np.asarray(slow_ok, bool).reshape(-1)[keep]
        cells = cells[keep]
    else:
        cells = drop_excluded(cells, z)
        conf = np.ones(len(cells), bool)
        sok = None
    stop_len = stop_length(speed_mps, z)
    slow_len = stop_len + z.slow_extra_m
    stop_rect, slow_rect = zone_rects(speed_mps, z)
    pc = to_path_frame(cells, curvature_1pm, z.front_x_m)
    ahead = np.maximum(pc[:, 0] - z.front_x_m, 0.0)
    fwd = footprints_meet(pc, cell_m, cell_m, path_rect(z))
    stop_cells = fwd & footprints_meet(pc, cell_m, cell_m, stop_rect)
    in_stop = int(np.count_nonzero(stop_cells & conf))
    waiting = int(np.count_nonzero(stop_cells & ~conf))
    beyond = fwd & ~stop_cells & footprints_meet(pc, cell_m, cell_m, slow_rect)
    if sok is not None:
        beyond &= sok
    in_slow = int(np.count_nonzero(beyond)) + waiting
    nearest = float(ahead[fwd].min()) if np.any(fwd) else None
    slow_reason = None
    if waiting and not in_stop:
        near = float(ahead[stop_cells & ~conf].min())
        slow_reason = (f"unconfirmed obstacle {near:.1f} m ahead in the stop zone "
                       f"({stop_len:.1f} m): slow until it is seen again")
    return ZoneVerdict(stop_len, slow_len, in_stop, in_slow, nearest, sectors(cells),
                       slow_reason=slow_reason, **bend_fields(curvature_1pm))
