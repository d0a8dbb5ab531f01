"""Stamped data types that cross the HAL. Frozen: a sample is never changed after it is published."""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Mount:
    """A sensor's optical centre in the vehicle frame and its attitude (positive pitch looks down)."""

    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0

    def rotation(self) -> np.ndarray:
        """3x3 rotation taking a vector in the sensor's body frame (x fwd, y left, z up) to the
        vehicle frame. Pitch is positive nose-down, as in the run format."""
        r, p, y = (math.radians(self.roll_deg), math.radians(self.pitch_deg),
                   math.radians(self.yaw_deg))
        return rotation_rpy(r, p, y)

    def camera_to_vehicle(self) -> np.ndarray:
        """3x3 rotation taking a vector in the OPTICAL frame (x right, y down, z forward) to the
        vehicle frame."""
        # optical -> body: z_opt = x_body, x_opt = -y_body, y_opt = -z_body
        opt_to_body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
        return self.rotation() @ opt_to_body

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x_m, self.y_m, self.z_m], dtype=np.float64)


def move_with_vehicle(xy: np.ndarray, dt_s: float, vehicle: "VehicleState | None") -> np.ndarray:
    """Vehicle-frame points fixed in the world, ``dt_s`` later: the grid's own ego-motion
    (``appliance.fusion.GridFusion._ego_motion``) for points (speed and yaw rate over the
    interval; a point at p is at R(-dth) (p - t) in the new frame, t the chord of the arc
    driven). Shared by the grid's hold and stereo-novelty's recall."""
    p = np.asarray(xy, np.float64).reshape(-1, 2)
    if vehicle is None or dt_s <= 0 or not len(p):
        return p
    dx = vehicle.speed_mps * dt_s
    dth = vehicle.yaw_rate_radps * dt_s
    if not (math.isfinite(dx) and math.isfinite(dth)) or (abs(dx) < 1e-9 and abs(dth) < 1e-12):
        return p
    cos, sin = math.cos(-dth), math.sin(-dth)
    t = np.array([dx * math.cos(dth / 2), dx * math.sin(dth / 2)])
    return (p - t) @ np.array([[cos, -sin], [sin, cos]]).T


def rotation_rpy(roll: float, pitch_down: float, yaw: float) -> np.ndarray:
    """Body->parent rotation for roll (about x), pitch (positive nose DOWN) and yaw (about z, left
    positive). Applied as yaw, then pitch, then roll (intrinsic z-y-x)."""
    cr, sr = math.cos(roll), math.sin(roll)
    # nose-down pitch is a positive rotation about +y in a z-up, y-left frame
    cp, sp = math.cos(pitch_down), math.sin(pitch_down)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class PinholeCalibration:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width / (2 * self.fx)))

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2 * math.atan(self.height / (2 * self.fy)))


@dataclass(frozen=True)
class StereoCalibration:
    """A rectified pair: one pinhole model for both, the LEFT camera's mount."""

    camera: PinholeCalibration
    baseline_m: float
    mount: Mount


@dataclass(frozen=True)
class DepthCalibration:
    """An RGB-D camera: depth registered to the colour image."""

    camera: PinholeCalibration
    mount: Mount
    depth_unit_m: float = 0.001
    min_range_m: float = 0.5
    max_range_m: float = 5.0


@dataclass(frozen=True)
class LaserGeometry:
    angle_min_deg: float
    angle_step_deg: float
    beams: int
    range_max_m: float
    mount: Mount

    def angles_rad(self) -> np.ndarray:
        return np.radians(self.angle_min_deg + self.angle_step_deg * np.arange(self.beams))


@dataclass(frozen=True)
class _Stamped:
    stamp_ns: int
    seq: int


@dataclass(frozen=True)
class StereoFrame(_Stamped):
    left: np.ndarray          # HxWx3 uint8 BGR, rectified
    right: np.ndarray
    calib: StereoCalibration
    illumination: str = "day"  # "day" | "night-strobe"


@dataclass(frozen=True)
class DepthFrame(_Stamped):
    color: np.ndarray         # HxWx3 uint8 BGR
    depth_m: np.ndarray       # HxW float32 z-depth in metres, 0 = no reading
    calib: DepthCalibration


@dataclass(frozen=True)
class LaserScan(_Stamped):
    ranges_m: np.ndarray      # (beams,) float32, NaN = no return
    geometry: LaserGeometry


@dataclass(frozen=True)
class VehicleState(_Stamped):
    speed_mps: float = 0.0
    yaw_rate_radps: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    # the path the vehicle's origin will drive, as its autopilot planned it: (N, 2) points in
    # the vehicle frame at this stamp, from the origin on (None: not known). [zones]
    # follow_path lays the zones along it (docs/zones.md)
    path_xy: np.ndarray | None = field(default=None, compare=False, repr=False)


class GateState(enum.Enum):
    STOP = "STOP"
    SLOW = "SLOW"
    CLEAR = "CLEAR"


@dataclass(frozen=True)
class ObstacleSector:
    """Nearest obstacle in one angular sector of the vehicle frame (for OBSTACLE_DISTANCE etc.)."""

    angle_min_deg: float
    angle_max_deg: float
    distance_m: float | None    # None = sector clear


@dataclass(frozen=True)
class GateOutput(_Stamped):
    """What the box tells the vehicle every cycle. ``seq`` is a rolling counter the vehicle side
    checks for freshness."""

    state: GateState
    reason: str
    nearest_m: float | None = None            # nearest obstacle in the stop/slow zones
    speed_limit_mps: float | None = None      # for SLOW
    sectors: tuple[ObstacleSector, ...] = field(default_factory=tuple)
    source_stamp_ns: int | None = None        # capture stamp of the oldest sensor data used

    def checksum(self) -> int:
        """8-bit checksum over counter, state and reason, for the heartbeat on the wire."""
        data = f"{self.seq}|{self.state.value}|{self.reason}".encode()
        return sum(data) & 0xFF
