"""SICK LMS1xx-class laser over Ethernet: SOPAS CoLa-A telegrams on TCP port 2111.

The driver logs in (``sMN SetAccessMode 03 F4724744``, the "authorised client" level), starts the
measurement (``sMN LMCstartmeas``, ``sMN Run``), subscribes to scans (``sEN LMDscandata 1``) and
parses every ``sSN LMDscandata`` telegram it receives into a :class:`hal.LaserScan`.

CoLa-A frames are ``STX (0x02) <ASCII tokens separated by spaces> ETX (0x03)``. They carry no
checksum (CoLa-B does), so the integrity checks are the framing and the telegram's own structure:
every number must parse, the channel's value count must match the values present and the
trailer must follow, and the scan layout (DIST1 beam count, start angle, step, scale factor and
offset, scan frequency) must be the one the previous telegram on this connection had: a device
does not change it while streaming, so a change is a corrupted header that still parses (one
flipped bit in the start angle would rotate the whole scan). A telegram that fails is counted
(``bad_telegrams``) and marks the device FAULT; bytes outside frames are counted
(``garbage_bytes``); a frame cut off by a new STX is counted (``truncated``). Each of these holds
the FAULT for ``fault_hold_s`` (scans arriving meanwhile are discarded) so the loop sees it. A
corrupted *range value* that is still a valid 16-bit hex number cannot be told from a real one
(CoLa-A has no checksum): such a scan is used as it came. A TCP connection that closes or resets marks FAULT at
once and reconnects with exponential back-off; a connection that stays silent for ``silence_s``
is dropped and reconnected (the base class has already marked the data stale after
``timeout_s``).

Angles: SICK counts the scan angle with 90 deg straight ahead (an LMS1xx scans -45..225 deg). The
HAL's laser frame has 0 deg straight ahead (x forward, y left), so ``angle_offset_deg`` (default
-90) is added to SICK's angles, as the ROS sick_scan driver does. Distances are in mm times the
telegram's scale factor; 0 means no return (NaN in the HAL).

Samples are stamped when the telegram's last byte arrives (the loop's clock), not with the
device's own microsecond counter, which is not synchronised to the box.
"""
from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass, field

import numpy as np

from hal.devices import SafetyLaser, check_timeout
from hal.errors import (DeviceDataError, DeviceInitializationError,
                        DeviceOperationError, DeviceTimeoutError)
from hal.types import LaserGeometry, LaserScan, Mount

from .calibration import MOUNT_SCHEMA, mount_from_options
from .reconnect import Backoff, Reconnecting

STX, ETX = 0x02, 0x03
_WIRE_ERRORS = {"garbage_bytes": "byte(s) outside any telegram",
                "truncated": "telegram(s) cut short", "overflows": "overlong telegram(s)"}
_LAYOUT_FIELDS = ("beams", "start angle", "angle step", "scale factor", "scale offset",
                  "scan frequency")
DEFAULT_PORT = 2111
CLIENT_PASSWORD = "F4724744"     # SOPAS "authorised client" (level 03), the documented default


class ColaError(DeviceDataError):
    """A CoLa-A telegram that cannot be used."""


# ---------------------------------------------------------------------------------------------
# framing
class ColaAFramer:
    """Splits a TCP byte stream into CoLa-A telegram payloads (without STX/ETX).

    Counts ``garbage_bytes`` (outside any frame), ``truncated`` (a frame cut off by the next STX)
    and ``overflows`` (a frame longer than ``max_len`` without ETX, dropped)."""

    def __init__(self, max_len: int = 65536):
        self.max_len = max_len
        self._buf = bytearray()
        self._in_frame = False
        self.garbage_bytes = 0
        self.truncated = 0
        self.overflows = 0

    def reset(self) -> None:
        self._buf.clear()
        self._in_frame = False

    def feed(self, data: bytes) -> list[bytes]:
        out: list[bytes] = []
        i, n = 0, len(data)
        while i < n:
            if not self._in_frame:
                j = data.find(b"\x02", i)
                if j < 0:
                    self.garbage_bytes += n - i
                    break
                self.garbage_bytes += j - i
                self._in_frame = True
                self._buf.clear()
                i = j + 1
                continue
            j_etx = data.find(b"\x03", i)
            j_stx = data.find(b"\x02", i)
            if j_stx >= 0 and (j_etx < 0 or j_stx < j_etx):
                # a new frame starts before this one ended: the earlier one was cut off
                self.truncated += 1
                self._buf.clear()
                i = j_stx + 1
                continue
            if j_etx < 0:
                self._buf += data[i:]
                if len(self._buf) > self.max_len:
                    self.overflows += 1
                    self._buf.clear()
                    self._in_frame = False
                break
            self._buf += data[i:j_etx]
            out.append(bytes(self._buf))
            self._buf.clear()
            self._in_frame = False
            i = j_etx + 1
        return out


# ---------------------------------------------------------------------------------------------
# parsing
@dataclass(frozen=True)
class ColaChannel:
    name: str            # DIST1, DIST2, RSSI1, ...
    scale: float
    offset: float
    start_deg: float     # SICK's angle convention (90 deg = straight ahead on an LMS1xx)
    step_deg: float
    values: np.ndarray   # raw integer values (uint16 or uint8)


@dataclass(frozen=True)
class ScanTelegram:
    version: int
    device_number: int
    serial: int
    device_status: tuple[int, int]
    telegram_counter: int
    scan_counter: int
    time_since_start_us: int
    time_of_tx_us: int
    scan_frequency_hz: float
    measurement_frequency_hz: float
    channels16: dict = field(default_factory=dict)
    channels8: dict = field(default_factory=dict)

    def ranges_m(self, channel: str = "DIST1") -> np.ndarray:
        """Ranges in metres (float32), NaN where the device reported 0 (no return)."""
        ch = self.channels16[channel]
        r = (ch.values.astype(np.float64) * ch.scale + ch.offset) / 1000.0
        r[ch.values == 0] = np.nan
        return r.astype(np.float32)


_HEX_DIGITS = b"0123456789ABCDEFabcdef"


def _hex(tok: bytes, what: str) -> int:
    # digits only: int(x, 16) also takes a sign, "0x" and "_" (a value count of "-7BB" once
    # walked the parser backwards: found by tests/fuzz/fuzz_cola.py)
    if not tok or tok.strip(_HEX_DIGITS):
        raise ColaError(f"bad telegram: {what} {tok[:16]!r} is not hexadecimal")
    return int(tok, 16)


def _int32(tok: bytes, what: str) -> int:
    v = _hex(tok, what)
    if v > 0xFFFFFFFF:
        raise ColaError(f"bad telegram: {what} {tok!r} is out of range")
    return v - (1 << 32) if v & 0x80000000 else v


def _float32(tok: bytes, what: str) -> float:
    v = _hex(tok, what)
    if v > 0xFFFFFFFF:
        raise ColaError(f"bad telegram: {what} {tok!r} is not a 32-bit float")
    f = struct.unpack(">f", struct.pack(">I", v))[0]
    if not np.isfinite(f):
        raise ColaError(f"bad telegram: {what} is not finite")
    return f


def parse_scandata(payload: bytes) -> ScanTelegram:
    """Parse one ``sRA``/``sSN LMDscandata`` payload (without STX/ETX). Raises ColaError."""
    t = payload.split()
    if len(t) < 2 or t[0] not in (b"sSN", b"sRA") or t[1] != b"LMDscandata":
        raise ColaError(f"not a scan telegram: {payload[:32]!r}")
    if len(t) < 21:
        raise ColaError(f"bad telegram: only {len(t)} tokens in the header")
    pos = 2

    def take(n=1):
        nonlocal pos
        if pos + n > len(t):
            raise ColaError(f"bad telegram: ends early ({len(t)} tokens)")
        v = t[pos:pos + n]
        pos += n
        return v

    version = _hex(take()[0], "version")
    devnum = _hex(take()[0], "device number")
    serial = _hex(take()[0], "serial number")
    status = tuple(_hex(x, "device status") for x in take(2))
    tel_counter = _hex(take()[0], "telegram counter")
    scan_counter = _hex(take()[0], "scan counter")
    t_start = _hex(take()[0], "time since start-up")
    t_tx = _hex(take()[0], "time of transmission")
    take(2)  # input status
    take(2)  # output status
    take(1)  # reserved byte A
    scan_freq = _hex(take()[0], "scan frequency") / 100.0
    meas_freq = _hex(take()[0], "measurement frequency") * 100.0
    n_enc = _hex(take()[0], "encoder count")
    if n_enc > 3:
        raise ColaError(f"bad telegram: {n_enc} encoders")
    take(2 * n_enc)

    def channels(bits: int) -> dict:
        out = {}
        n = _hex(take()[0], f"{bits}-bit channel count")
        if n > 5:
            raise ColaError(f"bad telegram: {n} {bits}-bit channels")
        for _ in range(n):
            name = take()[0].decode("ascii", "replace")
            scale = _float32(take()[0], f"{name} scale factor")
            offset = _float32(take()[0], f"{name} scale offset")
            start = _int32(take()[0], f"{name} start angle") / 10000.0
            step = _hex(take()[0], f"{name} angle step") / 10000.0
            count = _hex(take()[0], f"{name} value count")
            if count == 0 or count > 10000 or step <= 0:
                raise ColaError(f"bad telegram: {name} has {count} values, step {step}")
            toks = take(count)
            if any(not x or x.strip(_HEX_DIGITS) for x in toks):
                raise ColaError(f"bad telegram: a {name} value is not hexadecimal")
            try:
                vals = np.array([int(x, 16) for x in toks], dtype=np.int64)
            except ValueError:
                raise ColaError(f"bad telegram: a {name} value is not hexadecimal") from None
            except OverflowError:       # more than 64 bits (found by tests/fuzz/fuzz_cola.py)
                raise ColaError(f"bad telegram: a {name} value does not fit in {bits} "
                                "bits") from None
            if vals.max(initial=0) >= (1 << bits):
                raise ColaError(f"bad telegram: a {name} value does not fit in {bits} bits")
            out[name] = ColaChannel(name, scale, offset, start, step,
                                    vals.astype(np.uint16 if bits == 16 else np.uint8))
        return out

    ch16 = channels(16)
    ch8 = channels(8)
    # trailer: position, name, comment, time, event (each a flag, then its block if 1)
    if pos >= len(t):
        raise ColaError("bad telegram: the trailer is missing (cut short?)")
    if _hex(take()[0], "position flag"):
        take(7)
    if pos < len(t) and _hex(take()[0], "name flag"):
        take(2)
    if pos < len(t) and _hex(take()[0], "comment flag"):
        take(2)
    if pos < len(t) and _hex(take()[0], "time flag"):
        take(7)
    if pos < len(t) and _hex(take()[0], "event flag"):
        take(4)
    if "DIST1" not in ch16:
        raise ColaError("bad telegram: no DIST1 channel")
    return ScanTelegram(version, devnum, serial, status, tel_counter, scan_counter, t_start,
                        t_tx, scan_freq, meas_freq, ch16, ch8)


# ---------------------------------------------------------------------------------------------
class SickLms1xxLaser(Reconnecting, SafetyLaser):
    """A SICK LMS1xx (LMS100/111/151) on TCP 2111, CoLa-A."""

    options_schema = {"host": str, "port": int, "range_max_m": float, "angle_offset_deg": float,
                      "login": bool, "password": str, "silence_s": float,
                      "connect_timeout_s": float, "backoff_max_s": float, "rssi": bool,
                      "fault_hold_s": float,
                      **MOUNT_SCHEMA}
    # one scan period (25 Hz: 40 ms) + 60 ms late tolerance: a silent laser is stale 60 ms after
    # its next scan was due, so the gate stops within two 10 Hz cycles (docs/hardware.md)
    default_timeout_s = 0.1
    DEFAULT_MOUNT = Mount(x_m=1.3, z_m=0.7)
    reconnect_counter = "disconnects"

    def __init__(self, name, clock, host: str = "192.168.0.1", port: int = DEFAULT_PORT,
                 timeout_s: float = default_timeout_s, mount: Mount | None = None,
                 range_max_m: float = 20.0, angle_offset_deg: float = -90.0, login: bool = True,
                 password: str = CLIENT_PASSWORD, silence_s: float = 1.0,
                 connect_timeout_s: float = 0.5, backoff_max_s: float = 2.0, rssi: bool = False,
                 fault_hold_s: float = 0.3):
        super().__init__(name, clock, timeout_s)
        self.host, self.port = host, int(port)
        self.mount = mount or self.DEFAULT_MOUNT
        self.range_max_m = float(range_max_m)
        self.angle_offset_deg = float(angle_offset_deg)
        self.login, self.password = bool(login), password
        self.silence_s = float(silence_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.rssi = bool(rssi)
        self.fault_hold_s = float(fault_hold_s)
        self.backoff = Backoff(0.1, backoff_max_s)
        self.framer = ColaAFramer()
        self._sock: socket.socket | None = None
        self._last_rx = 0.0
        self._geometry: LaserGeometry | None = None
        self._last_counter: int | None = None
        self._layout: tuple | None = None     # the scan layout of the previous telegram
        self.last_telegram: ScanTelegram | None = None
        self.last_rssi: np.ndarray | None = None
        self.device_ident = ""

    @classmethod
    def from_config(cls, cfg, clock, shared):
        o = cfg.options
        check_timeout(cfg.name, cfg.timeout_s, 0.04, "the scan period at 25 Hz")
        return cls(cfg.name, clock, host=o.get("host", "192.168.0.1"),
                   port=o.get("port", DEFAULT_PORT), timeout_s=cfg.timeout_s,
                   mount=mount_from_options(o, cls.DEFAULT_MOUNT),
                   range_max_m=o.get("range_max_m", 20.0),
                   angle_offset_deg=o.get("angle_offset_deg", -90.0), login=o.get("login", True),
                   password=o.get("password", CLIENT_PASSWORD), silence_s=o.get("silence_s", 1.0),
                   connect_timeout_s=o.get("connect_timeout_s", 0.5),
                   backoff_max_s=o.get("backoff_max_s", 2.0), rssi=o.get("rssi", False),
                   fault_hold_s=o.get("fault_hold_s", 0.3))

    # ---- connection ---------------------------------------------------------------------------
    def _open(self) -> None:
        # the first connection is made by the acquisition thread (never blocks start-up);
        # only obviously wrong settings fail here
        if not self.host:
            raise DeviceInitializationError(f"{self.name}: no host configured")
        if not 0 < self.port < 65536:
            raise DeviceInitializationError(f"{self.name}: bad port {self.port}")

    def _close(self) -> None:
        s, self._sock = self._sock, None
        if s is None:
            return
        try:   # best effort: unsubscribe and stop the measurement
            s.settimeout(0.2)
            s.sendall(b"\x02sEN LMDscandata 0\x03\x02sMN LMCstopmeas\x03")
        except OSError:
            pass
        finally:
            s.close()

    def _disconnect(self) -> None:
        s, self._sock = self._sock, None
        if s is not None:
            try:
                s.close()
            except OSError:
                pass
        self.framer.reset()
        self._last_counter = None
        self._layout = None

    def _command(self, text: str, expect: bytes, timeout_s: float = 0.5) -> bytes:
        """Send one CoLa-A command, return the payload of the answer starting with ``expect``
        (scan telegrams arriving meanwhile are handled as usual)."""
        assert self._sock is not None
        self._sock.sendall(b"\x02" + text.encode("ascii") + b"\x03")
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not self._stop_evt.is_set():
            for p in self._receive(min(0.1, max(0.01, end - time.monotonic()))):
                if p.startswith(expect):
                    return p
                if p.startswith(b"sFA"):
                    raise DeviceOperationError(f"{self.name}: device refused {text.split()[1]!r}: "
                                               f"{p.decode('ascii', 'replace')}")
                self._handle(p)
        raise DeviceTimeoutError(f"{self.name}: no answer to {text.split()[1]!r} from "
                                 f"{self.host}:{self.port}")

    def _receive(self, timeout_s: float) -> list[bytes]:
        """Read what arrived within ``timeout_s``; [] on timeout. Raises DeviceOperationError
        when the connection is gone."""
        assert self._sock is not None
        self._sock.settimeout(timeout_s)
        try:
            data = self._sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return []
        except OSError as exc:
            raise DeviceOperationError(f"connection lost: {exc}") from None
        if not data:
            raise DeviceOperationError("connection closed by the device")
        self._last_rx = time.monotonic()
        before = {k: getattr(self.framer, k) for k in _WIRE_ERRORS}
        frames = self.framer.feed(data)
        for k in _WIRE_ERRORS:
            d = getattr(self.framer, k) - before[k]
            if d:
                self._count(k, d)
                self._wire_error(f"bad data on the wire: {d} {_WIRE_ERRORS[k]}")
        return frames

    def _connect(self) -> None:
        try:
            self._sock = socket.create_connection((self.host, self.port),
                                                  timeout=self.connect_timeout_s)
        except OSError as exc:
            self._sock = None
            raise DeviceOperationError(f"cannot connect to {self.host}:{self.port}: "
                                       f"{exc.strerror or exc}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.framer.reset()
        self._layout = None                   # a new connection may bring a new configuration
        self._last_rx = time.monotonic()
        ident = self._command("sRN DeviceIdent", b"sRA DeviceIdent")
        w = ident.decode("ascii", "replace").split()
        self.device_ident = " ".join(w[3::2]) if len(w) >= 4 else "unknown device"
        if self.login:
            ans = self._command(f"sMN SetAccessMode 03 {self.password}", b"sAN SetAccessMode")
            if ans.split()[-1:] != [b"1"]:
                raise DeviceInitializationError(f"{self.name}: login refused (check password)")
            ans = self._command("sMN LMCstartmeas", b"sAN LMCstartmeas")
            if ans.split()[-1:] != [b"0"]:
                raise DeviceOperationError(f"{self.name}: LMCstartmeas refused: {ans!r}")
            self._command("sMN Run", b"sAN Run")
        ans = self._command("sEN LMDscandata 1", b"sEA LMDscandata")
        if ans.split()[-1:] != [b"1"]:
            raise DeviceOperationError(f"{self.name}: scan subscription refused: {ans!r}")
        self._count("connects")

    # ---- acquisition --------------------------------------------------------------------------
    def _acquire_once(self) -> None:
        if self._sock is None:
            self._connect_when_due(self._connect)
            return
        try:
            frames = self._receive(0.1)
        except DeviceOperationError as exc:
            self._drop(str(exc))
            return
        for p in frames:
            self._handle(p)
        if time.monotonic() - self._last_rx > self.silence_s:
            self._drop(f"silent for {self.silence_s:.1f} s: reconnecting")

    def _handle(self, payload: bytes) -> None:
        if not (payload.startswith(b"sSN LMDscandata") or payload.startswith(b"sRA LMDscandata")):
            self._count("other_telegrams")
            return
        try:
            tel = parse_scandata(payload)
        except ColaError as exc:
            self._count("bad_telegrams")
            self._wire_error(str(exc))
            return
        ch = tel.channels16["DIST1"]
        layout = (len(ch.values), ch.start_deg, ch.step_deg, ch.scale, ch.offset,
                  tel.scan_frequency_hz)
        prev, self._layout = self._layout, layout
        if prev is not None and layout != prev:
            # the next telegram with the same layout is accepted again (after fault_hold_s):
            # a real reconfiguration costs one discarded scan and the hold
            self._count("bad_telegrams")
            self._wire_error("bad telegram: the scan layout changed mid-stream (" + ", ".join(
                f"{n} {a:g}, was {b:g}" for n, a, b in zip(_LAYOUT_FIELDS, layout, prev)
                if a != b) + ")")
            return
        if self._last_counter is not None:
            gap = (tel.telegram_counter - self._last_counter - 1) & 0xFFFF
            if 0 < gap < 1000:
                self._count("missed_scans", gap)
        self._last_counter = tel.telegram_counter
        g = self._geometry
        amin = ch.start_deg + self.angle_offset_deg
        if (g is None or g.beams != len(ch.values) or abs(g.angle_min_deg - amin) > 1e-6
                or abs(g.angle_step_deg - ch.step_deg) > 1e-9):
            g = self._geometry = LaserGeometry(amin, ch.step_deg, len(ch.values),
                                               self.range_max_m, self.mount)
        r = tel.ranges_m("DIST1")
        r[r > self.range_max_m] = np.nan
        self.last_telegram = tel
        if self.rssi and "RSSI1" in tel.channels8:
            self.last_rssi = tel.channels8["RSSI1"].values
        self._count("scans")
        self.backoff.reset()
        if self._distrusted():
            self._count("scans_discarded")
            return
        self._publish(LaserScan(stamp_ns=self.clock.now_ns(), seq=tel.scan_counter,
                                ranges_m=r, geometry=g))

    def selftest(self) -> tuple[bool, str]:
        h = self.selftest_health()
        where = f"{self.host}:{self.port}"
        if h.ok:
            tel = self.last_telegram
            freq = f", {tel.scan_frequency_hz:g} Hz" if tel else ""
            return True, (f"streaming from {where} ({self.device_ident or 'LMS1xx'}{freq}, "
                          f"{h.samples} scans)")
        return False, f"{where}: {h.reason or h.state.value}"

