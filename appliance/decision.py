"""The one decision core: detections -> fusion grid -> candidates -> tracks -> zones -> gate.

Both the 10 Hz loop (appliance/loop.py) and the evaluator (appliance/evaluation.py) run this,
so what ``fieldguard eval`` scores is what the box decides.

- ``[tracking] enabled = false``: the papers' cell-based decision. Every pipeline's points go
  into the fusion grid; the occupied cells are the obstacle picture and any occupied cell in the
  stop zone is a STOP (the reproduction tables).
- ``enabled = true``: the grid is still kept (status, console), but the decision is on tracks
  (appliance/tracking.py): STOP when a confirmed track's footprint is in the stop zone, or its
  own motion over ground carries it into the stop zone within the reaction time
  (``[zones] reaction_time_s``); SLOW likewise for the slow zone. The obstacle picture (cells,
  for scoring and the sectors of OBSTACLE_DISTANCE) is the cells of the confirmed tracks.

Pure code: arrays in, verdicts out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from appliance.config import Config
from appliance.fusion import GridFusion, confirmed_points, move_with_vehicle
from appliance.gate import SafetyGate
from appliance.perception.base import Detections
from appliance.tracking import Tracker, TrackView
from appliance.zones import (STRAIGHT_1PM, PathBend, ZoneVerdict, assess, bend_fields,
                             drop_excluded, footprints_meet, sectors, stop_length,
                             to_path_frame, zone_rects)
from hal.types import GateOutput, VehicleState


@dataclass
class Picture:
    """What the fusion stage hands the gate this cycle."""

    cells_xy: np.ndarray                  # the obstacle picture (vehicle frame cell centres)
    verdict: ZoneVerdict
    speed_mps: float
    grid_cells_xy: np.ndarray             # the fusion grid's occupied cells
    tracks: list[TrackView] = field(default_factory=list)   # every track (confirmed flag)
    # [grid] hold_blind: the cells (among cells_xy) held out of the cameras' sight this cycle
    held_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def objects(self) -> list[TrackView]:
        return [t for t in self.tracks if t.confirmed]


def assess_tracks(tracks: list[TrackView], cells_xy: np.ndarray, speed_mps: float, cfg: Config,
                  cells_by_id: dict[int, np.ndarray] | None = None,
                  curvature_1pm: "float | PathBend" = 0.0) -> ZoneVerdict:
    """The zone verdict on confirmed tracks (see the module doc). ``cells_by_id``: each
    track's cells; a track with cells is in a zone when any part of one of its cells is (a
    front end's candidate can be far larger than what stands in it), else when any part of
    its footprint is (the one zone test, :func:`appliance.zones.footprints_meet`)."""
    z, tc = cfg.zones, cfg.tracking
    stop_len = stop_length(speed_mps, z)
    slow_len = stop_len + z.slow_extra_m
    stop_rect, slow_rect = zone_rects(speed_mps, z)
    cell_m = cfg.grid.cell_m
    f = z.front_x_m
    horizon = z.reaction_time_s
    steps = np.linspace(0.0, horizon, 6)[1:] if horizon > 0 else np.zeros(0)
    stop, slow, nearest = [], [], None
    stop_pred, slow_pred = {}, {}
    live = [t for t in tracks if t.confirmed and not (
        len(z.exclusion) and not len(drop_excluded(np.array([[t.x_m, t.y_m]]), z)))]
    # every live track's footprints (its cells, else its own footprint) now and at each
    # predicted step, tested against both zones in two calls (a call per track and step cost
    # 10 ms a cycle with 30 moving tracks)
    shifts = np.concatenate([[0.0], steps])
    k_n, n_t = len(shifts), len(live)
    own = [None if cells_by_id is None else cells_by_id.get(t.id) for t in live]
    own = [None if c is None or not len(c) else np.asarray(c, dtype=np.float64).reshape(-1, 2)
           for c in own]
    if live:
        base = np.concatenate([np.array([[t.x_m, t.y_m]]) if c is None else c
                               for t, c in zip(live, own)])
        counts = np.array([1 if c is None else len(c) for c in own])
        size = np.repeat(np.array([(t.length_m, t.width_m) if c is None else (cell_m, cell_m)
                                   for t, c in zip(live, own)]), counts, axis=0)
        vel = np.repeat(np.array([(t.vx_mps, t.vy_mps) for t in live]), counts, axis=0)
        xy = (base[None] + shifts[:, None, None] * vel[None]).reshape(-1, 2)   # step-major
        xy = to_path_frame(xy, curvature_1pm, f)     # the zones bent along the turn, if they are
        size = np.tile(size, (k_n, 1))
        g = (np.repeat(np.arange(n_t), counts)[None, :] * k_n
             + np.arange(k_n)[:, None]).ravel()                             # track, step

        def hits(rect):
            m = footprints_meet(xy, size[:, 0], size[:, 1], rect)
            return np.bincount(g[m], minlength=n_t * k_n).reshape(n_t, k_n) > 0
        hit_stop, hit_slow = hits(stop_rect), hits(slow_rect)
    for i, t in enumerate(live):
        tc_ = own[i]
        in_stop = bool(hit_stop[i, 0])
        in_slow = not in_stop and bool(hit_slow[i, 0])
        moving = math.hypot(t.vx_mps, t.vy_mps) >= tc.predict_min_mps
        if not in_stop and moving:
            for k in range(1, k_n):
                if hit_stop[i, k]:
                    in_stop = True
                    stop_pred[t.id] = float(shifts[k])
                    break
        if not in_stop and not in_slow and moving:
            for k in range(1, k_n):
                if hit_slow[i, k]:
                    in_slow = True
                    slow_pred[t.id] = float(shifts[k])
                    break
        if in_stop or in_slow:
            if tc_ is not None:
                ahead = max(0.0, float(to_path_frame(tc_, curvature_1pm, f)[:, 0].min()) - f)
            else:
                xp = float(to_path_frame(np.array([[t.x_m, t.y_m]]), curvature_1pm, f)[0, 0])
                ahead = max(0.0, xp - t.length_m / 2 - f)
            (stop if in_stop else slow).append((ahead, t))
            nearest = ahead if nearest is None else min(nearest, ahead)

    def name(t: TrackView) -> str:
        return f"track {t.id} ({'+'.join(t.sources) or '?'})"

    stop_reason = slow_reason = None
    if stop:
        ahead, t = min(stop, key=lambda a: a[0])
        if t.id in stop_pred and len(stop) == 1:
            stop_reason = (f"obstacle {name(t)} {ahead:.1f} m ahead, moving "
                           f"{math.hypot(t.vx_mps, t.vy_mps):.1f} m/s, predicted into the stop "
                           f"zone ({stop_len:.1f} m) in {stop_pred[t.id]:.1f} s")
        else:
            stop_reason = (f"obstacle {name(t)} {ahead:.1f} m ahead in the stop zone "
                           f"({stop_len:.1f} m)" + (", held out of the cameras' sight"
                                                    if t.held else ""))
    elif slow:
        ahead, t = min(slow, key=lambda a: a[0])
        what = " predicted" if t.id in slow_pred else ""
        slow_reason = f"obstacle {name(t)} {ahead:.1f} m ahead{what} in the slow zone"
    cells = drop_excluded(np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2), z)
    return ZoneVerdict(stop_len, slow_len, len(stop), len(slow), nearest, sectors(cells),
                       stop_reason=stop_reason, slow_reason=slow_reason,
                       track_ids=tuple(t.id for _, t in stop + slow),
                       **bend_fields(curvature_1pm))


def decision_name(tc) -> str:
    """What decides, for status and the evaluator: "tracks", "cells+movers" or "cells"."""
    return "tracks" if tc.enabled else ("cells+movers" if tc.movers else "cells")


def near_squares(xy: np.ndarray, other_xy: np.ndarray, side_m: float) -> np.ndarray:
    """Per point of ``xy``: does a point of ``other_xy`` lie in the same square of side
    ``side_m`` (a grid from the origin) or in one of its eight neighbours?"""
    a = np.floor(np.asarray(xy, np.float64).reshape(-1, 2) / side_m).astype(np.int64)
    b = np.floor(np.asarray(other_xy, np.float64).reshape(-1, 2) / side_m).astype(np.int64)
    out = np.zeros(len(a), bool)
    if not len(a) or not len(b):
        return out
    span = 1 << 31
    keys = np.unique((b[:, 0] + (span >> 1)) * span + (b[:, 1] + (span >> 1)))
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            k = (a[:, 0] + dx + (span >> 1)) * span + (a[:, 1] + dy + (span >> 1))
            i = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
            out |= keys[i] == k
    return out


def camera_points(detections: dict) -> list[np.ndarray]:
    """This cycle's obstacle points (each (N, 2), vehicle frame) of every pipeline but the
    laser: what a camera saw."""
    return [o.points_xy for n, o in detections.items()
            if n != "laser" and o is not None and len(o.points_xy)]


def camera_views(detections: dict) -> list:
    """This cycle's camera detections that carry a view (``Detections.view``): what a laser
    return can be confirmed by."""
    return [o for n, o in detections.items()
            if n != "laser" and o is not None and getattr(o, "view", None) is not None]


def camera_confirms(cams: list, xyz: np.ndarray, names, radius_m: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(inside, confirmed) per vehicle-frame point ``xyz`` (N, 3): in the view of one of the
    camera pipelines' detections ``cams`` (each with a ``view``), and confirmed by one of them
    through ``names`` (their masks at the point's pixel, or "points": one of their obstacle
    points in the same or a neighbouring square of side ``radius_m``)."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    masks = [n for n in names if n != "points"]
    inside = np.zeros(len(xyz), bool)
    ok = np.zeros(len(xyz), bool)
    for o in cams:
        ins, raised = o.view.look(xyz, masks)
        inside |= ins
        ok |= raised
        if "points" in names and len(o.points_xy):
            ok |= near_squares(xyz[:, :2], o.points_xy, radius_m)
    return inside, ok


def path_heading_deg(p: np.ndarray, over_m: float = 1.0) -> float | None:
    """The direction of a planned path's first ``over_m`` metres (from its first point to its
    point that far along it, or its end) against the vehicle's heading, degrees left
    positive; None when the path has no length."""
    d = np.hypot(*np.diff(p, axis=0).T) if len(p) >= 2 else np.zeros(0)
    if not len(d) or d.sum() <= 1e-9:
        return None
    cum = np.concatenate([[0.0], np.cumsum(d)])
    s = min(over_m, float(cum[-1]))
    x, y = np.interp(s, cum, p[:, 0]), np.interp(s, cum, p[:, 1])
    return math.degrees(math.atan2(y - p[0, 1], x - p[0, 0]))


class DecisionCore:
    """Fusion, tracking, zones and the gate for one box (one instance per loop or per run)."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.grid = GridFusion(cfg.grid)
        self.tracker = Tracker(cfg.tracking, cfg.grid) if cfg.tracking.enabled else None
        # [tracking] movers: the cell decision, and a tracker beside it for what moves
        self.movers = (Tracker(cfg.tracking, cfg.grid)
                       if cfg.tracking.movers and not cfg.tracking.enabled else None)
        self.gate = SafetyGate(cfg.gate, cfg.zones)
        self.last: Picture | None = None
        self.curvature_1pm = 0.0          # the arc the zones bend along ([zones] follow_turn)
        self.laser_unconfirmed = 0        # laser returns no camera confirmed this cycle
        self.path_refused = ""            # why this cycle's planned path was not used
        # [grid] hold_blind: cells held out of the cameras' sight (vehicle frame, this cycle),
        # the next cycle's candidates for holding, their stamp, and whether a camera view
        # has been seen at all (a laser-only box holds nothing)
        self.held_xy = np.zeros((0, 2))
        self._held_cells = np.zeros((0, 2))    # ... as the grid cells' centres
        self._hold_seeds = np.zeros((0, 2))
        self._hold_past = np.zeros(0, np.int64)   # per seed: cycles running a camera saw past it
        self._hold_ns: int | None = None
        self._had_camera = False

    # below this speed the yaw rate says nothing of the path: the last curvature is kept (a
    # vehicle stopped in a turn drives on along it: its steering has not moved)
    TURN_MIN_MPS = 0.1

    def _curvature(self, vehicle: VehicleState | None) -> float:
        z = self.cfg.zones
        if not z.follow_turn:
            return 0.0
        if vehicle is not None and vehicle.speed_mps >= self.TURN_MIN_MPS:
            k = vehicle.yaw_rate_radps / vehicle.speed_mps
            if not math.isfinite(k):
                k = 0.0                   # a broken yaw rate: the straight zones
            self.curvature_1pm = max(-z.max_curvature_1pm, min(z.max_curvature_1pm, k))
            if abs(self.curvature_1pm) < STRAIGHT_1PM:
                self.curvature_1pm = 0.0
        return self.curvature_1pm

    def _bend(self, vehicle: VehicleState | None) -> float | PathBend:
        """What the zones are laid along this cycle: the planned path (``[zones]
        follow_path``, when the vehicle state carries a usable one), else the arc of
        ``follow_turn``, else straight (0)."""
        z = self.cfg.zones
        self.path_refused = ""
        if z.follow_path:
            path = None if vehicle is None else vehicle.path_xy
            if path is None:
                self.path_refused = "no planned path"
            else:
                try:
                    p = np.asarray(path, dtype=np.float64)
                    if p.ndim != 2 or p.shape[1] != 2:
                        raise ValueError(f"it is not a list of (x, y) points (shape "
                                         f"{p.shape})")
                    if not np.all(np.isfinite(p)):
                        raise ValueError("it has points that are not numbers")
                    if not len(p):
                        raise ValueError("it has no points")
                    off = math.hypot(p[0, 0], p[0, 1])
                    if off > z.path_max_offset_m:
                        raise ValueError(f"it starts {off:.2f} m from the vehicle")
                    head = path_heading_deg(p)
                    if head is not None and abs(head) > z.path_max_heading_deg:
                        raise ValueError(f"it heads {head:+.0f} deg off the vehicle's "
                                         f"heading")
                    # as far as the slow zone reaches, and a cell beyond
                    speed = vehicle.speed_mps if math.isfinite(vehicle.speed_mps) else 0.0
                    reach = stop_length(speed, z) + z.slow_extra_m + 2 * self.cfg.grid.cell_m
                    return PathBend(p, z.front_x_m, z.half_width_m, reach_m=reach,
                                    rear_m=z.body_rear_m)
                except (ValueError, TypeError) as exc:
                    self.path_refused = f"planned path not used: {exc}"
        return self._curvature(vehicle)

    def laser_on_ground(self, detections: dict[str, Detections]) -> dict[str, Detections]:
        """``[perception.laser] ground_min_m``: the laser's returns where its scan plane runs
        lower than that above the ground a camera pipeline measured this cycle are dropped
        (the top of a stubble tuft on a rise, or ahead of a vehicle pitching nose-down: a
        planar laser cannot tell it from an obstacle, a ground ahead can). Without such a
        ground this cycle (no camera pipeline fitting one, its fit refused, the camera
        faulted) every return stays, as without the rule."""
        t = self.cfg.perception.laser.ground_min_m
        d = detections.get("laser")
        if t <= 0 or d is None or d.points_z is None or not len(d.points_xy):
            return detections
        g = next((o.ground for n, o in detections.items()
                  if n != "laser" and o is not None and o.ground is not None), None)
        if g is None:
            return detections
        xy = np.asarray(d.points_xy, np.float64)
        z = np.asarray(d.points_z, np.float64)
        gz = np.asarray(g.z(xy[:, 0], xy[:, 1]), np.float64)
        # a ground that says nothing here (not finite) drops nothing: only a measured ground
        # less than t below the plane takes a return away
        ok = np.isfinite(gz)
        keep = np.ones(len(z), bool)
        keep[ok] = (z[ok] - gz[ok]) >= t
        if keep.all():
            return detections
        cands = tuple(c for c in d.candidates
                      if np.any(keep & (np.abs(xy[:, 0] - c.x_m) <= c.length_m / 2 + 0.05)
                                & (np.abs(xy[:, 1] - c.y_m) <= c.width_m / 2 + 0.05)))
        out = dict(detections)
        out["laser"] = Detections(points_xy=d.points_xy[keep], candidates=cands,
                                  points_z=d.points_z[keep], ground=d.ground,
                                  debug={**d.debug, "below_ground_min": int((~keep).sum())})
        return out

    def laser_confirmed(self, detections: dict[str, Detections]
                        ) -> tuple[np.ndarray, np.ndarray] | None:
        """``[grid] laser_confirm_by``: (the laser's returns a camera pipeline had in view this
        cycle and did not confirm, the rest), each (N, 2) in the vehicle frame; None when off,
        without laser returns, without a camera view this cycle, or without the returns'
        heights (``use_attitude``: a gravity frame, not the camera's)."""
        g = self.cfg.grid
        names = g.laser_confirm_by
        d = detections.get("laser")
        if not names or d is None or d.points_z is None or not len(d.points_xy):
            return None
        cams = camera_views(detections)
        if not cams:
            return None
        xy = np.asarray(d.points_xy, np.float64).reshape(-1, 2)
        xyz = np.column_stack([xy, np.asarray(d.points_z, np.float64)])
        inside, ok = camera_confirms(cams, xyz, names, g.laser_confirm_radius_m)
        unconf = inside & ~ok
        self.laser_unconfirmed = int(unconf.sum())
        return xy[unconf], xy[~unconf]

    def perceive(self, detections: dict[str, Detections], vehicle: VehicleState | None,
                 now_ns: int) -> Picture:
        """Fuse this cycle's detections (the loop's "fusion" stage)."""
        detections = self.laser_on_ground(detections)
        self.laser_unconfirmed = 0
        laser_split = self.laser_confirmed(detections)
        pts = [d.points_xy for d in detections.values() if d is not None and len(d.points_xy)]
        pts_xy = np.concatenate(pts) if pts else np.zeros((0, 2), np.float32)
        g = self.cfg.grid
        grid_cells = self.grid.update(pts_xy, vehicle, now_ns,
                                      confirmed_points(detections, g, self.cfg.zones.front_x_m))
        speed = vehicle.speed_mps if vehicle is not None else 0.0
        kappa = self._bend(vehicle)
        if self.tracker is None:
            conf = None
            if g.stop_at > g.occupied_at:    # a STOP needs a cell seen in more cycles running
                conf = self.grid.evidence_at(grid_cells) >= g.stop_at - 1e-6
            if g.stop_chain > 0:             # ... or an object that stayed (or moved slowly)
                chained = self.grid.chain_at(grid_cells) >= g.stop_chain - 1e-6
                conf = chained if conf is None else (conf & chained)
            if g.stop_recur > 0:             # ... or occupied again, nearby, in the last cycles
                recurs = self.grid.recur_at(grid_cells) >= g.stop_recur - 1e-6
                now = [d.points_xy for n, d in detections.items()
                       if n in g.stop_recur_now and d is not None and len(d.points_xy)]
                if now:                      # ... or hit by a laser return this cycle
                    recurs |= self.grid.hit_by(grid_cells, np.concatenate(now))
                conf = recurs if conf is None else (conf & recurs)
            if laser_split is not None and len(laser_split[0]):
                # ... and a cell that only unconfirmed laser returns hit this cycle is a SLOW
                others = camera_points(detections) + [laser_split[1]]
                slow = self.grid.hit_by(grid_cells, laser_split[0])
                slow &= ~self.grid.hit_by(grid_cells, np.concatenate(others))
                conf = ~slow if conf is None else (conf & ~slow)
            cells = grid_cells
            if g.hold_blind:
                cells, conf = self._hold_blind(grid_cells, conf, detections, vehicle, now_ns)
            slow_ok = None
            if g.slow_recur > 0:             # a SLOW for the slow zone wants a recurrent cell
                slow_ok = self.grid.recur_at(cells) >= g.slow_recur - 1e-6
                if conf is not None:         # (what may make a STOP may make a SLOW)
                    slow_ok |= np.asarray(conf, bool)
            verdict = assess(cells, speed, self.cfg.zones, conf, cell_m=g.cell_m,
                             curvature_1pm=kappa, slow_ok=slow_ok)
            if len(self._held_cells) and verdict.in_stop:
                # say so when what is stopped for includes a held cell: the vehicle stands
                # before a thing no camera sees now (the technician's first question)
                held = assess(self._held_cells, speed, self.cfg.zones, cell_m=g.cell_m,
                              curvature_1pm=kappa)
                if held.in_stop:
                    verdict = replace(verdict, stop_reason=(
                        f"obstacle {held.nearest_m:.1f} m ahead in the stop zone "
                        f"({verdict.stop_len_m:.1f} m), held out of the cameras' sight"))
            pic = Picture(cells, verdict, speed, grid_cells, held_xy=self._held_cells)
            if self.movers is not None:
                pic = self._with_movers(pic, detections, vehicle, now_ns)
        else:
            occ = self.grid.occupied_mask() if self.cfg.tracking.input == "occupied" else None
            z = self.cfg.zones
            stop_zone = (z.front_x_m, z.front_x_m + stop_length(speed, z), z.half_width_m,
                         kappa)
            blind = self._blind_test(detections) if self.cfg.grid.hold_blind else None
            tracks = self.tracker.update(detections, vehicle, now_ns, occ, stop_zone, blind)
            by_id = self.tracker.cells_by_track()
            cells = np.concatenate(list(by_id.values())) if by_id else np.zeros((0, 2))
            held = [by_id[t.id] for t in tracks if t.held and t.id in by_id]
            self.held_xy = np.concatenate(held) if held else np.zeros((0, 2))
            pic = Picture(cells, assess_tracks(tracks, cells, speed, self.cfg, by_id, kappa),
                          speed, grid_cells, tracks, held_xy=self.held_xy)
        self.last = pic
        return pic

    def _blind_test(self, detections: dict):
        """``[grid] hold_blind``, for the cells' and the tracks' decision: vehicle-frame points
        (N, 2) -> which
        lie in the hold's region (from half a cell behind the front to ``hold_blind_range_m``
        ahead of it) where no camera pipeline observes a point ``hold_blind_probe_m`` above
        them; a cycle without a camera view (after one had a view) holds all in the region,
        a box that never had one nothing (as the cells' hold)."""
        g = self.cfg.grid
        cams = camera_views(detections)
        self._had_camera |= bool(cams)
        lo, hi = self._hold_region()
        had = self._had_camera

        def blind(xy: np.ndarray) -> np.ndarray:
            xy = np.asarray(xy, np.float64).reshape(-1, 2)
            out = (xy[:, 0] >= lo) & (xy[:, 0] <= hi) & had
            if cams and out.any():
                xyz = np.column_stack([xy, np.full(len(xy), g.hold_blind_probe_m)])
                for o in cams:
                    out &= ~o.view.observes(xyz)
            return out
        return blind

    def _hold_region(self) -> tuple[float, float]:
        """The hold's region along x: half a cell behind the front to hold_blind_range_m
        ahead of it."""
        g, z = self.cfg.grid, self.cfg.zones
        return z.front_x_m - 0.5 * g.cell_m, z.front_x_m + g.hold_blind_range_m

    def _hold_blind(self, cells: np.ndarray, conf: np.ndarray | None, detections: dict,
                    vehicle: VehicleState | None, now_ns: int
                    ) -> tuple[np.ndarray, np.ndarray | None]:
        """``[grid] hold_blind``: the cells (and their STOP flags) with the held ones added.

        A cell confirmed (a STOP, were it in the stop zone) at most ``hold_blind_range_m``
        ahead of the front in one cycle is followed in the world as the vehicle moves; in the
        next cycle, where no camera pipeline observes it (``CameraView.observes``: under the
        image, or nearer than its stereo ranges, a point ``hold_blind_probe_m`` above it), it
        is held: a confirmed obstacle cell this cycle, followed again. It ends when a camera
        sees its place again (then the sensors decide, as for any cell), when it passes behind
        the front, or when it lies farther ahead than the range. A cycle without any camera
        view (a camera fault: the loop stops the vehicle for that) keeps every hold."""
        g = self.cfg.grid
        dt = 0.0 if self._hold_ns is None else (now_ns - self._hold_ns) * 1e-9
        self._hold_ns = now_ns
        seeds = move_with_vehicle(self._hold_seeds, dt, vehicle)
        blind = self._blind_test(detections)(seeds)          # the one test the tracks share
        held, past = seeds[blind], self._hold_past[blind]
        if g.hold_blind_look_frames > 0 and len(held):
            # a camera that looked again and saw past a held cell, cycles running: let go
            looks = [o.view.stereo_look for o in camera_views(detections)
                     if getattr(o.view, "stereo_look", None) is not None]
            seen = np.zeros(len(held), bool)
            for lk in looks:
                seen |= lk.sees_past(held)
            past = np.where(seen, past + 1, 0)
            keep = past < g.hold_blind_look_frames
            held, past = held[keep], past[keep]
        lo, hi = self._hold_region()
        # next cycle's candidates: this cycle's confirmed cells near the front (a margin of
        # 1 m beyond the range: what moves into it before the next look) and the held ones
        c = np.asarray(cells, np.float64).reshape(-1, 2)
        if conf is not None:
            c = c[np.asarray(conf, bool)]
        c = c[(c[:, 0] >= lo) & (c[:, 0] <= hi + 1.0)]
        if g.hold_blind_min_evidence > 0 and len(c):
            c = c[self.grid.evidence_at(c) >= g.hold_blind_min_evidence - 1e-6]
        if not g.hold_blind_laser and len(c):
            # only what a camera saw: a camera pipeline's points hit the cell this cycle, or
            # it is a candidate already (hit by one in an earlier cycle while confirmed)
            cam = camera_points(detections)
            ok = (self.grid.hit_by(c, np.concatenate(cam)) if cam
                  else np.zeros(len(c), bool))
            if len(seeds) and not ok.all():
                ok |= near_squares(c, seeds, g.cell_m)
            c = c[ok]
        nxt = np.concatenate([c, held]) if len(held) else c
        cnt = np.concatenate([np.zeros(len(c), np.int64), past])
        if len(nxt):      # one per grid cell (the first: a confirmed cell before a held one)
            key = np.floor(nxt / g.cell_m).astype(np.int64)
            _, first = np.unique(key, axis=0, return_index=True)
            nxt, cnt = nxt[np.sort(first)], cnt[np.sort(first)]
        self._hold_seeds, self._hold_past = nxt, cnt
        self.held_xy = held
        ix, iy, ok = self.grid.cell_index(held)
        add = self._held_cells = self.grid.centres(ix[ok], iy[ok])
        if not len(add):
            return cells, conf
        out = np.concatenate([np.asarray(cells, np.float64).reshape(-1, 2), add])
        flags = (np.ones(len(cells), bool) if conf is None else np.asarray(conf, bool))
        return out, np.concatenate([flags, np.ones(len(add), bool)])

    MOVER_STEP_S = 0.1            # movers: the meeting is looked for at these steps

    def _near_front(self, detections: dict[str, Detections], range_m: float,
                    behind_m: float) -> dict[str, Detections]:
        """The detections within ``range_m`` ahead of the front and to either side, and up to
        ``behind_m`` behind the front (the movers' tracker needs no more)."""
        f = self.cfg.zones.front_x_m
        out = {}
        for name, d in detections.items():
            if d is None:
                continue
            xy = np.asarray(d.points_xy, np.float64).reshape(-1, 2)
            keep = ((xy[:, 0] >= f - behind_m) & (xy[:, 0] <= f + range_m) &
                    (np.abs(xy[:, 1]) <= range_m))
            cands = tuple(c for c in d.candidates
                          if f - behind_m <= c.x_m <= f + range_m and abs(c.y_m) <= range_m)
            if keep.all() and len(cands) == len(d.candidates):
                out[name] = d
                continue
            out[name] = replace(d, points_xy=d.points_xy[keep], candidates=cands,
                                points_z=None if d.points_z is None else d.points_z[keep])
        return out

    def _with_movers(self, pic: Picture, detections: dict[str, Detections],
                     vehicle: VehicleState | None, now_ns: int) -> Picture:
        """``[tracking] movers``: the cells' verdict, and a STOP for a mover that meets the
        vehicle within the horizon if both go on as they are (a SLOW within twice it).

        A mover: a confirmed track seen this cycle and in the ``movers_min_run`` frames before
        it, no larger than ``movers_max_size_m``, whose centres lie on a straight line at
        constant speed (rms ``movers_max_rms_m``; :meth:`Tracker.motion_fit`) between
        ``movers_min_mps`` and ``movers_max_mps`` over ground; that fitted velocity is the one
        it is moved on with (the Kalman filter's lags, and reads speed into stubble). It meets
        the vehicle when, moved on at its velocity relative to the vehicle (its own over ground
        less the vehicle's, straight ahead: the zones' curvature is not used here), any part
        of its footprint comes within the vehicle's path width
        (``[zones] half_width_m``) between ``movers_body_m`` behind the front and the front:
        it walks into the front or the side. A person walking in from the side is outside the
        stop zone until it is too late to stop at cruise speed, and cells never predict; one
        that crosses well ahead of the vehicle, or behind it, does not meet it. The cells'
        STOP wins (it names what it stops for); a mover's STOP wins over the cells' SLOW."""
        tc, z = self.cfg.tracking, self.cfg.zones
        occ = self.grid.occupied_mask() if tc.movers_input == "occupied" else None
        speed = pic.speed_mps
        tracks = self.movers.update(self._near_front(detections, tc.movers_range_m,
                                                     tc.movers_body_m + 1.0),
                                    vehicle, now_ns, occ, None)
        movers = []                     # their views, with the fitted velocity
        by_id = {t.id: t for t in self.movers.tracks}
        for t in tracks:
            if not t.confirmed or t.coasting or max(t.length_m, t.width_m) > tc.movers_max_size_m:
                continue
            tr = by_id.get(t.id)
            if tr is None or tr.run < tc.movers_min_run:
                continue
            vx, vy, rms, _, n = self.movers.motion_fit(tr)
            if n >= tc.movers_min_run and rms <= tc.movers_max_rms_m and \
                    tc.movers_min_mps <= math.hypot(vx, vy) <= tc.movers_max_mps:
                movers.append(replace(t, vx_mps=vx, vy_mps=vy))
        if not movers:
            return pic
        horizon = tc.movers_horizon_s or (z.reaction_time_s + max(0.0, speed) / z.decel_mps2
                                          + 0.5)
        steps = np.arange(0.0, 2 * horizon + 1e-9, self.MOVER_STEP_S)
        body = {"x_min_m": z.front_x_m - tc.movers_body_m, "x_max_m": z.front_x_m,
                "half_width_m": z.half_width_m}
        first = []                                   # (time it meets the vehicle, track)
        for t in movers:
            rel = np.array([t.vx_mps - max(0.0, speed), t.vy_mps])
            xy = np.array([t.x_m, t.y_m])[None] + steps[:, None] * rel[None]
            meet = footprints_meet(xy, t.length_m, t.width_m, body)
            if meet.any():
                first.append((float(steps[int(np.argmax(meet))]), t))
        v = pic.verdict
        if not first or v.in_stop:
            return replace(pic, tracks=movers)
        t_meet, t = min(first, key=lambda a: a[0])
        ahead = max(0.0, t.x_m - t.length_m / 2 - z.front_x_m)
        nearest = ahead if v.nearest_m is None else min(v.nearest_m, ahead)
        what = (f"moving obstacle track {t.id} ({'+'.join(t.sources) or '?'}) {ahead:.1f} m "
                f"ahead, {t.y_m:+.1f} m aside, moving {math.hypot(t.vx_mps, t.vy_mps):.1f} m/s"
                f": meets the vehicle in {t_meet:.1f} s (stop zone {v.stop_len_m:.1f} m)")
        ids = tuple(m.id for _, m in first)
        if t_meet <= horizon + 1e-9:
            v = replace(v, in_stop=sum(a <= horizon + 1e-9 for a, _ in first),
                        stop_reason=what, nearest_m=nearest, track_ids=ids)
        elif not v.in_slow:
            v = replace(v, in_slow=len(first), slow_reason=what, nearest_m=nearest,
                        track_ids=ids)
        return replace(pic, verdict=v, tracks=movers)

    def decide(self, now_ns: int, faults: list[str], picture: Picture | None,
               source_stamp_ns: int | None = None) -> GateOutput:
        """The gate's answer for this cycle (the loop's "gate" stage)."""
        return self.gate.decide(now_ns, faults, None if picture is None else picture.verdict,
                                source_stamp_ns)
