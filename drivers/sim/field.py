"""SimField: one deterministic world, a vehicle driving through it, every sensor rendered.

    field = SimField("stubble-day", seed=0, stereo_scale=0.5)
    for i in range(50):
        sample = field.render(stamp_ns=i * 100_000_000, seq=i)
        ...                                   # the box decides
        field.step(0.1, GateState.CLEAR)

``render`` renders the CURRENT pose; ``step`` then moves the vehicle. Everything is a function of
(scene, seed, the command sequence), so runs are reproducible bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from hal.types import (DepthCalibration, DepthFrame, GateState, LaserGeometry, LaserScan, Mount,
                       PinholeCalibration, StereoCalibration, StereoFrame, VehicleState)

from .render import Intrinsics, Lighting, cast_laser, expose, kinect_depth, render_view
from .scenes import SCENES, Scene, build_scene
from .vehicle import Vehicle
from .world import MAT_OBSTACLE

# where the vehicle state's planned path comes from ([sim] path): the route itself (what a
# path can do at best), a survey mission's lane ends as the box builds it from an autopilot's
# mission (drivers/mission_path.py), or none
PATH_SOURCES = ("route", "mission", "none")
SENSORS = ("stereo", "laser", "rgbd")
STEREO_RANGE_M = (0.5, 50.0)       # obstacles farther than this are not "seen" by the stereo


def stereo_calibration(scale: float = 1.0) -> StereoCalibration:
    """The papers' pair: 1280x1024, fx = fy = 1100 (HFOV ~60 deg), 0.75 m baseline, left camera
    at x=1.2, z=1.55 m, pitched 15 deg down. ``scale`` shrinks the image and focal length."""
    w, h = int(round(1280 * scale)), int(round(1024 * scale))
    cam = PinholeCalibration(w, h, 1100.0 * scale, 1100.0 * scale, 640.0 * scale, 512.0 * scale)
    return StereoCalibration(cam, 0.75, Mount(1.2, 0.0, 1.55, 0.0, 15.0, 0.0))


def depth_calibration() -> DepthCalibration:
    """Kinect-class: 640x480, 57 x 43 deg, 0.5-5 m, at x=1.0, z=0.9, pitched 10 deg down."""
    fx = 320.0 / math.tan(math.radians(57.0 / 2))
    fy = 240.0 / math.tan(math.radians(43.0 / 2))
    cam = PinholeCalibration(640, 480, fx, fy, 319.5, 239.5)
    return DepthCalibration(cam, Mount(1.0, 0.0, 0.9, 0.0, 10.0, 0.0), 0.001, 0.5, 5.0)


def laser_geometry() -> LaserGeometry:
    """SICK LMS151-like: +-135 deg, 0.5 deg step, 50 m, at x=1.3, z=0.7 m, level."""
    return LaserGeometry(-135.0, 0.5, 541, 50.0, Mount(1.3, 0.0, 0.7, 0.0, 0.0, 0.0))


def _intr(c: PinholeCalibration) -> Intrinsics:
    return c


@dataclass(frozen=True)
class SimSample:
    stereo: StereoFrame | None
    rgbd: DepthFrame | None
    laser: LaserScan | None
    vehicle: VehicleState
    truth: list[dict]
    pose: tuple[float, float, float]          # world x, y, yaw of the vehicle reference point


class SimField:
    """A simulated field with a vehicle in it. See the module docstring."""

    def __init__(self, scene: str = "stubble-day", seed: int = 0,
                 sensors: tuple[str, ...] = ("stereo", "laser", "rgbd"),
                 stereo_scale: float = 1.0, rate_hz: float = 10.0,
                 decel_mps2: float = 2.5, start_speed_mps: float | None = None,
                 path: str = "route", mission_wp_radius_m: float = 2.0):
        if scene not in SCENES:
            raise ValueError(f"unknown scene {scene!r}; known scenes: {', '.join(sorted(SCENES))}")
        bad = [s for s in sensors if s not in SENSORS]
        if bad:
            raise ValueError(f"unknown sensor(s) {bad}; known: {', '.join(SENSORS)}")
        if not 0.05 <= stereo_scale <= 1.0:
            raise ValueError(f"stereo_scale must be in [0.05, 1], got {stereo_scale}")
        if path not in PATH_SOURCES:
            raise ValueError(f"unknown path source {path!r}; known: {', '.join(PATH_SOURCES)}")
        self.path_source = path
        self.mission_wp_radius_m = float(mission_wp_radius_m)
        self.scene_name = scene
        self.seed = int(seed)
        self.sensors = tuple(sensors)
        self.stereo_scale = float(stereo_scale)
        self.rate_hz = float(rate_hz)
        self.scene: Scene = build_scene(scene, self.seed)
        self.world = self.scene.world
        self.vehicle = Vehicle(self.scene, self.seed, decel_mps2=decel_mps2,
                               start_speed_mps=start_speed_mps)
        self.stereo_calibration = stereo_calibration(stereo_scale) if "stereo" in sensors else None
        self.depth_calibration = depth_calibration() if "rgbd" in sensors else None
        self.laser_geometry = laser_geometry() if "laser" in sensors else None
        self.illumination = self.scene.frame_illumination
        rng = np.random.default_rng([self.seed, 3])
        if self.scene.illumination == "day":
            el = math.radians(rng.uniform(35, 60))
            az = rng.uniform(-math.pi, math.pi)
            sun = (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))
            if self.scene.sun is not None:
                sun = self.scene.sun
            self.lighting = Lighting("day", sun, cloud=self.scene.cloud, dusk=self.scene.dusk,
                                     wind_mps=self.scene.wind_mps)
        else:
            self.lighting = Lighting(self.scene.illumination)
        self._advance_world()

    # ---- the loop -------------------------------------------------------------------------
    def step(self, dt_s: float, command: GateState | None = None) -> None:
        """Advance the vehicle by dt_s under the gate's command (None keeps the last one)."""
        self.vehicle.step(dt_s, command)
        self._advance_world()

    def open_loop(self, frames: int, dt_s: float = 0.1) -> list:
        """``frames`` samples (:meth:`render`, stamped and numbered from 0), the vehicle
        driving on under CLEAR between them: a probe's or a test's course of real rendered
        frames, open loop."""
        out = []
        for i in range(int(frames)):
            out.append(self.render(int(round(i * dt_s * 1e9)), i))
            self.step(dt_s, GateState.CLEAR)
        return out

    def _advance_world(self) -> None:
        """The world's clock follows the vehicle's; walkers walk (their footprints move)."""
        for k in self.world.advance(self.vehicle.time_s, self.vehicle.s):
            self.vehicle.refresh_footprint(k)

    def stats(self) -> dict:
        return self.vehicle.stats()

    def oracle_command(self, margin_m: float = 1.0, reaction_s: float = 0.2) -> GateState:
        """What a perfect box would say: STOP when an obstacle in the corridor ahead is within
        the braking distance (plus a margin), else CLEAR."""
        v = self.vehicle.speed
        d = self.vehicle.clearance_ahead()
        need = v * v / (2 * self.vehicle.decel_mps2) + v * reaction_s + margin_m
        return GateState.STOP if d <= need else GateState.CLEAR

    # ---- sensor poses -----------------------------------------------------------------------
    def _sensor_pose(self, mount: Mount, offset_body=(0.0, 0.0, 0.0)):
        """(centre_world, R optical->world, R body->world) of a sensor."""
        Rwv, O = self.vehicle.world_from_vehicle()
        Rvb = mount.rotation()
        centre = O + Rwv @ (mount.position + Rvb @ np.asarray(offset_body, float))
        return centre, Rwv @ mount.camera_to_vehicle(), Rwv @ Rvb

    def _rng(self, seq: int, sensor: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, 11, int(seq) & 0x7FFFFFFF, sensor])

    # ---- rendering --------------------------------------------------------------------------
    def render_stereo(self, stamp_ns: int, seq: int) -> StereoFrame:
        cal = self.stereo_calibration
        if cal is None:
            raise ValueError("this SimField has no stereo sensor")
        cam = _intr(cal.camera)
        rel = 0.004 / min(1.0, max(self.stereo_scale, 0.25)) ** 0.5
        out = []
        for i, off in enumerate(((0.0, 0.0, 0.0), (0.0, -cal.baseline_m, 0.0))):
            c, r, _ = self._sensor_pose(cal.mount, off)
            v = render_view(self.world, self.lighting, c, r, cam, t_max=80.0, rel_step=rel,
                            need_depth=False)
            out.append(expose(v.radiance, self._rng(seq, i), self.lighting.mode))
        return StereoFrame(int(stamp_ns), int(seq), out[0], out[1], cal, self.illumination)

    def render_rgbd(self, stamp_ns: int, seq: int, view_out: list | None = None) -> DepthFrame:
        cal = self.depth_calibration
        if cal is None:
            raise ValueError("this SimField has no rgbd sensor")
        c, r, _ = self._sensor_pose(cal.mount)
        t_max = 40.0 if self.world.kind == "greenhouse" else 60.0
        v = render_view(self.world, self.lighting, c, r, _intr(cal.camera), t_max=t_max,
                        t_min=0.2, rel_step=0.006, min_step=0.008)
        colour = expose(v.radiance, self._rng(seq, 2), self.lighting.mode)
        depth = kinect_depth(v, self.world, self._rng(seq, 3), cal.min_range_m, cal.max_range_m,
                             cal.camera.fx)
        if view_out is not None:
            view_out.append(v)
        return DepthFrame(int(stamp_ns), int(seq), colour, depth, cal)

    def render_laser(self, stamp_ns: int, seq: int, geometry: LaserGeometry | None = None,
                     sensor: int = 4) -> LaserScan:
        """The field's laser scan; ``geometry`` another scanner's (a second laser, mounted
        elsewhere: tools/tilted_laser_probe.py), ``sensor`` its own noise stream."""
        g = geometry or self.laser_geometry
        if g is None:
            raise ValueError("this SimField has no laser")
        c, _, rb = self._sensor_pose(g.mount)
        a = g.angles_rad()
        dirs = (rb @ np.stack([np.cos(a), np.sin(a), np.zeros_like(a)])).T
        ranges = cast_laser(self.world, c, dirs, g.range_max_m)
        # range noise (~1 cm), a return must be beyond the minimum range
        noise = self._rng(seq, sensor).standard_normal(ranges.shape).astype(np.float32) * 0.01
        ranges = np.where(ranges > 0.05, ranges + noise, np.nan).astype(np.float32)
        return LaserScan(int(stamp_ns), int(seq), ranges, g)

    def vehicle_state(self, stamp_ns: int, seq: int) -> VehicleState:
        roll, pitch, _ = self.vehicle.attitude()
        _, _, yaw = self.vehicle.pose()
        return VehicleState(int(stamp_ns), int(seq), float(self.vehicle.speed),
                            float(self.vehicle.yaw_rate), float(roll), float(pitch), float(yaw),
                            path_xy=self._planned_path())

    def _planned_path(self) -> np.ndarray | None:
        """What the vehicle state carries as the planned path (``[sim] path``)."""
        if self.path_source == "route":
            return self.vehicle.planned_path()
        if self.path_source == "mission":
            return self.vehicle.mission_path(self.mission_wp_radius_m)
        return None

    def render(self, stamp_ns: int, seq: int) -> SimSample:
        """Every sensor of the field at the current pose."""
        stereo = self.render_stereo(stamp_ns, seq) if self.stereo_calibration else None
        rgbd = self.render_rgbd(stamp_ns, seq) if self.depth_calibration else None
        laser = self.render_laser(stamp_ns, seq) if self.laser_geometry else None
        return SimSample(stereo, rgbd, laser, self.vehicle_state(stamp_ns, seq), self.truth(),
                         self.vehicle.pose())

    def set_obstacles(self, obs: list, on_ground: bool = True) -> None:
        """Replace the world's obstacles with ``obs`` (a probe's or a test's field: one
        obstacle set where it is wanted, or one taken away), stood on the ground at their x, y
        (``on_ground``; else their z0 as they are), and the vehicle's collision footprints with
        them."""
        for o in obs:
            if on_ground:
                o.z0 = float(self.world.ground(np.float32(o.x), np.float32(o.y)))
        self.world.obstacles[:] = obs
        self.vehicle._footprints = [self.vehicle._footprint_points(o) for o in obs]

    # ---- ground truth -----------------------------------------------------------------------
    def _cameras(self):
        """(name, centre, R optical->world, PinholeCalibration, (min, max) range) of the cameras."""
        cams = []
        if self.stereo_calibration is not None:
            c, r, _ = self._sensor_pose(self.stereo_calibration.mount)
            cams.append(("stereo", c, r, self.stereo_calibration.camera, STEREO_RANGE_M))
        if self.depth_calibration is not None:
            d = self.depth_calibration
            c, r, _ = self._sensor_pose(d.mount)
            cams.append(("rgbd", c, r, d.camera, (d.min_range_m, d.max_range_m)))
        if not cams:
            # a laser-only run: truth is what the box's stereo camera WOULD see (it is on the
            # vehicle, just not recorded), so laser runs are scored on the same obstacles
            sc = stereo_calibration(1.0)
            c, r, _ = self._sensor_pose(sc.mount)
            cams.append(("stereo", c, r, sc.camera, STEREO_RANGE_M))
        return cams

    # where _visible looks on an obstacle: across its footprint (fractions of its length and
    # width, about its centre; the diagonals at 0.35 so they stay inside a round one) ...
    _FOOT = ((0.0, 0.0), (0.45, 0.0), (-0.45, 0.0), (0.0, 0.45), (0.0, -0.45),
             (0.35, 0.35), (0.35, -0.35), (-0.35, 0.35), (-0.35, -0.35))
    # ... and up it (fractions of its height)
    _UP = (0.15, 0.5, 0.85, 0.97)

    def _visible(self, k: int, cams, xyr: np.ndarray) -> bool:
        """The run format's "obstacles that at least one of the run's cameras can see" (a fully
        hidden one is left out, so a partly visible one is listed): at least one of 36 points
        on the obstacle (nine across its footprint, ``_FOOT``, at four heights, ``_UP``) inside
        a camera's image, within that camera's range (the point's own depth), with a clear
        line of sight past the ground and the other obstacles (stubble is not counted as
        hiding anything).

        Until the twentieth session the obstacle's centre had to be within range and its axis
        inside the image: an obstacle at the edge of the view (its axis just outside), a near
        box of which only the far edge of its top is in view, or one whose front face was
        within the RGB-D camera's 5 m but its centre beyond, was left out, and what the box
        found on it was scored a false positive."""
        o = self.world.obstacles[k]
        yaw = math.radians(o.yaw_deg)
        cy, sy = math.cos(yaw), math.sin(yaw)
        pts = np.array([(o.x + a * o.length_m * cy - b * o.width_m * sy,
                         o.y + a * o.length_m * sy + b * o.width_m * cy, o.z0 + fz * o.height_m)
                        for fz in self._UP for a, b in self._FOOT])
        for _name, c, r, cal, (rmin, rmax) in cams:
            q = (pts - c) @ r                                # optical frame, one row a point
            z = np.where(q[:, 2] > 0.05, q[:, 2], np.nan)
            with np.errstate(invalid="ignore"):
                u = cal.fx * q[:, 0] / z + cal.cx
                v = cal.fy * q[:, 1] / z + cal.cy
                ok = ((z >= rmin) & (z <= rmax) & (u >= 0) & (u < cal.width) & (v >= 0)
                      & (v < cal.height))
            for j in np.flatnonzero(ok):
                if self._line_of_sight(c, pts[j], k, xyr):
                    return True
        return False

    def _line_of_sight(self, c: np.ndarray, p: np.ndarray, k: int, xyr: np.ndarray) -> bool:
        d = p - c
        dist = float(np.linalg.norm(d[:2]))
        o = self.world.obstacles[k]
        stop = max(dist - o.radius - 0.05, 0.0)
        if stop <= 0.1:
            return True
        s = np.arange(0.1, stop, 0.05) / dist
        x, y, z = c[0] + d[0] * s, c[1] + d[1] * s, c[2] + d[2] * s
        # world.height(x, y, stubble=False) with only the obstacles whose footprint circle
        # comes within 0.1 m of the sampled segment (the others stand on none of its samples:
        # the same heights and materials, without testing every obstacle of the field at
        # every sample; the truth of a frame tests up to 36 sight lines per obstacle)
        x32, y32 = np.asarray(x, np.float32), np.asarray(y, np.float32)
        h = self.world.ground(x32, y32)
        near = self._obstacles_near_segment(xyr, np.array([x[0], y[0]]),
                                            np.array([x[-1], y[-1]]))
        h, mat = self.world.obstacle_heights(x32, y32, h.copy(), np.zeros(h.shape, np.int16),
                                             only=near)
        block = (h >= z) & (mat != MAT_OBSTACLE + k)
        return not bool(block.any())

    @staticmethod
    def _obstacles_near_segment(xyr: np.ndarray, a: np.ndarray, b: np.ndarray) -> set[int]:
        """Indices of the obstacles (rows of ``xyr``: x, y, footprint radius) whose footprint
        circle comes within 0.1 m of the segment a-b (world xy)."""
        ab = b - a
        t = np.clip(((xyr[:, :2] - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        gap = np.hypot(*(a + t[:, None] * ab - xyr[:, :2]).T)
        return set(np.flatnonzero(gap <= xyr[:, 2] + 0.1).tolist())

    def truth(self) -> list[dict]:
        """Run-format truth for the current pose: obstacles a camera of the run can see, their
        footprint centres in the vehicle frame (x fwd, y left, z up; attitude included)."""
        cams = self._cameras()
        if not cams:
            return []
        Rwv, O = self.vehicle.world_from_vehicle()
        _, _, yaw = self.vehicle.pose()
        # every obstacle's footprint circle, for the sight lines (walkers moved before this)
        xyr = np.array([(o.x, o.y, o.radius) for o in self.world.obstacles],
                       np.float64).reshape(-1, 3)
        out = []
        for k, o in enumerate(self.world.obstacles):
            if math.hypot(o.x - O[0], o.y - O[1]) > STEREO_RANGE_M[1] + 10:
                continue
            if not self._visible(k, cams, xyr):
                continue
            p = Rwv.T @ (np.array([o.x, o.y, o.z0]) - O)
            yaw_rel = math.degrees(math.radians(o.yaw_deg) - yaw)
            yaw_rel = (yaw_rel + 180.0) % 360.0 - 180.0
            out.append({"id": o.id, "class": o.cls, "x_m": round(float(p[0]), 4),
                        "y_m": round(float(p[1]), 4), "z_m": round(float(p[2]), 4),
                        "length_m": o.length_m, "width_m": o.width_m, "height_m": o.height_m,
                        "yaw_deg": round(yaw_rel, 2)})
            if o.moving:
                # a walker: its ground velocity (not relative to the vehicle) in the level
                # vehicle frame (x forward, y left)
                vx, vy = o.velocity_now(self.world.time_s)
                c, sn = math.cos(yaw), math.sin(yaw)
                out[-1]["vx_mps"] = round(vx * c + vy * sn, 3)
                out[-1]["vy_mps"] = round(-vx * sn + vy * c, 3)
        return out

    # ---- pictures -----------------------------------------------------------------------------
    def preview(self, image: np.ndarray | None = None) -> np.ndarray:
        return preview(self, image)


def preview(field: SimField, image: np.ndarray | None = None) -> np.ndarray:
    """A BGR picture: the first camera image (rendered now unless given) beside a top-down map
    of the path, the obstacles (labelled), the vehicle and the camera's field of view."""
    if image is None:
        if field.stereo_calibration is not None:
            image = field.render_stereo(0, 0).left
        elif field.depth_calibration is not None:
            image = field.render_rgbd(0, 0).color
    H = 512
    if image is not None:
        img = cv2.resize(image, (int(round(image.shape[1] * H / image.shape[0])), H),
                         interpolation=cv2.INTER_AREA)
    else:
        img = np.zeros((H, 0, 3), np.uint8)
    x, y, yaw = field.vehicle.pose()
    span = 60.0 if field.world.kind == "stubble" else 16.0
    scale = H / span                                       # px per metre, map centred ahead
    cxw = x + math.cos(yaw) * span * 0.35
    cyw = y + math.sin(yaw) * span * 0.35
    m = np.full((H, H, 3), (40, 70, 90) if field.world.kind == "stubble" else (60, 75, 95),
                np.uint8)

    def px(wx, wy):
        # map: world +x to the right, +y up
        return (int(round(H / 2 + (wx - cxw) * scale)), int(round(H / 2 - (wy - cyw) * scale)))

    pts = np.array([px(a, b) for a, b in field.scene.path], np.int32)
    cv2.polylines(m, [pts], False, (200, 200, 200), 1, cv2.LINE_AA)
    if field.world.kind == "greenhouse":
        w = field.world
        for kk in range(-3, 4):
            yc = w.path_half_width_m + 0.5 + kk * w.bush_period_m
            cv2.rectangle(m, px(-5, yc + 0.5), px(60, yc - 0.5), (40, 110, 40), -1)
    for o in field.world.obstacles:
        c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
        if o.shape == "cylinder":
            cv2.circle(m, px(o.x, o.y), max(2, int(o.length_m / 2 * scale)), (0, 0, 255), -1)
        else:
            corners = [(o.x + a * c - b * s, o.y + a * s + b * c)
                       for a, b in ((o.length_m / 2, o.width_m / 2), (-o.length_m / 2, o.width_m / 2),
                                    (-o.length_m / 2, -o.width_m / 2), (o.length_m / 2, -o.width_m / 2))]
            cv2.fillPoly(m, [np.array([px(*q) for q in corners], np.int32)], (0, 0, 255))
        cv2.putText(m, o.cls, px(o.x + 0.3, o.y), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (255, 255, 255), 1, cv2.LINE_AA)
    # vehicle footprint and the first camera's field of view
    rear, length, width = field.scene.footprint
    c, s = math.cos(yaw), math.sin(yaw)
    fp = [(-rear, width / 2), (-rear + length, width / 2), (-rear + length, -width / 2),
          (-rear, -width / 2)]
    cv2.fillPoly(m, [np.array([px(x + a * c - b * s, y + a * s + b * c) for a, b in fp], np.int32)],
                 (255, 200, 0))
    cams = field._cameras()
    if cams:
        _, cc, _, cal, (_, rmax) = cams[0]
        half = math.atan(cal.width / (2 * cal.fx))
        rng_m = min(rmax, span)
        for sgn in (-1, 1):
            a = yaw + sgn * half
            cv2.line(m, px(cc[0], cc[1]), px(cc[0] + rng_m * math.cos(a), cc[1] + rng_m * math.sin(a)),
                     (0, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(m, f"{field.scene_name} seed {field.seed}", (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([img, m], axis=1)
