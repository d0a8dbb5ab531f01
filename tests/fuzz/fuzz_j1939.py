"""j1939: CAN frames into the box's J1939 link (address claims and requests, the vehicle's
wheel-based speed, error frames, anything else on the bus).

The link runs on python-can's ``virtual`` bus (a real python-can Bus, in-process); a second
node on the same channel puts the input's frames on the bus and the link's ``_acquire_once``
takes each, as its thread does (address claim state machine, speed decoding through the DBC,
error-frame counting). Each frame is 6 + n bytes of input: a 32-bit identifier, a flags byte
(extended id, error frame, remote, CAN FD), a length byte, then the data. Nothing may escape
``_acquire_once`` except DeviceError (which the thread turns into a fault); a published speed
must be finite. ``J1939Id.parse`` and ``AddressClaimer.on_frame`` are also fed directly."""
from __future__ import annotations

import atexit
import math
import struct

import can

from drivers.can_link import CanJ1939VehicleLink
from drivers.j1939 import AddressClaimer, J1939Id
from hal.clock import ManualClock
from hal.errors import DeviceError

_link = None
_peer = None
_claimer = None


def _setup():
    global _link, _peer, _claimer
    if _link is None:
        _link = CanJ1939VehicleLink("link", ManualClock(10**9), interface="virtual",
                                    channel="fieldguard-fuzz-j1939")
        _link._open()
        _peer = can.Bus(interface="virtual", channel="fieldguard-fuzz-j1939")
        atexit.register(_peer.shutdown)
        atexit.register(_link._close)
        _claimer = AddressClaimer(_link.jname, 0x80)
    return _link, _peer, _claimer


def _frames(data: bytes):
    i = 0
    while i + 6 <= len(data):
        can_id, flags, n = struct.unpack_from("<IBB", data, i)
        i += 6
        fd = bool(flags & 8)
        n = n % (65 if fd else 9)
        payload = data[i:i + n]
        i += n
        yield can.Message(arbitration_id=can_id & (0x1FFFFFFF if flags & 1 else 0x7FF),
                          is_extended_id=bool(flags & 1), is_error_frame=bool(flags & 2),
                          is_remote_frame=bool(flags & 4) and not fd, is_fd=fd,
                          data=payload, check=False)


def one_input(data: bytes) -> None:
    link, peer, claimer = _setup()
    while link.bus.recv(timeout=0) is not None:      # nothing left from the last input
        pass
    link._err_times.clear()
    link._sample = None
    claimer.start(0.0)
    for k, msg in enumerate(_frames(data)):
        jid = J1939Id.parse(msg.arbitration_id)
        assert 0 <= jid.pgn < (1 << 18) and 0 <= jid.sa <= 255
        claimer.on_frame(msg.arbitration_id, bytes(msg.data), float(k))
        claimer.tick(float(k))
        peer.send(msg)
        try:
            link._acquire_once()
        except DeviceError:
            pass
        s, link._sample = link._sample, None
        if s is not None:
            assert math.isfinite(s.speed_mps), f"non-finite speed {s}"
