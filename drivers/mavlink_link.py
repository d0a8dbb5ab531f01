"""The box's link to an autopilot (ArduPilot Rover, PX4) over MAVLink 2, with pymavlink.

Out, from the loop's ``send()`` only (a hung loop therefore falls silent, and the autopilot's
failsafe takes over — see docs/vehicle-links.md):

* HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, component 196) at ``heartbeat_hz`` and on every change
  of state; system_status ACTIVE (CLEAR), CRITICAL (SLOW), EMERGENCY (STOP).
* OBSTACLE_DISTANCE (330) every cycle: 72 sectors, MAV_FRAME_BODY_FRD, ``increment_f`` and
  ``angle_offset`` (centre of element 0) from the sectors' real field of view, cm,
  ``max_distance + 1`` = clear, ``UINT16_MAX`` = no data (never 0). Optionally DISTANCE_SENSOR.
* STATUSTEXT with the reason on every change of state.
* On entering STOP: MAV_CMD_DO_SET_MODE to the hold mode (Rover HOLD = custom mode 4). The
  acquisition thread retries with back-off until COMMAND_ACK says ACCEPTED, the vehicle's
  HEARTBEAT shows the hold mode, or the gate releases. A refusal is a fault (visible in status)
  until the vehicle holds. No automatic resume unless ``resume_custom_mode`` >= 0.

In, in the acquisition thread: ATTITUDE, VFR_HUD, GLOBAL_POSITION_INT, LOCAL_POSITION_NED (speed
and attitude -> VehicleState), HEARTBEAT (mode), COMMAND_ACK. A stale autopilot is NO_DATA; a
burst of malformed packets or non-finite values is a fault.

With ``mission_path``: the autopilot's mission, downloaded over the mission protocol
(drivers/mavlink_mission.py), and MISSION_CURRENT -> the planned path in VehicleState.path_xy
while the vehicle is in ``auto_custom_mode`` (``[zones] follow_path``; docs/vehicle-links.md).

Every write is non-blocking: a socket or serial port that would block is a failed send, never a
stall of the 10 Hz loop.
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
import select
import socket
import threading
import time

from drivers.mavlink_mission import MissionReader
from hal.devices import VehicleLink
from hal.errors import DeviceInitializationError, DeviceOperationError
from hal.types import GateOutput, GateState, VehicleState

log = logging.getLogger("fieldguard.link.mavlink")

COMP_ID_OBSTACLE_AVOIDANCE = 196
UINT16_MAX = 65535
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_STATE = {GateState.CLEAR: 4, GateState.SLOW: 5, GateState.STOP: 6}   # ACTIVE/CRITICAL/EMERGENCY
SEVERITY = {GateState.STOP: 2, GateState.SLOW: 4, GateState.CLEAR: 6}   # CRITICAL/WARNING/INFO
MAV_RESULT = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED",
              4: "FAILED", 5: "IN_PROGRESS", 6: "CANCELLED"}


def obstacle_distances(sectors, min_cm: int, max_cm: int) -> tuple[list[int], float, float]:
    """(distances[72] in cm, increment_f deg, angle_offset deg) for OBSTACLE_DISTANCE.

    More than 72 sectors are merged (nearest wins); unused elements are UINT16_MAX. A sector
    with no obstacle is ``max_cm + 1``; one nearer than ``min_cm`` is sent as ``min_cm`` (an
    autopilot ignores values below min_distance, and 0 is discarded)."""
    secs = list(sectors)
    if not secs:
        return [UINT16_MAX] * 72, 2.5, -88.75
    group = max(1, math.ceil(len(secs) / 72))
    inc = (secs[0].angle_max_deg - secs[0].angle_min_deg) * group
    offset = secs[0].angle_min_deg + inc / 2
    out = []
    for g in range(0, len(secs), group):
        ds = [s.distance_m for s in secs[g:g + group]]
        vals = []
        for d in ds:
            if d is None:
                vals.append(max_cm + 1)
            elif not math.isfinite(d) or d < 0:
                vals.append(UINT16_MAX)
            else:
                cm = int(round(d * 100))
                vals.append(max_cm + 1 if cm > max_cm else max(min_cm, cm))
        known = [v for v in vals if v != UINT16_MAX]
        out.append(min(known) if known else UINT16_MAX)
    out += [UINT16_MAX] * (72 - len(out))
    return out[:72], float(inc), float(offset)


def signing_key(text: str) -> bytes:
    """64 hex digits are the 32-byte key itself; anything else is a passphrase, hashed with
    SHA-256 as MAVProxy's ``signing setup`` does."""
    t = text.strip()
    if len(t) == 64:
        try:
            return bytes.fromhex(t)
        except ValueError:
            pass
    return hashlib.sha256(t.encode()).digest()


class _Writer:
    """Takes pymavlink's place as the file it writes to: non-blocking, and it raises when the
    bytes did not go out (pymavlink's own UDP write swallows errors)."""

    def __init__(self, link: "MavlinkVehicleLink"):
        self.link = link
        self._resolved = None

    def write(self, buf) -> None:
        from pymavlink import mavutil
        c = self.link.conn
        buf = bytes(buf)
        try:
            if isinstance(c, mavutil.mavudp):
                if c.udp_server:
                    if not c.clients:
                        raise DeviceOperationError("no vehicle address yet (udpin: nothing "
                                                   "received)")
                    for addr in list(c.clients):
                        c.port.sendto(buf, socket.MSG_DONTWAIT, addr)
                else:
                    if self._resolved is None:
                        host, port = c.destination_addr
                        self._resolved = (socket.gethostbyname(host), port)
                    c.port.sendto(buf, socket.MSG_DONTWAIT, self._resolved)
            elif isinstance(c, mavutil.mavtcp):
                n = c.port.send(buf, socket.MSG_DONTWAIT)
                if n != len(buf):
                    raise DeviceOperationError(f"TCP write short: {n} of {len(buf)} bytes")
            elif isinstance(c, mavutil.mavserial):
                n = c.port.write(buf)            # write_timeout=0: non-blocking
                if n != len(buf):
                    raise DeviceOperationError(f"serial write short: {n} of {len(buf)} bytes")
            else:
                c.write(buf)
        except BlockingIOError:
            raise DeviceOperationError("write would block (link congested)")
        except OSError as exc:
            raise DeviceOperationError(f"write failed: {exc}")
        self.link.last_wire_ns = time.monotonic_ns()


class MavlinkVehicleLink(VehicleLink):
    options_schema = {
        "connection": str, "baud": int, "sysid": int, "target_system": int,
        "target_component": int, "hold_custom_mode": int, "hold_custom_submode": int,
        "resume_custom_mode": int, "resume_custom_submode": int, "heartbeat_hz": float,
        "min_distance_cm": int, "max_distance_cm": int, "distance_sensor": bool,
        "signing_key": str, "ack_timeout_s": float, "retry_max_s": float,
        "stream_hz": float, "bad_packets_per_s_fault": int,
        "mission_path": bool, "auto_custom_mode": int,
    }
    default_timeout_s = 0.5

    def __init__(self, name, clock, timeout_s=0.5, *, connection="udpout:127.0.0.1:14550",
                 baud=115200, sysid=1, target_system=1, target_component=1,
                 hold_custom_mode=4, hold_custom_submode=0, resume_custom_mode=-1,
                 resume_custom_submode=0, heartbeat_hz=1.0, min_distance_cm=20,
                 max_distance_cm=3000, distance_sensor=False, signing_key="",
                 ack_timeout_s=0.3, retry_max_s=2.0, stream_hz=10.0,
                 bad_packets_per_s_fault=5, mission_path=False, auto_custom_mode=10):
        super().__init__(name, clock, timeout_s)
        if not 1 <= sysid <= 255:
            raise ValueError("sysid must be 1..255")
        self.connection, self.baud, self.sysid = connection, baud, sysid
        self.target_system, self.target_component = target_system, target_component
        self.hold_mode = (hold_custom_mode, hold_custom_submode)
        self.resume_mode = (resume_custom_mode, resume_custom_submode)
        self.heartbeat_period_s = 1.0 / max(1.0, heartbeat_hz)
        self.min_cm, self.max_cm = min_distance_cm, max_distance_cm
        self.distance_sensor = distance_sensor
        self.signing = signing_key
        self.ack_timeout_s, self.retry_max_s = ack_timeout_s, retry_max_s
        self.stream_hz = stream_hz
        self.bad_limit = bad_packets_per_s_fault
        self.conn = None
        self.mav = None
        self._tx_lock = threading.Lock()
        self._t0 = time.monotonic()
        self._last_state: GateState | None = None
        self._last_hb = -1e9
        self._text_id = 0
        # vehicle state in
        self._att = None            # (t, roll, pitch, yaw, yawspeed)
        self._speed = None          # (t, speed)
        self._state_seq = 0
        self._bad_times: list[float] = []
        self._quarantine_until = 0.0
        self._quarantine_reason = ""
        self._systems: dict[tuple[int, int], dict] = {}
        self._vehicle_mode: int | None = None
        self._streams_requested_at = -1e9
        # hold
        self._hold_wanted = False
        self._hold_done = False
        self._hold_attempts = 0
        self._hold_next = 0.0
        self._hold_result = ""
        self._hold_refused = ""
        self.last_wire_ns: int | None = None
        # the planned path from the autopilot's mission ([zones] follow_path)
        self.mission = (MissionReader(sysid, COMP_ID_OBSTACLE_AVOIDANCE,
                                      auto_custom_mode=auto_custom_mode)
                        if mission_path else None)
        self._gpos = None           # (t, lat, lon) degrees
        self._lpos = None           # (t, north, east) metres
        self.path_refused = ""

    @classmethod
    def from_config(cls, cfg, clock, shared):
        return cls(cfg.name, clock, cfg.timeout_s, **dict(cfg.options))

    NET_PREFIXES = ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin")

    @classmethod
    def check_options(cls, options) -> tuple[str, str] | None:
        """(key, message) for an option ``open`` would refuse (config check and run agree),
        else None. A connection is ``PREFIX:HOST:PORT`` or a serial device path."""
        # the numbers first: they hold for a serial device as for a network one (a serial
        # path returned before sysid was looked at, and sysid = 0 reached the constructor's
        # ValueError: found by tests/fuzz/fuzz_config.py, corpus regress-sysid-0-serial-path)
        sysid = options.get("sysid", 1)
        if not 1 <= sysid <= 255:
            return "sysid", f"must be 1..255, got {sysid}"
        for key in ("target_system", "target_component"):
            v = options.get(key, 1)
            if not 0 <= v <= 255:
                return key, f"must be 0..255 (0: every system/component), got {v}"
        for key in ("heartbeat_hz", "stream_hz", "ack_timeout_s", "retry_max_s", "baud"):
            if key in options and not options[key] > 0:
                return key, f"must be > 0, got {options[key]}"
        mode = options.get("auto_custom_mode", 10)
        if not 0 <= mode <= 0xFFFFFFFF:
            return "auto_custom_mode", (f"must be a HEARTBEAT custom_mode (0..4294967295), "
                                        f"got {mode}")
        lo, hi = options.get("min_distance_cm", 20), options.get("max_distance_cm", 3000)
        if not 0 <= lo < hi <= 65535:
            return "max_distance_cm" if lo >= 0 else "min_distance_cm", (
                f"needs 0 <= min_distance_cm < max_distance_cm <= 65535 (OBSTACLE_DISTANCE "
                f"sends uint16 cm), got {lo} and {hi}")
        conn = options.get("connection", "udpout:127.0.0.1:14550")
        want = ("expected udpout:HOST:PORT, udpin:HOST:PORT or tcp:HOST:PORT (also udp:, "
                "udpbcast:, tcpin:) or a serial device such as /dev/ttyACM0")
        if conn.startswith("/"):
            return None
        prefix, sep, rest = conn.partition(":")
        host, sep2, port = rest.rpartition(":")
        if not sep or prefix not in cls.NET_PREFIXES:
            return "connection", f"{conn!r} is not a MAVLink connection: {want}"
        if not sep2 or not host or not port.isdigit() or not 0 < int(port) < 65536:
            return "connection", (f"{conn!r}: needs HOST:PORT after {prefix}: (a port 1-65535), "
                                  f"e.g. {prefix}:127.0.0.1:14550")
        return None

    # ---- life cycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        os.environ.setdefault("MAVLINK20", "1")
        try:
            from pymavlink import mavutil
        except ImportError as exc:
            raise DeviceInitializationError(f"pymavlink is needed: {exc}")
        try:
            self.conn = mavutil.mavlink_connection(
                self.connection, baud=self.baud, source_system=self.sysid,
                source_component=COMP_ID_OBSTACLE_AVOIDANCE, dialect="ardupilotmega",
                autoreconnect=False, robust_parsing=True)
        except Exception as exc:
            raise DeviceInitializationError(f"cannot open MAVLink {self.connection!r}: {exc}")
        if self.conn.WIRE_PROTOCOL_VERSION != "2.0":
            self.conn.close()
            raise DeviceInitializationError("pymavlink loaded MAVLink 1; set MAVLINK20=1 before "
                                            "anything imports pymavlink")
        if isinstance(self.conn, mavutil.mavserial):
            self.conn.port.write_timeout = 0
        self.mav = self.conn.mav
        self.mav.file = _Writer(self)
        if self.signing:
            self.conn.setup_signing(signing_key(self.signing), sign_outgoing=True)

    def _close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            conn.close()

    def _now_boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF

    # ---- the loop side ------------------------------------------------------------------------
    def send(self, output: GateOutput) -> bool:
        if self.conn is None:
            return False
        now = time.monotonic()
        try:
            changed = output.state is not self._last_state
            if changed:
                self._on_change(output, now)
            if changed or now - self._last_hb >= self.heartbeat_period_s:
                self._heartbeat(output.state)
                self._last_hb = now
            dist, inc, off = obstacle_distances(output.sectors, self.min_cm, self.max_cm)
            with self._tx_lock:
                self.mav.obstacle_distance_send(
                    int((time.monotonic() - self._t0) * 1e6), 4, dist, 0, self.min_cm,
                    self.max_cm, inc, off, 12)          # sensor UNKNOWN, frame BODY_FRD
                if self.distance_sensor:
                    cur = self.max_cm + 1
                    if output.nearest_m is not None and math.isfinite(output.nearest_m):
                        cur = min(self.max_cm + 1, max(self.min_cm,
                                                       int(round(output.nearest_m * 100))))
                    self.mav.distance_sensor_send(self._now_boot_ms(), self.min_cm, self.max_cm,
                                                  cur, 4, 0, 0, 255)
            self._count("obstacle_distance_sent")
        except DeviceOperationError as exc:
            self._count("send_errors")
            self._fault(f"MAVLink {exc}")
            return False
        return True

    def _heartbeat(self, state: GateState) -> None:
        with self._tx_lock:
            self.mav.heartbeat_send(18, 8, 0, 0, MAV_STATE[state])   # ONBOARD_CONTROLLER, INVALID
        self._count("heartbeats_sent")

    def _on_change(self, output: GateOutput, now: float) -> None:
        prev, self._last_state = self._last_state, output.state
        self._statustext(SEVERITY[output.state],
                         f"fieldguard {output.state.value}: {output.reason}")
        if output.state is GateState.STOP:
            with self._tx_lock:
                self._hold_wanted, self._hold_done = True, False
                self._hold_attempts, self._hold_result = 0, ""
                self._hold_next = now
            self._service_hold(now)            # the first attempt at once
        elif prev is GateState.STOP:
            with self._tx_lock:
                self._hold_wanted = False
                self._hold_refused = ""
                resume = self.resume_mode[0] >= 0 and self._hold_done
            if resume:
                self._set_mode(self.resume_mode, 0)
                self._count("resume_sent")

    def _statustext(self, severity: int, text: str) -> None:
        data = text.encode("ascii", "replace")[:150]
        chunks = [data[i:i + 50] for i in range(0, len(data), 50)] or [b""]
        self._text_id = self._text_id % 65535 + 1
        with self._tx_lock:
            for n, chunk in enumerate(chunks):
                self.mav.statustext_send(severity, chunk, self._text_id if len(chunks) > 1
                                         else 0, n)
        self._count("statustext_sent")

    def _set_mode(self, mode: tuple[int, int], confirmation: int) -> None:
        with self._tx_lock:
            self.mav.command_long_send(self.target_system, self.target_component,
                                       MAV_CMD_DO_SET_MODE, confirmation & 0xFF,
                                       MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode[0], mode[1],
                                       0, 0, 0, 0)

    # ---- hold retries (acquisition thread, and once from send) --------------------------------
    def _service_hold(self, now: float) -> None:
        with self._tx_lock:
            due = self._hold_wanted and not self._hold_done and now >= self._hold_next
            if not due:
                return
            attempt = self._hold_attempts
            self._hold_attempts += 1
            self._hold_next = now + min(self.ack_timeout_s * (2 ** attempt), self.retry_max_s)
        try:
            self._set_mode(self.hold_mode, attempt)
            self._count("hold_sent")
        except DeviceOperationError as exc:
            self._count("hold_send_errors")
            log.warning("%s: HOLD command not sent: %s", self.name, exc)

    def _hold_achieved(self, how: str) -> None:
        with self._tx_lock:
            if not self._hold_wanted or self._hold_done:
                return
            self._hold_done = True
            self._hold_result = how
            refused, self._hold_refused = self._hold_refused, ""
        self._count("hold_acked")
        log.info("%s: vehicle holds (%s)", self.name, how)
        if refused:
            self.clear_fault()

    # ---- the receive side ---------------------------------------------------------------------
    def _acquire_once(self) -> None:
        conn = self.conn
        if conn is None:
            self._stop_evt.wait(0.1)
            return
        wait = 0.05
        if self._hold_wanted and not self._hold_done:    # a HOLD retry is due on time, not
            wait = max(0.0, min(wait, self._hold_next - time.monotonic()))   # up to 50 ms late
        try:
            select.select([conn.fd], [], [], wait)
        except (OSError, ValueError, TypeError):
            self._stop_evt.wait(0.05)
        for _ in range(200):
            try:
                m = conn.recv_msg()
            except Exception as exc:      # pymavlink raises on some garbage
                self._bad_packet(f"{type(exc).__name__}: {exc}")
                continue
            if m is None:
                break
            self._handle(m)
        now = time.monotonic()
        self._service_hold(now)
        self._request_streams(now)
        if self.mission is not None and (self.target_system,
                                         self.target_component) in self._systems:
            self.mission.service(now, self._send_mission)

    def _send_mission(self, name: str, *args) -> None:
        try:
            with self._tx_lock:
                getattr(self.mav, name + "_send")(self.target_system, self.target_component,
                                                  *args)
            self._count("mission_requests_sent")
        except DeviceOperationError:
            self._count("send_errors")

    def _bad_packet(self, why: str) -> None:
        self._count("bad_packets")
        now = time.monotonic()
        self._bad_times = [t for t in self._bad_times if now - t < 1.0] + [now]
        if len(self._bad_times) >= self.bad_limit:
            self._quarantine(f"malformed MAVLink input: {len(self._bad_times)} bad packets in "
                             f"1 s ({why})")

    def _quarantine(self, reason: str) -> None:
        """Stop trusting the autopilot's data for a second: a fault, not merely stale."""
        self._quarantine_until = time.monotonic() + 1.0
        self._quarantine_reason = reason
        self._fault(reason)

    def _handle(self, m) -> None:
        t = m.get_type()
        if t == "BAD_DATA":
            self._bad_packet(getattr(m, "reason", "bad data"))
            return
        src = (m.get_srcSystem(), m.get_srcComponent())
        if t == "HEARTBEAT":
            self._systems[src] = {"sysid": src[0], "compid": src[1], "type": m.type,
                                  "autopilot": m.autopilot, "custom_mode": m.custom_mode,
                                  "armed": bool(m.base_mode & 128), "seen": time.monotonic()}
        if src != (self.target_system, self.target_component):
            return
        now = time.monotonic()
        if t == "HEARTBEAT":
            self._vehicle_mode = m.custom_mode
            if self._hold_wanted and m.custom_mode == self.hold_mode[0]:
                self._hold_achieved(f"vehicle reports mode {m.custom_mode}")
        elif t == "COMMAND_ACK" and m.command == MAV_CMD_DO_SET_MODE:
            self._on_ack(m.result)
        elif t.startswith("MISSION_"):
            if self.mission is not None:
                self.mission.on_message(t, m, now)
            return
        elif t == "ATTITUDE":
            vals = (m.roll, m.pitch, m.yaw, m.yawspeed)
            if not all(math.isfinite(v) for v in vals):
                self._count("bad_values")
                self._quarantine("autopilot sent a non-finite ATTITUDE")
                return
            self._att = (now, *vals)
            self._publish_state(now)
        elif t in ("VFR_HUD", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"):
            if t == "VFR_HUD":
                v = float(m.groundspeed)
            else:
                scale = 0.01 if t == "GLOBAL_POSITION_INT" else 1.0
                vn, ve = m.vx * scale, m.vy * scale
                if t == "GLOBAL_POSITION_INT":
                    lat, lon = m.lat * 1e-7, m.lon * 1e-7
                    if (lat, lon) != (0.0, 0.0) and abs(lat) <= 90 and abs(lon) <= 180:
                        self._gpos = (now, lat, lon)      # 0, 0: no fix
                elif math.isfinite(m.x) and math.isfinite(m.y):
                    self._lpos = (now, float(m.x), float(m.y))
                if self._att is not None:
                    yaw = self._att[3]
                    v = vn * math.cos(yaw) + ve * math.sin(yaw)     # signed, along the heading
                else:
                    v = math.hypot(vn, ve)
            if not math.isfinite(v):
                self._count("bad_values")
                self._quarantine(f"autopilot sent a non-finite speed in {t}")
                return
            self._speed = (now, v)
            self._publish_state(now)

    def _on_ack(self, result: int) -> None:
        name = MAV_RESULT.get(result, str(result))
        self._count(f"ack_{name.lower()}")
        if result == 0:
            self._hold_achieved("COMMAND_ACK ACCEPTED")
        elif result == 5:
            return
        elif self._hold_wanted and not self._hold_done:
            with self._tx_lock:
                self._hold_result = f"refused: {name}"
                self._hold_refused = f"autopilot refused HOLD (mode {self.hold_mode[0]}): {name}"
            self._count("hold_refused")
            self._fault(self._hold_refused)

    def _publish_state(self, now: float) -> None:
        if now < self._quarantine_until:
            self._fault(self._quarantine_reason)
            return
        if self._hold_refused:
            self._fault(self._hold_refused)
            return
        if self._att is None or self._speed is None:
            self._count("incomplete_state")
            return
        if abs(self._att[0] - self._speed[0]) > self.timeout_s:
            self._count("incomplete_state")     # one of the two has stopped coming
            return
        _, roll, pitch, yaw, yawspeed = self._att
        self._state_seq += 1
        # MAVLink: NED body, pitch up positive, yaw clockwise. hal: pitch DOWN positive,
        # yaw (and yaw rate) left positive; roll right-side-down positive in both.
        self._publish(VehicleState(stamp_ns=self.clock.now_ns(), seq=self._state_seq,
                                   speed_mps=self._speed[1], yaw_rate_radps=-yawspeed,
                                   roll_rad=roll, pitch_rad=-pitch, yaw_rad=-yaw,
                                   path_xy=self._planned_path(now, yaw)))

    def _planned_path(self, now: float, yaw_ned: float):
        """The path from the autopilot's mission (``mission_path``), else None; why not in
        ``path_refused`` (the link's status)."""
        if self.mission is None:
            return None
        fresh = lambda p: p is not None and now - p[0] <= self.timeout_s   # noqa: E731
        path, self.path_refused = self.mission.path(
            self._vehicle_mode, yaw_ned,
            global_pos=self._gpos[1:] if fresh(self._gpos) else None,
            local_pos=self._lpos[1:] if fresh(self._lpos) else None)
        if path is not None:
            self._count("paths_sent")
        return path

    def _request_streams(self, now: float) -> None:
        """Ask the autopilot for ATTITUDE and VFR_HUD at stream_hz, when it is there but the
        data is not."""
        if self.stream_hz <= 0 or (self.target_system, self.target_component) not in self._systems:
            return
        fresh = self._att is not None and now - self._att[0] < self.timeout_s
        if fresh or now - self._streams_requested_at < 5.0:
            return
        self._streams_requested_at = now
        try:
            with self._tx_lock:
                for msg_id in (30, 74):
                    self.mav.command_long_send(self.target_system, self.target_component,
                                               MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                               1e6 / self.stream_hz, 0, 0, 0, 0, 0)
        except DeviceOperationError:
            pass

    # ---- status -------------------------------------------------------------------------------
    def peers(self):
        now = time.monotonic()
        out = []
        for (sysid, compid), p in sorted(self._systems.items()):
            d = {k: v for k, v in p.items() if k != "seen"}
            d["age_s"] = round(now - p["seen"], 2)
            d["role"] = ("vehicle" if (sysid, compid) == (self.target_system,
                                                         self.target_component) else "other")
            out.append(d)
        out.append({"role": "self", "connection": self.connection, "sysid": self.sysid,
                    "compid": COMP_ID_OBSTACLE_AVOIDANCE, "signing": bool(self.signing),
                    "hold": {"wanted": self._hold_wanted, "done": self._hold_done,
                             "attempts": self._hold_attempts, "result": self._hold_result,
                             "mode": self.hold_mode[0]},
                    "mission": (None if self.mission is None else
                                dict(self.mission.status(), path=self.path_refused or "used"))})
        return out
