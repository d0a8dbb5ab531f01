"""cola: bytes from the SICK laser's TCP stream (CoLa-A telegrams).

The input is the byte stream as the driver receives it; the first byte picks how it is cut into
recv() chunks (a telegram split across reads is the normal case on TCP). Every chunk goes
through the driver's framer and every framed payload through the driver's telegram handler
(``SickLms1xxLaser._handle``: parse, layout check, geometry, publish), as ``_acquire_once``
does. Besides, every payload goes through ``parse_scandata`` alone, which may refuse it only
with ColaError (a DeviceDataError); a telegram it accepts must give ranges that are finite or
NaN, one per value."""
from __future__ import annotations

import math

import numpy as np

from drivers.sick_lms1xx import ColaError, SickLms1xxLaser, parse_scandata
from hal.clock import ManualClock
from hal.errors import FieldguardError

_laser = None


def _device() -> SickLms1xxLaser:
    global _laser
    if _laser is None:
        _laser = SickLms1xxLaser("laser", ManualClock(10**9), host="127.0.0.1", fault_hold_s=0.0)
    return _laser


def one_input(data: bytes) -> None:
    dev = _device()
    dev.framer.reset()
    dev._layout = None
    dev._geometry = None
    dev._last_counter = None
    if not data:
        return
    step = 1 + data[0] * 7 if data[0] else len(data)
    stream = data[1:]
    for i in range(0, len(stream), step):
        for payload in dev.framer.feed(stream[i:i + step]):
            try:
                tel = parse_scandata(payload)
            except ColaError:
                tel = None
            if tel is not None:
                r = tel.ranges_m("DIST1")
                assert r.shape == tel.channels16["DIST1"].values.shape
                assert not np.isinf(r).any(), "infinite range"
                assert math.isfinite(tel.scan_frequency_hz)
            try:
                dev._handle(payload)
            except FieldguardError:
                raise AssertionError("_handle must turn a bad telegram into a fault, "
                                     "not raise") from None
