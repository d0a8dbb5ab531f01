"""A SICK LMS1xx emulator: SOPAS CoLa-A on TCP (port 2111 on a real device), serving scans
rendered from the simulated field (or any ranges you give it).

It answers what a LMS1xx answers to the commands drivers send (``sRN DeviceIdent``,
``sMN SetAccessMode``, ``sMN LMCstartmeas``/``LMCstopmeas``, ``sMN Run``, ``sEN LMDscandata``,
``sRN LMDscandata``, ``sRN SCdevicestate``), streams ``sSN LMDscandata`` telegrams at the scan
rate to every subscribed client, and lets a test or a technician inject the faults a field
brings: garbage bytes, a telegram cut in half, corrupted numbers, telegrams split into small
pieces, silence, dropped connections.

Run it on the bench::

    python -m drivers.emulators.sick_lms1xx --port 2111 --scene stubble-day --frames 20

then point the driver (``[devices.laser] type = "sick-lms1xx", host = "127.0.0.1"``) at it.
Commands on stdin, one per line:

    silent | resume          stop / restart sending scans (connections stay open)
    garbage N                send N random bytes between two telegrams
    truncate                 send the next telegram cut off half-way (the rest never comes)
    corrupt [angle]          send the next telegram with a value that is not hexadecimal
                             (``angle``: with one bit of the start angle flipped instead, a
                             telegram that still parses but is rotated by 6.55 deg)
    split on|off             send every telegram in 10 pieces (cut after the STX, inside
                             tokens and before the ETX) with 1 ms pauses
    drop                     close every client connection now (the cable is pulled)
    rate HZ                  scans from now on at HZ (e.g. 4: every scan late for a 25 Hz
                             driver's timeout); ``rate 25`` back to normal
    object X_M [WIDTH_M]     put a post X_M metres straight ahead of the scanner
    clear                    remove the post
    quit

Each fault is recorded when its bytes go on the wire (``injected``: (fault, time.monotonic_ns()),
and a ``{"event": "injected", ...}`` line on stdout), so a test can count cycles from the moment
the fault reached the wire rather than from the command.

The telegram encoder here is written separately from the driver's parser on purpose, and is
cross-checked against an independent client (``sick-scan-tcp``) in the tests.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import socket
import struct
import sys
import threading
import time

import numpy as np

from hal.types import LaserGeometry

from . import FaultCommands, serve_commands


# ---------------------------------------------------------------------------------------------
def _h(v: int) -> str:
    return f"{v & 0xFFFFFFFF:X}"


def _hf(f: float) -> str:
    return f"{struct.unpack('>I', struct.pack('>f', f))[0]:08X}"


def encode_scandata(ranges_m: np.ndarray, start_deg_sick: float, step_deg: float, *,
                    telegram_counter: int, scan_counter: int, time_us: int,
                    scan_hz: float = 25.0, serial: int = 0x89A27F,
                    rssi: np.ndarray | None = None, method: str = "sSN",
                    scale: float | None = None) -> bytes:
    """One LMDscandata telegram (with STX/ETX) in the LMS1xx layout. ``ranges_m`` NaN or <= 0 =
    no return (sent as 0); ``start_deg_sick`` in SICK's convention (90 deg = ahead); ``scale``:
    the scale factor (None: 1, or 2 when a range is 65 m or more)."""
    r = np.asarray(ranges_m, dtype=np.float64)
    valid = np.isfinite(r) & (r > 0)
    if scale is None:
        scale = 1.0 if np.nanmax(np.where(valid, r, 0.0), initial=0.0) < 65.0 else 2.0
    mm = np.where(valid, np.round(r * 1000.0 / scale), 0).clip(0, 65535).astype(np.int64)
    start = int(round(start_deg_sick * 10000))
    step = int(round(step_deg * 10000))
    head = ["sRA" if method == "sRA" else "sSN", "LMDscandata", "1", "1", _h(serial),
            "0", "0", _h(telegram_counter & 0xFFFF), _h(scan_counter & 0xFFFF),
            _h(time_us), _h(time_us + 300), "0", "0", "0", "0", "0",
            _h(int(round(scan_hz * 100))), _h(360), "0",       # meas. freq 36 kHz, 0 encoders
            "1", "DIST1", _hf(scale), _hf(0.0), _h(start), _h(step), _h(len(mm))]
    parts = head + [f"{v:X}" for v in mm]
    if rssi is not None:
        q = np.asarray(rssi).astype(np.int64).clip(0, 255)
        parts += ["1", "RSSI1", _hf(1.0), _hf(0.0), _h(start), _h(step), _h(len(q))]
        parts += [f"{v:X}" for v in q]
    else:
        parts += ["0"]
    parts += ["0", "0", "0", "0", "0"]      # position, name, comment, time, event
    return b"\x02" + " ".join(parts).encode("ascii") + b"\x03"


def sim_scans(scene: str = "stubble-day", frames: int = 20, seed: int = 0,
              scan_hz: float = 25.0, speed_mps: float | None = None):
    """``frames`` consecutive scans of the simulated field's laser, the vehicle driving on.
    Returns (geometry, [ranges_m float32 ...])."""
    from drivers.sim.field import SimField
    from hal.types import GateState
    f = SimField(scene=scene, seed=seed, sensors=("laser",), start_speed_mps=speed_mps)
    scans = []
    for i in range(frames):
        if i:
            f.step(1.0 / scan_hz, GateState.CLEAR)
        scans.append(f.render_laser(0, i + 1).ranges_m)
    return f.laser_geometry, scans


# ---------------------------------------------------------------------------------------------
class SickLms1xxEmulator(FaultCommands):
    """A threaded CoLa-A TCP server. ``port=0`` picks a free port (see ``.port``)."""

    ident = "LMS1xx_FG_EMU"
    firmware = "V1.00-fieldguard"

    def __init__(self, geometry: LaserGeometry, scans: list[np.ndarray], host: str = "127.0.0.1",
                 port: int = 0, scan_hz: float = 25.0, serial: int = 0x89A27F,
                 password: str = "F4724744", rssi: bool = True, log=None):
        if not scans:
            raise ValueError("need at least one scan")
        self.geometry = geometry
        self.scans = [np.asarray(s, np.float32) for s in scans]
        self.host, self.port = host, port
        self.scan_hz = float(scan_hz)
        self.declared_hz = self.scan_hz         # what the telegrams say (a late scan is late)
        self.serial = serial
        self.password = password
        self.rssi = rssi
        self.log = log or (lambda **ev: None)
        self.measuring = True           # a real LMS1xx measures from power-on
        self.silent = False
        self.split = False
        self._garbage = 0
        self._truncate = False
        self._corrupt: str | None = None        # None | "hex" | "angle"
        # a device's scale factor does not change while it streams (the driver checks that)
        top = max(float(np.nanmax(np.where(np.isfinite(s), s, 0.0), initial=0.0))
                  for s in self.scans)
        self.scale = 1.0 if top < 65.0 else 2.0
        self.injected: collections.deque = collections.deque(maxlen=64)  # (fault, monotonic ns)
        self._post: tuple[float, float] | None = None
        self._lock = threading.Lock()
        self._clients: list[socket.socket] = []
        self._stop = threading.Event()
        self._srv: socket.socket | None = None
        self.telegram_counter = 0
        self.scan_counter = 0
        self.sent_scans = 0
        self.t0 = time.monotonic()
        self.last_sent: tuple[int, np.ndarray] | None = None   # (telegram counter, ranges)
        self.history: collections.deque = collections.deque(maxlen=16)

    # ---- control ------------------------------------------------------------------------------
    def start(self) -> "SickLms1xxEmulator":
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((self.host, self.port))
        srv.listen(4)
        srv.settimeout(0.1)
        self._srv = srv
        self.port = srv.getsockname()[1]
        threading.Thread(target=self._accept, name="sick-emu-accept", daemon=True).start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self.drop()
        if self._srv is not None:
            self._srv.close()

    def drop(self) -> None:
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()

    def inject_garbage(self, n: int) -> None:
        self._garbage += int(n)

    def truncate_next(self) -> None:
        self._truncate = True

    def corrupt_next(self, how: str = "hex") -> None:
        if how not in ("hex", "angle"):
            raise ValueError(f"corrupt: unknown kind {how!r} (hex or angle)")
        self._corrupt = how

    def put_post(self, x_m: float | None, width_m: float = 0.3) -> None:
        self._post = None if x_m is None else (float(x_m), float(width_m))

    def handle(self, c: str, w: list[str]) -> bool:
        """One stdin command (see the module doc), ``w`` its words; False if unknown."""
        if c == "silent":
            self.silent = True
        elif c == "resume":
            self.silent = False
        elif c == "garbage":
            self.inject_garbage(int(w[1]) if len(w) > 1 else 64)
        elif c == "truncate":
            self.truncate_next()
        elif c == "corrupt":
            self.corrupt_next(w[1] if len(w) > 1 else "hex")
        elif c == "rate":
            self.scan_hz = max(0.2, float(w[1]))
        elif c == "split":
            self.split = len(w) < 2 or w[1] == "on"
        elif c == "drop":
            self.drop()
        elif c == "object":
            self.put_post(float(w[1]), float(w[2]) if len(w) > 2 else 0.3)
        elif c == "clear":
            self.put_post(None)
        else:
            return False
        return True

    # ---- the scans ----------------------------------------------------------------------------
    def _ranges(self) -> np.ndarray:
        r = self.scans[self.scan_counter % len(self.scans)].copy()
        if self._post is not None:
            x, w = self._post
            g = self.geometry
            a = np.radians(g.angle_min_deg + g.angle_step_deg * np.arange(g.beams))
            # a post of width w at distance x straight ahead of the scanner
            hit = (np.abs(x * np.tan(a)) <= w / 2) & (np.cos(a) > 0)
            d = x / np.cos(a[hit])
            r[hit] = np.where(np.isfinite(r[hit]) & (r[hit] < d), r[hit], d)
        return r

    def next_telegram(self, method: str = "sSN") -> bytes:
        with self._lock:
            self.telegram_counter += 1
            self.scan_counter += 1
            r = self._ranges()
            g = self.geometry
            t_us = int((time.monotonic() - self.t0) * 1e6)
            rssi = None
            if self.rssi:
                rssi = np.where(np.isfinite(r), 200 - np.clip(np.nan_to_num(r) * 3, 0, 150), 0)
            tel = encode_scandata(r, g.angle_min_deg + 90.0, g.angle_step_deg,
                                  telegram_counter=self.telegram_counter,
                                  scan_counter=self.scan_counter, time_us=t_us,
                                  scan_hz=self.declared_hz, serial=self.serial, rssi=rssi,
                                  method=method, scale=self.scale)
            self.last_sent = (self.telegram_counter, r)
            self.history.append(self.last_sent)
        return tel

    def _injected(self, fault: str, t: int) -> None:
        """``fault`` went on the wire at ``t`` (time.monotonic_ns() just before the bytes)."""
        self.injected.append((fault, t))
        self.log(event="injected", fault=fault, t_ns=t)

    # ---- server -------------------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                c, addr = self._srv.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._clients.append(c)
            self.log(event="client", peer=f"{addr[0]}:{addr[1]}")
            threading.Thread(target=self._serve, args=(c,), name="sick-emu-client",
                             daemon=True).start()

    def _send(self, c: socket.socket, data: bytes) -> None:
        if self.split and len(data) > 8:
            # few pieces, so the emulator keeps up on a loaded machine (it shares the CPU with
            # the daemon in the tests); every kind of cut is there (byte by byte: the framer's
            # unit test)
            n = len(data)
            cuts = sorted(x for x in {1, n - 1, *(n * k // 8 + k for k in range(1, 8))}
                          if 0 < x < n)
            for a, b in zip([0] + cuts, cuts + [n]):
                c.sendall(data[a:b])
                time.sleep(0.001)
        else:
            c.sendall(data)

    def _answer(self, req: str, state: dict) -> str | None:
        w = req.split()
        if len(w) < 2:
            return "sFA 1"
        kind, name, args = w[0], w[1], w[2:]
        if kind == "sRN" and name == "DeviceIdent":
            return f"sRA DeviceIdent {len(self.ident):X} {self.ident} {len(self.firmware):X} " \
                   f"{self.firmware}"
        if kind == "sMN" and name == "SetAccessMode":
            ok = len(args) == 2 and args[1].upper() == self.password
            state["level"] = int(args[0], 16) if ok else 0
            return f"sAN SetAccessMode {1 if ok else 0}"
        if kind == "sMN" and name in ("LMCstartmeas", "LMCstopmeas"):
            if not state.get("level"):
                return "sFA 2"         # access denied: log in first
            self.measuring = name == "LMCstartmeas"
            return f"sAN {name} 0"
        if kind == "sMN" and name == "Run":
            return "sAN Run 1"
        if kind == "sEN" and name == "LMDscandata":
            state["subscribed"] = bool(args and args[0] == "1")
            return f"sEA LMDscandata {1 if state['subscribed'] else 0}"
        if kind == "sRN" and name == "LMDscandata":
            return None                # answered with a full telegram by the caller
        if kind == "sRN" and name == "SCdevicestate":
            return "sRA SCdevicestate 1"
        return "sFA 5"

    def _serve(self, c: socket.socket) -> None:
        state = {"level": 0, "subscribed": False}
        buf = b""
        next_scan = time.monotonic()
        try:
            while not self._stop.is_set():
                c.settimeout(min(0.05, max(0.001, next_scan - time.monotonic())))
                try:
                    data = c.recv(4096)
                    if not data:
                        break
                    buf += data
                except socket.timeout:
                    pass
                while b"\x03" in buf:
                    frame, buf = buf.split(b"\x03", 1)
                    req = frame[frame.rfind(b"\x02") + 1:].decode("ascii", "replace")
                    ans = self._answer(req, state)
                    if ans is None:
                        self._send(c, self.next_telegram("sRA"))
                    else:
                        self._send(c, b"\x02" + ans.encode("ascii") + b"\x03")
                now = time.monotonic()
                if now < next_scan:
                    continue
                period = 1.0 / self.scan_hz              # "rate" may change it
                next_scan = max(next_scan + period, now - period)
                if not (state["subscribed"] and self.measuring) or self.silent:
                    continue
                faults = []
                if self._garbage:
                    n, self._garbage = self._garbage, 0
                    junk = bytes(b for b in os.urandom(n * 2) if b not in (2, 3))[:n]
                    self._injected("garbage", time.monotonic_ns())
                    c.sendall(junk)
                tel = self.next_telegram()
                if self._truncate:
                    self._truncate = False
                    tel = tel[:len(tel) // 2]
                    faults.append("truncate")
                elif self._corrupt:
                    how, self._corrupt = self._corrupt, None
                    toks = tel.split(b" ")
                    if how == "angle":         # DIST1 start angle: token 23 of the header
                        toks[23] = f"{int(toks[23], 16) ^ 0x10000:X}".encode()
                    else:
                        toks[len(toks) // 2] = b"Z" + toks[len(toks) // 2][1:]
                    tel = b" ".join(toks)
                    faults.append("corrupt" if how == "hex" else "corrupt angle")
                t_tel = time.monotonic_ns()
                self._send(c, tel)
                for f in faults:
                    self._injected(f, t_tel)
                self.sent_scans += 1
        except OSError:
            pass
        finally:
            with self._lock:
                if c in self._clients:
                    self._clients.remove(c)
            try:
                c.close()
            except OSError:
                pass


# ---------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.emulators.sick_lms1xx",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=2111)
    ap.add_argument("--scene", default="stubble-day", help="simulated field scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=20, help="scans rendered, then served in a loop")
    ap.add_argument("--scan-hz", type=float, default=25.0, help="25 or 50 on a real LMS1xx")
    ap.add_argument("--no-rssi", action="store_true", help="leave out the RSSI1 channel")
    ap.add_argument("--object", type=float, default=None, help="a post this far ahead (m)")
    a = ap.parse_args(argv)

    out_lock = threading.Lock()

    def log(**ev):
        # one write per event, under a lock: the serving thread logs too, and print() writes
        # the text and its newline apart, so two events could share a line (seen in CI: a
        # client's "client" event glued to "listening" when the daemon reconnected at once)
        with out_lock:
            sys.stdout.write(json.dumps(ev) + "\n")
            sys.stdout.flush()

    geo, scans = sim_scans(a.scene, max(1, a.frames), a.seed, a.scan_hz)
    emu = SickLms1xxEmulator(geo, scans, host=a.host, port=a.port, scan_hz=a.scan_hz,
                             rssi=not a.no_rssi, log=log)
    if a.object is not None:
        emu.put_post(a.object)
    emu.start()
    log(event="listening", host=a.host, port=emu.port, beams=geo.beams, scan_hz=a.scan_hz)
    serve_commands(emu)
    return 0


if __name__ == "__main__":
    sys.exit(main())
