"""A strobe/trigger controller emulator on a serial port (the protocol is in
drivers/strobe_serial.py and docs/hardware.md).

Give it one end of a pty pair (``socat -d -d pty,rawer,link=/tmp/ttyA pty,rawer,link=/tmp/ttyB``
then ``--port /tmp/ttyB``), or let it make its own pseudo-terminal (``--pty``; it prints the path
the driver should open). It counts trigger pulses at the set rate while armed, answers commands,
and takes fault-injection commands on stdin:

    garbage N        send N random bytes
    half             send half a STATUS line (the rest never comes)
    badsum           send a STATUS line with a wrong checksum
    silent | resume  stop / restart answering (the controller hangs)
    stall | fire     the trigger stops / restarts firing (status still answered)
    fault CODE TEXT  report a fault (e.g. ``fault 2 strobe lamp open circuit``); ``fault 0`` clears
    quit

For tests, ``injected`` records (fault, time.monotonic_ns()) as each injected fault goes on the
wire, and ``stall_due_ns`` the moment the first pulse a ``stall`` suppressed was due.
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import os
import sys
import threading
import time

from drivers.strobe_serial import checksum, frame_line

from . import FaultCommands, serve_commands


class StrobeControllerEmulator(FaultCommands):
    model, firmware = "FG-STROBE-EMU", "1.0"

    def __init__(self, fd: int, log=None):
        self.fd = fd
        self.log = log or (lambda **ev: None)
        self.rate_hz = 10.0
        self.armed = False
        self.strobe = False
        self.silent = False
        self.stalled = False
        self.fault_code = 0
        self.injected: collections.deque = collections.deque(maxlen=64)   # (fault, monotonic ns)
        self.stall_due_ns: int | None = None
        self._pulses = 0.0
        self._t = time.monotonic()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.received: list[str] = []
        self._thread = threading.Thread(target=self._run, name="strobe-emu", daemon=True)

    def start(self):
        os.set_blocking(self.fd, False)
        self._thread.start()
        return self

    def stop(self):
        self._stop.set()
        self._thread.join(2)

    # ---- state --------------------------------------------------------------------------------
    def _tick(self):
        now = time.monotonic()
        if self.armed and not self.stalled:
            self._pulses += (now - self._t) * self.rate_hz
        self._t = now

    @property
    def pulses(self) -> int:
        with self._lock:
            self._tick()
            return int(self._pulses)

    def status_payload(self) -> str:
        return (f"STATUS rate={self.rate_hz:.2f} armed={int(self.armed)} strobe={int(self.strobe)}"
                f" pulses={self.pulses} fault={self.fault_code}")

    # ---- wire ---------------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        try:
            os.write(self.fd, data)
        except (BlockingIOError, OSError):
            pass       # nobody reading: a real UART drops bytes too

    def answer(self, payload: str) -> None:
        if not self.silent:
            self.write(frame_line(payload))

    def _command(self, line: bytes) -> None:
        text = line.decode("ascii", "replace").strip("\r\n")
        payload, star, cs = text.rpartition("*")
        if not star or checksum(payload) != cs.upper():
            self.answer("ERR 1 bad checksum")
            return
        self.received.append(payload)
        w = payload.split()
        with self._lock:
            self._tick()
            if w[0] == "RATE" and len(w) == 2:
                try:
                    r = float(w[1])
                except ValueError:
                    r = -1
                if not 0.1 <= r <= 60:
                    self.answer("ERR 2 rate out of range")
                    return
                self.rate_hz = r
                self.answer(f"OK RATE {r:.2f}")
            elif w[0] in ("ARM", "DISARM"):
                self.armed = w[0] == "ARM"
                self.answer(f"OK {w[0]}")
            elif w[0] == "STROBE" and len(w) == 2 and w[1] in ("ON", "OFF"):
                self.strobe = w[1] == "ON"
                self.answer(f"OK STROBE {w[1]}")
            elif w[0] == "PING":
                self.answer(f"PONG {self.model} {self.firmware}")
            elif w[0] != "STATUS?":
                self.answer(f"ERR 3 unknown command {w[0]}")
        if w[0] == "STATUS?":
            self.answer(self.status_payload())

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                data = os.read(self.fd, 4096)
            except BlockingIOError:
                data = b""
            except OSError:
                data = b""
                time.sleep(0.05)
            if data:
                buf += data
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    self._command(line)
                buf = buf[-512:]
            else:
                time.sleep(0.005)

    # ---- faults -------------------------------------------------------------------------------
    def handle(self, c: str, w: list[str]) -> bool:
        """One stdin command (see the module doc), ``w`` its words; False if unknown."""
        if c == "garbage":
            n = int(w[1]) if len(w) > 1 else 32
            junk = bytes(b for b in os.urandom(2 * n) if b != 0x0A)[:n]
            self.injected.append((c, time.monotonic_ns()))
            self.write(junk)
        elif c == "half":
            full = frame_line(self.status_payload())
            self.injected.append((c, time.monotonic_ns()))
            self.write(full[:len(full) // 2])
        elif c == "badsum":
            p = self.status_payload()
            self.injected.append((c, time.monotonic_ns()))
            self.write(f"{p}*{(int(checksum(p), 16) ^ 0x5A):02X}\n".encode())
        elif c in ("silent", "resume"):
            self.silent = c == "silent"
        elif c in ("stall", "fire"):
            with self._lock:
                self._tick()
                if c == "stall" and self.armed and not self.stalled:
                    # the next pulse would have fired when the counter reached the next integer
                    wait = (math.floor(self._pulses) + 1 - self._pulses) / self.rate_hz
                    self.stall_due_ns = int((self._t + wait) * 1e9)
                self.stalled = c == "stall"
        elif c == "fault":
            self.fault_code = int(w[1]) if len(w) > 1 else 1
            if self.fault_code:
                self.answer(f"FAULT {self.fault_code} {' '.join(w[2:]) or 'fault'}")
        else:
            return False
        return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.emulators.strobe",
                                 description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--port", help="serial device to serve (e.g. one end of a socat pty pair)")
    g.add_argument("--pty", action="store_true", help="make a pseudo-terminal and print its path")
    a = ap.parse_args(argv)

    out_lock = threading.Lock()

    def log(**ev):
        # one write per event, under a lock: the serving thread logs too, and print() writes
        # the text and its newline apart, so two events could share a line (seen in CI: a
        # client's "client" event glued to "listening" when the daemon reconnected at once)
        with out_lock:
            sys.stdout.write(json.dumps(ev) + "\n")
            sys.stdout.flush()

    if a.pty:
        import pty
        import tty
        master, slave = pty.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
        fd = master
    else:
        import termios
        import tty
        fd = os.open(a.port, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(fd)
        except termios.error:
            pass
        path = a.port
    emu = StrobeControllerEmulator(fd, log=log).start()
    log(event="ready", port=path)
    serve_commands(emu)
    return 0


if __name__ == "__main__":
    sys.exit(main())
