"""strobe: bytes from the trigger controller's serial line.

The driver reads from a real pyserial port: here pyserial's ``loop://`` port (what is written
to it is read back). The input is written to the port, then the driver's ``_acquire_once``
runs as its thread does (line splitting, overlong-line guard, checksum, OK/ERR/FAULT/STATUS
handling, pulse check) until the port is drained; the driver's own requests (STATUS?, ARM,
RATE) come back too, as harmless well-formed lines. Nothing may escape ``_acquire_once``
(a DeviceError there would mean the driver dropped the port over data it should have counted).
``parse_line``/``parse_status`` alone may refuse with ValueError only (their documented error,
which the driver turns into a counted fault)."""
from __future__ import annotations

import serial

from drivers.strobe_serial import StrobeSerialTrigger, parse_line, parse_status
from hal.clock import ManualClock

_dev = None


def _device() -> StrobeSerialTrigger:
    global _dev
    if _dev is None:
        _dev = StrobeSerialTrigger("strobe", ManualClock(10**9), port="loop://",
                                   status_period_s=3600.0, fault_hold_s=0.0)
    return _dev


def one_input(data: bytes) -> None:
    dev = _device()
    if dev._ser is None:
        dev._ser = serial.serial_for_url("loop://", timeout=0)
    dev._buf = b""
    dev._next_status = float("inf")        # no STATUS? of its own: the input is the traffic
    while not dev._cmds.empty():
        dev._cmds.get_nowait()
    dev._ser.reset_input_buffer()
    dev._ser.write(data)
    for _ in range(8):
        if not dev._ser.in_waiting and not dev._cmds.qsize():
            break
        dev._acquire_once()
        assert dev._ser is not None, f"the driver dropped the port: {dev.health().reason}"
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
