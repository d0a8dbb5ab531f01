"""mavlink: what the autopilot sends the box (HEARTBEAT mode, ATTITUDE, VFR_HUD /
GLOBAL_POSITION_INT / LOCAL_POSITION_NED speed, COMMAND_ACK), mixed with line garbage.

MAVLink 2 frames carry a CRC, so byte-level mutation alone almost never gets a changed field
past pymavlink's parser to the driver. The input is therefore read as a sequence of records:
a record is either raw bytes (garbage, cut frames) or one of the messages above with every
field taken from the input (any float bit pattern: NaN, inf, huge; any integer; any source
system/component), packed by pymavlink with a correct CRC. The byte stream so made is parsed
as the driver's connection does (pymavlink, MAVLink 2, robust parsing) and each message handed
to ``MavlinkVehicleLink._handle`` (a parser exception goes to ``_bad_packet``, as
``_acquire_once`` does). Nothing may escape ``_handle``; a published vehicle state must be
finite."""
from __future__ import annotations

import math
import os
import struct

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from drivers.mavlink_link import MavlinkVehicleLink  # noqa: E402
from hal.clock import ManualClock  # noqa: E402


class _Sink:
    """Where the link's own messages go (HOLD retries, STATUSTEXT): nowhere."""

    def write(self, buf) -> None:
        pass


class _Reader:
    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def left(self) -> int:
        return len(self.data) - self.pos

    def take(self, n: int) -> bytes:
        b = self.data[self.pos:self.pos + n]
        self.pos += n
        return b.ljust(n, b"\0")

    def u(self, fmt: str) -> int:
        return struct.unpack("<" + fmt, self.take(struct.calcsize(fmt)))[0]

    def f(self) -> float:
        return struct.unpack("<f", self.take(4))[0]


def _message(r: _Reader, kind: int):
    if kind == 0:
        return mav.MAVLink_heartbeat_message(r.u("B"), r.u("B"), r.u("B"), r.u("I"), r.u("B"), 3)
    if kind == 1:
        return mav.MAVLink_command_ack_message(176 if r.u("B") < 200 else r.u("H"), r.u("B"),
                                               r.u("B"), r.u("i"), 0, 0)
    if kind == 2:
        return mav.MAVLink_attitude_message(r.u("I"), r.f(), r.f(), r.f(), r.f(), r.f(), r.f())
    if kind == 3:
        return mav.MAVLink_vfr_hud_message(r.f(), r.f(), r.u("h"), r.u("H"), r.f(), r.f())
    if kind == 4:
        return mav.MAVLink_global_position_int_message(r.u("I"), r.u("i"), r.u("i"), r.u("i"),
                                                       r.u("i"), r.u("h"), r.u("h"), r.u("h"),
                                                       r.u("H"))
    return mav.MAVLink_local_position_ned_message(r.u("I"), r.f(), r.f(), r.f(), r.f(), r.f(),
                                                  r.f())


def _stream(data: bytes) -> bytes:
    r = _Reader(data)
    out = bytearray()
    while r.left() > 0:
        head = r.u("B")
        kind = head % 8
        if kind >= 6:                                   # raw bytes
            out += r.take(min(r.left(), 1 + (head >> 3) * 4))
            continue
        # mostly from the configured vehicle (1/1), sometimes anyone
        src, comp = (1, 1) if head < 0xC0 else (r.u("B"), r.u("B"))
        packer = mav.MAVLink(_Sink(), src, comp)
        try:
            out += _message(r, kind).pack(packer)
        except (struct.error, OverflowError):
            pass
    return bytes(out)


_link = None


def _device() -> MavlinkVehicleLink:
    global _link
    if _link is None:
        _link = MavlinkVehicleLink("link", ManualClock(10**9), bad_packets_per_s_fault=5)
        _link.mav = mav.MAVLink(_Sink(), 1, 196)
    return _link


def one_input(data: bytes) -> None:
    link = _device()
    link._att = link._speed = None
    link._quarantine_until = 0.0
    link._bad_times.clear()
    link._hold_wanted = bool(data[:1]) and data[0] & 1 == 1
    link._hold_done = False
    link._hold_refused = ""
    parser = mav.MAVLink(None, 255, 0)
    parser.robust_parsing = True
    stream = _stream(data[1:])
    for i in range(0, len(stream), 64):
        try:
            msgs = parser.parse_buffer(stream[i:i + 64]) or []
        except Exception as exc:      # pymavlink's own; the driver counts it as a bad packet
            link._bad_packet(f"{type(exc).__name__}: {exc}")
            continue
        for m in msgs:
            link._handle(m)
    s, link._sample = link._sample, None
    if s is not None:
        for v in (s.speed_mps, s.yaw_rate_radps, s.roll_rad, s.pitch_rad, s.yaw_rad):
            assert v is None or math.isfinite(v), f"non-finite vehicle state {s}"
