"""The simulated vehicle: follows the scene's path, obeys the box's gate, bounces on the ground,
and counts collisions.

- CLEAR: speed up (``accel_mps2``) to the scene's cruise speed; SLOW: go to the slow speed;
  STOP: brake at ``decel_mps2`` to a stand-still. ``None`` keeps the last command.
- A collision (the vehicle's footprint overlapping an obstacle's footprint) stops the vehicle
  dead and is counted once per obstacle. The vehicle may drive on when commanded (the sim lets it
  pass through an obstacle it has already hit, so one crash does not end a run).
- Operator takeover (``detour_after_s``, stubble scenes): held at STOP for that long before a
  REAL obstacle (within ``detour_trigger_m`` of the front, from the world, not from the box),
  the driver takes over and drives round it: he backs up along the path (as far as the way
  behind is free) far enough to steer out, then steers out ``detour_offset_m`` to the side
  along a smooth S at the slow speed, heading where he goes (`_manoeuvre_step`). The box's
  command is not obeyed while he does, and its odometry sees every metre of it (a negative
  speed while backing, the yaw rate of the S): until 2026-12 the vehicle was put beside its
  path at once, with no motion the box could see, so what the box had stopped for stayed in
  front of it in the box's grid. Once past, the driver steers back onto the path along a
  smooth S, heading where it goes (the gyro sees it: `_ease_back`). A long
  run can go on after a correct stop; a FALSE stop (nothing really ahead) is never taken over,
  Counted in ``stats()['detours']``. Where there is no room to steer round (a greenhouse lane,
  ``scene.clear_after_stop``) the driver instead clears the obstacle out of the way (carries
  it off; a person steps aside): it leaves the world and the drive goes on. Counted as a
  detour too (before this, a greenhouse drive stood in front of its first obstacle to the end).
- Operator override (``override_after_s``): held at STOP that long with NOTHING really ahead
  (a false stop), the driver overrides the box and creeps on at the slow speed for
  ``override_m``, so a long run goes on and counts its false stops
  (``stats()['overrides']``) — each one costs the time it waited, as it would in a field.
- Pitch and roll come from the ground under the four wheels plus a small seeded suspension
  oscillation; positive pitch is nose DOWN (as everywhere in fieldguard), positive roll is
  right side down.
"""
from __future__ import annotations

import math

import numpy as np

from drivers.mission_path import path_ahead, polyline_ahead
from hal.types import GateState, rotation_rpy

from .scenes import Scene


class Vehicle:
    def __init__(self, scene: Scene, seed: int = 0, decel_mps2: float = 2.5,
                 accel_mps2: float = 0.8, start_speed_mps: float | None = None,
                 start_s_m: float = 0.0, detour_after_s: float | None = None,
                 detour_offset_m: float | None = None, detour_trigger_m: float = 6.0,
                 override_after_s: float = 10.0, override_m: float = 5.0):
        self.scene = scene
        self.detour_after_s = float(getattr(scene, "detour_after_s", 5.0) if detour_after_s
                                    is None else detour_after_s)
        self.detour_offset_m = (scene.detour_offset_m if detour_offset_m is None
                                else float(detour_offset_m))
        self.detour_trigger_m = float(detour_trigger_m)
        self.offset_m = 0.0            # lateral offset from the path (left positive)
        self.heading_off = 0.0         # heading off the path's (rad, left positive): easing back
        self._ease: list[float] | None = None   # easing back: [offset it started from, progress]
        self._detour_until_s: float | None = None
        # the driver's manoeuvre round a real obstacle (None: the box's command is obeyed)
        self._manoeuvre: dict | None = None
        self._held_s = 0.0
        self.detours = 0
        self.cleared: list[str] = []          # obstacles the driver took out of the way
        self.override_after_s = float(override_after_s)
        self.override_m = float(override_m)
        self._override_until_s: float | None = None
        self.overrides = 0
        self.decel_mps2 = float(decel_mps2)
        self.accel_mps2 = float(accel_mps2)
        p = scene.path
        seg = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
        self._s = np.concatenate([[0.0], np.cumsum(seg)])
        yaw = np.arctan2(np.gradient(p[:, 1]), np.gradient(p[:, 0]))
        self._yaw = np.unwrap(yaw)
        self.path_length_m = float(self._s[-1])
        self.s = float(start_s_m)
        if start_speed_mps is None:
            start_speed_mps = getattr(scene, "start_speed_mps", None)
        self.speed = float(scene.cruise_mps if start_speed_mps is None else start_speed_mps)
        self.command = GateState.CLEAR
        self.time_s = 0.0
        self.distance_m = 0.0
        self.stopped_s = 0.0
        self.collisions = 0
        self.obstacles_hit: list[str] = []
        self.finished = False
        self.yaw_rate = 0.0
        rng = np.random.default_rng([seed, 7])
        self._osc = rng.uniform(0, 2 * math.pi, 4)
        self._osc_f = rng.uniform([1.1, 1.9, 0.9, 1.6], [1.5, 2.6, 1.3, 2.2])
        self._footprints = [self._footprint_points(o) for o in scene.world.obstacles]
        self._mission: tuple[np.ndarray, np.ndarray] | None = None

    # ---- path ---------------------------------------------------------------------------------
    def pose(self) -> tuple[float, float, float]:
        """World (x, y, yaw) of the vehicle's reference point (middle of the rear axle)."""
        p = self.scene.path
        s = min(max(self.s, 0.0), self.path_length_m)
        x = float(np.interp(s, self._s, p[:, 0]))
        y = float(np.interp(s, self._s, p[:, 1]))
        yaw = float(np.interp(s, self._s, self._yaw))
        if self.offset_m:
            x -= self.offset_m * math.sin(yaw)
            y += self.offset_m * math.cos(yaw)
        yaw += self.heading_off
        return x, y, math.atan2(math.sin(yaw), math.cos(yaw))

    def planned_path(self, reach_m: float = 15.0, step_m: float = 0.25) -> np.ndarray:
        """The route ahead as an autopilot would send it (``[zones] follow_path``): the path
        the origin follows from here for ``reach_m`` (to the route's end), every ``step_m``,
        in the vehicle frame (x ahead, y left). Off the route (a detour) it starts where the
        route is, beside the vehicle."""
        s0 = min(max(self.s, 0.0), self.path_length_m)
        return polyline_ahead(self.scene.path, self._s, s0, reach_m, step_m, self.pose())

    def mission_waypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """The route as a survey mission would give it (``[sim] path = "mission"``): each
        lane's start and end, world (x, y) (N, 2), and their route distances (N,). The turns
        between lanes are the autopilot's own, not in the mission."""
        if self._mission is None:
            s = sorted({float(v) for ab in self.scene.lanes for v in ab})
            if not s or s[-1] < self.path_length_m - 1e-6:
                s.append(self.path_length_m)
            s = np.array(s, np.float64)
            p = self.scene.path
            xy = np.stack([np.interp(s, self._s, p[:, 0]), np.interp(s, self._s, p[:, 1])], 1)
            self._mission = (xy, s)
        return self._mission

    def mission_current(self, wp_radius_m: float = 2.0) -> int | None:
        """The waypoint the autopilot heads for: the first one ahead on the route that the
        vehicle's origin is not within ``wp_radius_m`` of (ArduPilot Rover's WP_RADIUS: a
        waypoint is reached that near); None once the last is reached."""
        xy, s = self.mission_waypoints()
        x, y, _ = self.pose()
        for i in range(len(s)):
            if s[i] > self.s and math.hypot(xy[i, 0] - x, xy[i, 1] - y) > wp_radius_m:
                return i
        return None

    def mission_path(self, wp_radius_m: float = 2.0, reach_m: float = 15.0,
                     step_m: float = 0.25) -> np.ndarray | None:
        """The planned path as the box builds it from an autopilot's mission
        (drivers/mission_path.py): from the origin to the current waypoint, then along the
        lanes' ends, in the vehicle frame. None once the mission is done."""
        i = self.mission_current(wp_radius_m)
        if i is None:
            return None
        return path_ahead(self.pose(), self.mission_waypoints()[0], i, reach_m, step_m)

    def _curvature(self) -> float:
        ds = 0.5
        a = float(np.interp(min(self.s + ds, self.path_length_m), self._s, self._yaw))
        b = float(np.interp(max(self.s - ds, 0.0), self._s, self._yaw))
        return (a - b) / (2 * ds)

    # ---- attitude -----------------------------------------------------------------------------
    def attitude(self) -> tuple[float, float, float]:
        """(roll_rad, pitch_rad, z_m): from the ground under the wheels + suspension bounce."""
        x, y, yaw = self.pose()
        sc = self.scene
        c, s = math.cos(yaw), math.sin(yaw)
        wb, tr = sc.wheelbase_m, sc.track_m / 2
        pts = np.array([[0, tr], [0, -tr], [wb, tr], [wb, -tr]], np.float64)
        wx = x + pts[:, 0] * c - pts[:, 1] * s
        wy = y + pts[:, 0] * s + pts[:, 1] * c
        z = sc.world.ground(wx.astype(np.float32), wy.astype(np.float32)).astype(np.float64)
        rear, front = (z[0] + z[1]) / 2, (z[2] + z[3]) / 2
        left, right = (z[0] + z[2]) / 2, (z[1] + z[3]) / 2
        pitch = math.atan2(rear - front, wb)
        roll = math.atan2(left - right, 2 * tr)
        # suspension: amplitude grows with speed
        k = min(abs(self.speed) / max(sc.cruise_mps, 1e-6), 1.5)
        a = math.radians(sc.bounce_deg) * k
        t = self.time_s
        o, f = self._osc, self._osc_f
        pitch += a * (0.65 * math.sin(2 * math.pi * f[0] * t + o[0]) +
                      0.35 * math.sin(2 * math.pi * f[1] * t + o[1]))
        roll += 0.6 * a * (0.6 * math.sin(2 * math.pi * f[2] * t + o[2]) +
                           0.4 * math.sin(2 * math.pi * f[3] * t + o[3]))
        return roll, pitch, float(rear)

    def world_from_vehicle(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, origin): world = origin + R @ p_vehicle."""
        x, y, yaw = self.pose()
        roll, pitch, z = self.attitude()
        return rotation_rpy(roll, pitch, yaw), np.array([x, y, z])

    # ---- footprint / collisions ---------------------------------------------------------------
    @staticmethod
    def _footprint_points(o) -> np.ndarray:
        """Points covering an obstacle's footprint (world x, y)."""
        n = 11
        u = np.linspace(-0.5 * o.length_m, 0.5 * o.length_m, n)
        v = np.linspace(-0.5 * o.width_m, 0.5 * o.width_m, n)
        uu, vv = np.meshgrid(u, v)
        c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
        x = o.x + uu * c - vv * s
        y = o.y + uu * s + vv * c
        x, y = x.ravel(), y.ravel()
        inside = o.height(x.astype(np.float32), y.astype(np.float32)) > 0
        return np.stack([x[inside], y[inside]], 1)

    def refresh_footprint(self, k: int) -> None:
        """Obstacle k moved (a walker): its footprint points follow."""
        self._footprints[k] = self._footprint_points(self.scene.world.obstacles[k])

    def footprint_in_vehicle(self, k: int) -> np.ndarray:
        """Obstacle k's footprint points in the (level) vehicle frame, (N, 2)."""
        x, y, yaw = self.pose()
        c, s = math.cos(yaw), math.sin(yaw)
        d = self._footprints[k] - np.array([x, y])
        return np.stack([d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c], 1)

    def _overlaps(self, k: int, margin: float = 0.0) -> bool:
        rear, length, width = self.scene.footprint
        p = self.footprint_in_vehicle(k)
        return bool(np.any((p[:, 0] >= -rear - margin) & (p[:, 0] <= -rear + length + margin) &
                           (np.abs(p[:, 1]) <= width / 2 + margin)))

    def clearance_ahead(self, corridor_margin_m: float = 0.3) -> float:
        """Distance from the vehicle's front to the nearest obstacle footprint in its straight
        corridor ahead (inf if none)."""
        rear, length, width = self.scene.footprint
        front = -rear + length
        best = math.inf
        for k, o in enumerate(self.scene.world.obstacles):
            if o.id in self.obstacles_hit:
                continue
            p = self.footprint_in_vehicle(k)
            m = (np.abs(p[:, 1]) <= width / 2 + corridor_margin_m) & (p[:, 0] > -rear)
            if m.any():
                best = min(best, float(p[m, 0].min() - front))
        return best

    # ---- motion -------------------------------------------------------------------------------
    def step(self, dt_s: float, command: GateState | None = None) -> None:
        if dt_s <= 0:
            return
        if command is not None:
            self.command = command
        sc = self.scene
        target = {GateState.CLEAR: sc.cruise_mps, GateState.SLOW: sc.slow_mps,
                  GateState.STOP: 0.0}[self.command]
        if self._manoeuvre is not None:               # the driver drives, not the box
            target = self._manoeuvre_target()
        elif self._override_until_s is not None:
            if self.s < self._override_until_s and self.clearance_ahead() > self.detour_trigger_m:
                target = max(target, sc.slow_mps)
            else:
                self._override_until_s = None
        if self.finished:
            target = 0.0
        v0 = self.speed
        if target < v0:          # braking (forward) or speeding up backwards
            v1 = max(target, v0 - (self.decel_mps2 if v0 > 0 else self.accel_mps2) * dt_s)
        else:                    # speeding up (forward) or braking backwards
            v1 = min(target, v0 + (self.decel_mps2 if v0 < 0 else self.accel_mps2) * dt_s)
        travel = 0.5 * (v0 + v1) * dt_s
        ds = travel * math.cos(self.heading_off)          # along the path (less while easing back)
        self.s += ds
        if self.s >= self.path_length_m:
            self.s = self.path_length_m
            self.finished = True
            v1 = 0.0
        if self.s < 0.0:                                  # backed up to the route's start
            self.s, v1 = 0.0, 0.0
        self.speed = v1
        self.distance_m += abs(travel)
        self.time_s += dt_s
        if abs(self.speed) < 0.05:
            self.stopped_s += dt_s
        heading_before = self.heading_off
        if self._manoeuvre is not None:
            self._manoeuvre_step(ds)
        else:
            self._operator(dt_s, ds)
        # what a gyro would read: the path's turning and the driver's steering back onto it
        self.yaw_rate = self.speed * self._curvature() + (
            (self.heading_off - heading_before) / dt_s if dt_s > 0 else 0.0)
        x, y, _ = self.pose()
        for k, o in enumerate(sc.world.obstacles):
            if o.id in self.obstacles_hit or math.hypot(o.x - x, o.y - y) > o.radius + 3.5:
                continue
            if self._overlaps(k):
                self.collisions += 1
                self.obstacles_hit.append(o.id)
                self.speed = 0.0
                self.yaw_rate = 0.0

    EASE_M_PER_M = 5.0      # easing back takes 5 m of path per metre of offset (steepest 0.3)

    def _ease_back(self, ds: float) -> None:
        """Past the obstacle: steer back onto the path along a smooth S (offset ``o0 (1 -
        3u^2 + 2u^3)`` over ``EASE_M_PER_M * |o0|`` metres of path, at most 0.3 m a metre),
        heading along it as a steered vehicle does, so the gyro and the sensors see the turn
        (a sideways slide with the heading held made everything still look as if it moved
        sideways at 0.3x the vehicle's speed). Only where the way back is free: otherwise it
        drives straight on at the offset it has."""
        if self._ease is None:
            self._ease = [self.offset_m, 0.0]
        o0, u0 = self._ease
        length = max(self.EASE_M_PER_M * abs(o0), 1e-6)
        before = self.offset_m
        u = min(1.0, u0 + ds / length)
        self.offset_m = o0 * (1.0 - (3.0 * u * u - 2.0 * u ** 3))
        self.heading_off = math.atan(-o0 * 6.0 * u * (1.0 - u) / length)
        if self.clearance_ahead() < 2 * self.detour_trigger_m:
            self.offset_m, u, self.heading_off = before, u0, 0.0
        self._ease[1] = u
        if u >= 1.0:
            self.offset_m, self.heading_off = 0.0, 0.0
            self._ease, self._detour_until_s = None, None

    def _operator(self, dt_s: float, ds: float) -> None:
        """The safety driver: steers round a real obstacle the box has (rightly) stopped for."""
        if self._detour_until_s is not None and self.s >= self._detour_until_s:
            self._ease_back(ds)
        clear = self.scene.clear_after_stop
        if ((self.detour_offset_m <= 0 and not clear) or self.command is not GateState.STOP
                or self.speed >= 0.05):
            self._held_s = 0.0
            return
        self._held_s += dt_s
        if self._held_s < self.detour_after_s:
            return
        ahead = self.clearance_ahead()
        if ahead > self.detour_trigger_m:               # a false stop: the driver waits...
            if self._held_s >= self.override_after_s and self._override_until_s is None:
                self._override_until_s = self.s + self.override_m    # ...then overrides
                self.overrides += 1
                self._held_s = 0.0
            return
        if clear:
            self._clear_nearest()
            self.detours += 1
            self._held_s = 0.0
            return
        d, here = self.detour_offset_m, self.offset_m
        best, best_clear = here, ahead
        for off in (here + d, here - d, here + 2 * d, here - 2 * d):
            self.offset_m = off
            c = self.clearance_ahead()
            self.offset_m = here
            if c > best_clear + 1e-6 and self._way_out_free(here, off, ahead):
                best, best_clear = off, c
            if c > 3 * self.detour_trigger_m and best == off:
                break
        if best == here:                    # nowhere better to go: he waits (as before)
            self._held_s = 0.0
            return
        length, back = self._way_out(here, best, ahead)
        self._manoeuvre = {"phase": "back", "to_s": max(0.0, self.s - back), "o0": here,
                           "o1": best, "obstacle_s": self.s + ahead, "u": 0.0, "length": length}
        self.heading_off, self._ease = 0.0, None
        self._detour_until_s = self.s + ahead + self.scene.footprint[1] + 6.0
        self.detours += 1
        self._held_s = 0.0

    DETOUR_M_PER_M = 2.0    # steering out takes 2 m of path per metre of offset (steepest 37 deg)
    DETOUR_CLEAR_M = 1.0    # ...and ends this far short of the obstacle
    REVERSE_MPS = 0.8       # backing up

    def _way_out(self, here: float, off: float, ahead: float) -> tuple[float, float]:
        """(length of the S out, how far to back up first): the S takes DETOUR_M_PER_M of path
        a metre of offset and ends DETOUR_CLEAR_M short of the obstacle (a driver's full lock
        at walking pace)."""
        length = self.DETOUR_M_PER_M * abs(off - here)
        return length, max(0.0, length + self.DETOUR_CLEAR_M - ahead)

    def _way_out_free(self, here: float, off: float, ahead: float, samples: int = 16) -> bool:
        """Would the S out to ``off`` (after backing up for it) touch an obstacle? The driver
        looks before he goes: poses along the S, the footprint 0.1 m wider all round."""
        length, back = self._way_out(here, off, ahead)
        s0, o_was, h_was = self.s, self.offset_m, self.heading_off
        try:
            start = max(0.0, s0 - back)
            for u in np.linspace(0.0, 1.0, samples):
                self.s = start + u * length
                self.offset_m, self.heading_off = self._s_out(here, off, u, length)
                x, y, _ = self.pose()
                for k, o in enumerate(self.scene.world.obstacles):
                    if o.id in self.obstacles_hit or \
                            math.hypot(o.x - x, o.y - y) > o.radius + 4.0:
                        continue
                    if self._overlaps(k, margin=0.1):
                        return False
            return True
        finally:
            self.s, self.offset_m, self.heading_off = s0, o_was, h_was

    @staticmethod
    def _s_out(o0: float, o1: float, u: float, length: float) -> tuple[float, float]:
        """(offset, heading off the path) at progress ``u`` of the S from offset ``o0`` to
        ``o1`` over ``length`` m of path: the one curve the driver steers out along and looks
        along before he goes."""
        return (o0 + (o1 - o0) * (3.0 * u * u - 2.0 * u ** 3),
                math.atan((o1 - o0) * 6.0 * u * (1.0 - u) / length))

    def _free_behind(self, gap_m: float = 1.0, corridor_margin_m: float = 0.3) -> bool:
        """Nothing within ``gap_m`` behind the vehicle's rear (the driver looks round)."""
        rear, _, width = self.scene.footprint
        for k, o in enumerate(self.scene.world.obstacles):
            if o.id in self.obstacles_hit:
                continue
            p = self.footprint_in_vehicle(k)
            if np.any((np.abs(p[:, 1]) <= width / 2 + corridor_margin_m) &
                      (p[:, 0] < -rear + 0.5) & (p[:, 0] >= -rear - gap_m)):
                return False
        return True

    def _manoeuvre_target(self) -> float:
        """The speed the driver wants in his manoeuvre: back up at REVERSE_MPS, braking to rest
        where the backing ends; then out at the slow speed."""
        m = self._manoeuvre
        if m["phase"] == "back":
            left = self.s - m["to_s"]
            brake = self.speed * self.speed / (2.0 * self.decel_mps2)
            return 0.0 if left <= brake + 0.02 else -self.REVERSE_MPS
        return self.scene.slow_mps

    def _manoeuvre_step(self, ds: float) -> None:
        """Backing: ends at rest where it was to end (or where the way behind is no longer
        free); then the S out to the offset chosen, heading along it (as ``_ease_back``), over
        what is left before the obstacle if the backing was cut short."""
        m = self._manoeuvre
        if m["phase"] == "back":
            cut = self.speed < -0.05 and not self._free_behind()
            if cut:
                self.speed = 0.0                  # he stops (a hard stop at walking pace)
            if abs(self.speed) < 1e-6 and (cut or self.s - m["to_s"] <= 0.1 or self.s <= 0.0):
                # obstacle_s is where the front stood + what was ahead of it: the front's room
                room = m["obstacle_s"] - self.s - self.DETOUR_CLEAR_M
                m["length"] = max(1.0, min(m["length"], room))
                m["phase"] = "out"
            return
        o0, o1, length = m["o0"], m["o1"], m["length"]
        u = min(1.0, m["u"] + max(ds, 0.0) / length)
        m["u"] = u
        self.offset_m, self.heading_off = self._s_out(o0, o1, u, length)
        if u >= 1.0:
            self.offset_m, self.heading_off = o1, 0.0
            self._manoeuvre = None
            self._held_s = 0.0

    def _clear_nearest(self, corridor_margin_m: float = 0.3) -> None:
        """Take the nearest obstacle in the corridor ahead out of the world (moved 10 km away:
        the renderer, the truth and the collision test all read positions every frame)."""
        rear, length, width = self.scene.footprint
        best, best_k = math.inf, None
        for k, o in enumerate(self.scene.world.obstacles):
            if o.id in self.obstacles_hit:
                continue
            p = self.footprint_in_vehicle(k)
            m = (np.abs(p[:, 1]) <= width / 2 + corridor_margin_m) & (p[:, 0] > -rear)
            if m.any() and float(p[m, 0].min()) < best:
                best, best_k = float(p[m, 0].min()), k
        if best_k is None:
            return
        o = self.scene.world.obstacles[best_k]
        o.walk_time_s, o.vx_mps, o.vy_mps = 0.0, 0.0, 0.0    # a walker stays where put
        o.x, o.y = o.x + 1.0e4, o.y + 1.0e4
        o.x_start, o.y_start = o.x, o.y
        o.z0 = float(self.scene.world.ground(np.float32(o.x), np.float32(o.y)))
        self.refresh_footprint(best_k)
        self.cleared.append(o.id)

    def stats(self) -> dict:
        return {
            "collisions": self.collisions,
            "obstacles_hit": list(self.obstacles_hit),
            "distance_m": round(self.distance_m, 3),
            "time_s": round(self.time_s, 3),
            "stopped_s": round(self.stopped_s, 3),
            "speed_mps": round(self.speed, 3),
            "command": self.command.value,
            "finished": self.finished,
            "detours": self.detours,
            "cleared": list(self.cleared),
            "overrides": self.overrides,
            "offset_m": round(self.offset_m, 2),
            "manoeuvre": None if self._manoeuvre is None else self._manoeuvre["phase"],
            "clearance_m": round(min(self.clearance_ahead(), 999.0), 2),
            "path_length_m": round(self.path_length_m, 1),
        }
