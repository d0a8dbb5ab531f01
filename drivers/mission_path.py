"""The planned path from an autopilot's mission (``[zones] follow_path``, docs/zones.md).

An autopilot flying a mission (ArduPilot Rover in AUTO, PX4 in AUTO.MISSION) heads for its
current waypoint and then the ones after it. The box reads the mission over MAVLink's mission
protocol (drivers/mavlink_link.py, ``mission_path``) and lays the planned path as the vehicle's
origin will drive it: from where it is, straight to the current waypoint, then along the legs
between the following waypoints, for as far as the zones reach. The simulator builds the same
path from its route's lane ends (``[sim] path = "mission"``, drivers/sim/vehicle.py) so that a
campaign measures what this path is worth, not the simulator's exact route.

What the legs are not: the turn the autopilot drives at a waypoint (its own: ArduPilot's
S-curves or pivot turns, PX4's acceptance radius) is not in the mission, so the path bends at
the waypoint where the vehicle bends before it. docs/zones.md says what that costs.

Pure geometry, numpy only: no I/O.
"""
from __future__ import annotations

import math

import numpy as np

# MAV_CMD items that carry a position the vehicle drives to (the rest, DO_ and CONDITION_
# commands, are skipped)
NAV_POSITION_COMMANDS = {16: "NAV_WAYPOINT", 17: "NAV_LOITER_UNLIM", 18: "NAV_LOITER_TURNS",
                         19: "NAV_LOITER_TIME", 31: "NAV_LOITER_TO_ALT",
                         82: "NAV_SPLINE_WAYPOINT"}
# MAV_FRAME: x, y = latitude, longitude (degrees; degE7 in MISSION_ITEM_INT)
GLOBAL_FRAMES = {0, 3, 5, 6, 10, 11}
# MAV_FRAME_LOCAL_NED: x = north, y = east, metres (x 1e4 in MISSION_ITEM_INT)
LOCAL_NED_FRAMES = {1}
EARTH_RADIUS_M = 6378137.0


def local_en(lat_deg, lon_deg, lat0_deg: float, lon0_deg: float):
    """(east, north) metres of a latitude/longitude from a reference point (equirectangular:
    within 1 cm over a field a few kilometres across)."""
    k = math.pi / 180.0 * EARTH_RADIUS_M
    east = (np.asarray(lon_deg, np.float64) - lon0_deg) * k * math.cos(math.radians(lat0_deg))
    north = (np.asarray(lat_deg, np.float64) - lat0_deg) * k
    return east, north


def path_ahead(pose: tuple[float, float, float], waypoints, current: int,
               reach_m: float = 15.0, step_m: float = 0.25) -> np.ndarray | None:
    """The path the vehicle's origin will drive, in the vehicle frame (x ahead, y left).

    ``pose``: the origin's (x, y, yaw) in a plane frame (yaw counter-clockwise from x);
    ``waypoints``: (N, 2) in the same frame; ``current``: the index of the waypoint the vehicle
    heads for. The path runs from the origin to it, then along the following ones, every
    ``step_m`` up to ``reach_m`` of path (or the last waypoint). None when there is no waypoint
    left (a finished mission) or the input is not finite."""
    wp = np.asarray(waypoints, np.float64).reshape(-1, 2)
    if not 0 <= current < len(wp) or not np.isfinite(wp[current:]).all():
        return None
    x, y, yaw = (float(v) for v in pose)
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        return None
    pts = np.vstack([[x, y], wp[current:]])
    seg = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    end = min(reach_m, float(s[-1]))
    if end <= 0.0:
        return None
    keep = np.concatenate([[True], seg > 1e-9])          # a waypoint on the one before: no leg
    return polyline_ahead(pts[keep], s[keep], 0.0, reach_m, step_m, (x, y, yaw))


def polyline_ahead(pts: np.ndarray, s: np.ndarray, s0: float, reach_m: float, step_m: float,
                   pose: tuple[float, float, float]) -> np.ndarray:
    """The polyline ``pts`` (N, 2; ``s`` its arc lengths, increasing) from ``s0`` on for
    ``reach_m`` (or to its end), every ``step_m`` and at that end, in the frame of ``pose``
    (x ahead, y left). Shared by the mission's legs and the simulator's route ahead."""
    end = min(s0 + reach_m, float(s[-1]))
    ss = np.append(np.arange(s0, end, step_m), end)
    wx, wy = np.interp(ss, s, pts[:, 0]), np.interp(ss, s, pts[:, 1])
    x, y, yaw = pose
    c, sn = math.cos(yaw), math.sin(yaw)
    dx, dy = wx - x, wy - y
    return np.stack([dx * c + dy * sn, -dx * sn + dy * c], axis=1)
