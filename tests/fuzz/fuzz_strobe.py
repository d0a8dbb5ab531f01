"""strobe: bytes from the trigger controller's serial line.

The driver opens a real serial device: here the slave side of a pseudo-terminal (as the strobe
tests and the emulator do), whose master side writes the input and takes what the driver
writes. The driver's ``_acquire_once`` runs as its thread does (line splitting, the
overlong-line guard, checksum, OK/ERR/FAULT/STATUS handling, pulse check, the commands it
sends back) until the line is drained. Nothing may escape ``_acquire_once``, and the driver
must not drop the port over data it should count (a dropped port is a reconnect, not a bad
line). ``parse_line``/``parse_status`` alone may refuse with ValueError only (their
documented error, which the driver turns into a counted fault)."""
from __future__ import annotations

import os
import tty

from drivers.strobe_serial import StrobeSerialTrigger, parse_line, parse_status
from hal.clock import ManualClock

_dev = None
_master = None


def _device() -> StrobeSerialTrigger:
    global _dev, _master
    if _dev is None:
        _master, slave = os.openpty()
        tty.setraw(_master)
        os.set_blocking(_master, False)
        _dev = StrobeSerialTrigger("strobe", ManualClock(10**9), port=os.ttyname(slave),
                                   status_period_s=3600.0, fault_hold_s=0.0)
        _dev._connect()
        os.close(slave)           # the driver has its own descriptor
    return _dev


def _drain_master() -> None:
    try:
        while os.read(_master, 65536):
            pass
    except BlockingIOError:
        pass


def one_input(data: bytes) -> None:
    dev = _device()
    dev._buf = b""
    dev._next_status = float("inf")        # no STATUS? of its own: the input is the traffic
    for i in range(0, max(len(data), 1), 512):
        _drain_master()
        os.write(_master, data[i:i + 512])
        for _ in range(64):
            _drain_master()          # the controller reads what the driver sends (a full pty
            dev._acquire_once()      # buffer is a write timeout: a reconnect, rightly)
            assert dev._ser is not None, f"the driver dropped the port: {dev.health().reason}"
            if not dev._ser.in_waiting:
                break
    _drain_master()
    assert len(dev._buf) <= 512 + 4096, "line buffer grows without bound"
    for line in data.split(b"\n"):
        try:
            payload = parse_line(line)
        except ValueError:
            continue
        assert payload and "\n" not in payload
        if payload.startswith("STATUS"):
            try:
                parse_status(payload)
            except ValueError:
                pass
