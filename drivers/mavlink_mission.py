"""The autopilot's mission, read over MAVLink's mission protocol, as the box's planned path
(``mission_path`` of the MAVLink link; ``[zones] follow_path``; docs/vehicle-links.md).

The box is a mission client as a ground station is (mavlink.io "Mission Protocol", download):
MISSION_REQUEST_LIST -> MISSION_COUNT -> MISSION_REQUEST_INT(i) -> MISSION_ITEM_INT(i) ...
-> MISSION_ACK, each request retried after ``retry_s`` up to ``retries`` times. It downloads
when the vehicle first appears, again when the mission changes (MISSION_CURRENT's ``total``
changes, or the vehicle acknowledges someone else's upload) and every ``refresh_s``. After a
change, or a failed read, no mission is used until one is read (straight zones); a periodic
re-read keeps using the one it has.

The path (drivers/mission_path.py) is laid only while the vehicle flies its mission (its
HEARTBEAT's custom mode is ``auto_custom_mode``: ArduPilot Rover AUTO = 10; PX4 AUTO.MISSION =
67371008, main mode 4 and sub mode 4 packed as PX4 does) and its position is fresh: from the
vehicle, to the waypoint MISSION_CURRENT names (or the next one with a position), then on along
the following ones. Every other case gives no path, with the reason in the link's status.

This class does no I/O: the link hands it the vehicle's messages and a ``send`` callable.
"""
from __future__ import annotations

import math

import numpy as np

from drivers.mission_path import (GLOBAL_FRAMES, LOCAL_NED_FRAMES, NAV_POSITION_COMMANDS,
                                  local_en, path_ahead)

MAV_MISSION_ACCEPTED = 0
MISSION_TYPE_MISSION = 0


class MissionReader:
    def __init__(self, sysid: int, compid: int, *, auto_custom_mode: int = 10,
                 retry_s: float = 0.5, retries: int = 5, refresh_s: float = 30.0,
                 max_items: int = 2000, reach_m: float = 15.0, step_m: float = 0.25):
        self.sysid, self.compid = sysid, compid
        self.auto_custom_mode = auto_custom_mode
        self.retry_s, self.retries, self.refresh_s = retry_s, retries, refresh_s
        self.max_items, self.reach_m, self.step_m = max_items, reach_m, step_m
        self.state = "idle"              # idle | downloading | ready | failed
        # the waypoints below are this mission's (a periodic re-read keeps using them; a
        # change, a failure or the first read does not)
        self._usable = False
        self.failure = ""
        self._count: int | None = None
        self._items: dict[int, tuple[int, int, float, float]] = {}
        self._next = 0                   # the item requested (-1: the list itself)
        self._sent_at = -1e9
        self._tries = 0
        self._started_at = -1e9
        self._retry_at = 0.0
        self._want_again = False
        self._total: int | None = None   # MISSION_CURRENT's total, the latest
        self._total_read: int | None = None   # ... when the last download began
        self.current_seq: int | None = None
        self.downloads = 0
        # the mission as waypoints: (mission seq numbers, (N, 2) east/north metres, frame kind)
        self._seqs = np.zeros(0, np.int64)
        self._wp = np.zeros((0, 2))
        self._kind = ""                  # "global" | "local"
        self._ref: tuple[float, float] | None = None   # lat0, lon0 of the global frame

    # ---- messages from the vehicle ------------------------------------------------------------
    def _for_me(self, m) -> bool:
        return (getattr(m, "target_system", -1) == self.sysid and
                getattr(m, "target_component", -1) in (self.compid, 0) and
                getattr(m, "mission_type", 0) == MISSION_TYPE_MISSION)

    def on_message(self, t: str, m, now: float) -> None:
        if t == "MISSION_CURRENT":
            self.current_seq = int(m.seq)
            total = int(getattr(m, "total", 0))
            if total not in (0, 65535):
                self._total = total
                if total != self._total_read and self.state != "downloading":
                    self._want_again = True          # not the mission read last (or unknown)
        elif t == "MISSION_ACK" and not self._for_me(m):
            self._want_again = True                  # the vehicle took someone's upload
        elif t == "MISSION_COUNT" and self._for_me(m) and self.state == "downloading" \
                and self._next == -1:
            n = int(m.count)
            if n > self.max_items:
                self._fail(f"the mission has {n} items (more than {self.max_items})", now)
                return
            self._count, self._items, self._next, self._tries = n, {}, 0, 0
            self._sent_at = -1e9                     # request item 0 at the next service
        elif t in ("MISSION_ITEM_INT", "MISSION_ITEM") and self._for_me(m) and \
                self.state == "downloading" and self._count is not None and \
                int(m.seq) == self._next:
            x, y = float(m.x), float(m.y)
            if t == "MISSION_ITEM_INT":
                scale = 1e-7 if int(m.frame) in GLOBAL_FRAMES else 1e-4
                x, y = x * scale, y * scale
            self._items[self._next] = (int(m.command), int(m.frame), x, y)
            self._next += 1
            self._tries = 0
            self._sent_at = -1e9

    # ---- the download -------------------------------------------------------------------------
    def service(self, now: float, send) -> None:
        """Start, advance or retry the download. ``send(name, *args)`` sends one message
        (pymavlink's ``NAME_send`` with the target first); it may raise (counted by the link)."""
        if self.state in ("idle", "ready", "failed"):
            due = (self.state == "idle" or self._want_again or
                   (self.state == "ready" and now - self._started_at >= self.refresh_s) or
                   (self.state == "failed" and now >= self._retry_at))
            if not due:
                return
            if self.state != "ready" or self._want_again:
                self._usable = False             # changed or never read: not used till read
            self.state, self._want_again, self._count = "downloading", False, None
            self._total_read = self._total
            self._next, self._tries, self._sent_at = -1, 0, -1e9
            self._started_at = now
            self.downloads += 1
        if self._count is not None and self._next >= self._count:
            self._finish(now, send)
            return
        if now - self._sent_at < self.retry_s:
            return
        if self._tries >= self.retries:
            what = "MISSION_COUNT" if self._next == -1 else f"item {self._next}"
            self._fail(f"no {what} after {self.retries} requests", now)
            return
        self._tries += 1
        self._sent_at = now
        if self._next == -1:
            send("mission_request_list", MISSION_TYPE_MISSION)
        else:
            send("mission_request_int", self._next, MISSION_TYPE_MISSION)

    def _fail(self, why: str, now: float) -> None:
        self.state, self.failure = "failed", why
        self._retry_at = now + 5.0
        self._usable = False

    def _finish(self, now: float, send) -> None:
        try:
            send("mission_ack", MAV_MISSION_ACCEPTED, MISSION_TYPE_MISSION)
        except Exception:
            pass                                     # the vehicle times out its side
        seqs, pts, kinds = [], [], set()
        for seq in range(self._count or 0):
            cmd, frame, x, y = self._items[seq]
            if cmd not in NAV_POSITION_COMMANDS:
                continue
            if not (math.isfinite(x) and math.isfinite(y)):
                self._fail(f"item {seq} has a position that is not a number", now)
                return
            if frame in GLOBAL_FRAMES:
                if x == 0.0 and y == 0.0:            # 0, 0: "where the vehicle is then"
                    continue
                if not (-90 <= x <= 90 and -180 <= y <= 180):
                    self._fail(f"item {seq} has latitude/longitude out of range", now)
                    return
                kinds.add("global")
            elif frame in LOCAL_NED_FRAMES:
                kinds.add("local")
            else:
                self._fail(f"item {seq} is in MAV_FRAME {frame}, which the box does not read",
                           now)
                return
            seqs.append(seq)
            pts.append((x, y))
        if len(kinds) > 1:
            self._fail("the mission mixes global and local frames", now)
            return
        self._kind = kinds.pop() if kinds else ""
        p = np.asarray(pts, np.float64).reshape(-1, 2)
        if self._kind == "global":
            self._ref = (float(p[0, 0]), float(p[0, 1]))
            e, n = local_en(p[:, 0], p[:, 1], *self._ref)
            self._wp = np.stack([e, n], 1)
        else:                                        # LOCAL_NED: x north, y east
            self._wp = np.stack([p[:, 1], p[:, 0]], 1) if len(p) else np.zeros((0, 2))
        self._seqs = np.asarray(seqs, np.int64)
        self.state, self.failure, self._usable = "ready", "", True

    # ---- the path -----------------------------------------------------------------------------
    def path(self, mode: int | None, yaw_ned: float | None, global_pos=None, local_pos=None):
        """(path_xy or None, why not). ``global_pos`` (lat, lon) degrees, ``local_pos`` (north,
        east) metres, each None when not fresh; ``yaw_ned`` the vehicle's heading (rad,
        clockwise from north)."""
        if mode != self.auto_custom_mode:
            return None, f"vehicle not in its mission mode (custom mode {mode})"
        if not self._usable:
            return None, (f"mission {self.state}" +
                          (f": {self.failure}" if self.state == "failed" else ""))
        if self.current_seq is None:
            return None, "no MISSION_CURRENT from the vehicle"
        ahead = np.flatnonzero(self._seqs >= self.current_seq)
        if not len(ahead):
            return None, "no waypoint left in the mission"
        if yaw_ned is None or not math.isfinite(yaw_ned):
            return None, "no heading"
        if self._kind == "global":
            if global_pos is None:
                return None, "no fresh GLOBAL_POSITION_INT"
            e, n = local_en(global_pos[0], global_pos[1], *self._ref)
        else:
            if local_pos is None:
                return None, "no fresh LOCAL_POSITION_NED"
            n, e = local_pos
        yaw = math.pi / 2 - yaw_ned                   # east-north frame, counter-clockwise
        p = path_ahead((float(e), float(n), yaw), self._wp, int(ahead[0]), self.reach_m,
                       self.step_m)
        return (p, "") if p is not None else (None, "the vehicle is at its last waypoint")

    def status(self) -> dict:
        return {"state": self.state, "failure": self.failure, "items": self._count,
                "waypoints": int(len(self._wp)), "current_seq": self.current_seq,
                "frame": self._kind, "downloads": self.downloads}
