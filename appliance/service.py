"""systemd integration: the sd_notify protocol and journal-friendly logging.

We speak the notify protocol directly (one datagram per message on $NOTIFY_SOCKET, as
sd_notify(3) documents) instead of through systemd-python: the protocol is a few lines, and
systemd-python needs libsystemd-dev and a compiler on the box at install time. Logging goes to
stderr; under systemd ($JOURNAL_STREAM set) each line carries a syslog priority prefix
("<3>…"), which journald turns into the entry's priority — the same result as
systemd.journal.JournalHandler without the dependency.

- READY=1 once the devices are up and the gate has run a cycle;
- WATCHDOG=1 only after a healthy cycle (on time, sent on every link), at most every quarter
  of WATCHDOG_USEC, so a hung or lagging loop stops the pings and systemd restarts the daemon;
- STATUS=<state>: <reason> on every change of state or reason;
- STOPPING=1 on shutdown (after STOP went out on every link).
"""
from __future__ import annotations

import logging
import os
import socket
import sys
import time


class Notifier:
    def __init__(self, env: dict | None = None):
        env = os.environ if env is None else env
        path = env.get("NOTIFY_SOCKET", "")
        self.address = None
        if path:
            self.address = "\0" + path[1:] if path.startswith("@") else path
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        self.watchdog_s: float | None = None
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._sock: socket.socket | None = None
        self._last_ping = 0.0
        self._last_status = None
        self.sent: list[str] = []         # what went out (for status and tests)
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, text: str) -> bool:
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(text.encode(), self.address)
            self.sent.append(text.split("\n", 1)[0])
            del self.sent[:-20]
            return True
        except OSError:
            self.errors += 1
            return False

    def ready(self, status: str) -> None:
        self.notify(f"READY=1\nSTATUS={status}\nMAINPID={os.getpid()}")
        self._last_status = status

    def status(self, status: str) -> None:
        if status != self._last_status:
            self._last_status = status
            self.notify(f"STATUS={status}")

    def healthy_cycle(self) -> None:
        """Call after each healthy cycle: pings the watchdog at most every WATCHDOG_USEC/4."""
        if self.watchdog_s is None:
            return
        now = time.monotonic()
        if now - self._last_ping >= self.watchdog_s / 4:
            self._last_ping = now
            self.notify("WATCHDOG=1")

    def stopping(self, status: str = "stopping") -> None:
        self.notify(f"STOPPING=1\nSTATUS={status}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class _JournalFormatter(logging.Formatter):
    _PRIO = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6,
             logging.DEBUG: 7}

    def format(self, record):
        prio = self._PRIO.get(record.levelno, 6)
        return f"<{prio}>" + super().format(record)


def setup_logging(verbose: bool = False, env: dict | None = None) -> None:
    env = os.environ if env is None else env
    handler = logging.StreamHandler(sys.stderr)
    if env.get("JOURNAL_STREAM"):
        # journald stamps the time and the unit itself
        handler.setFormatter(_JournalFormatter("%(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter(
            "%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
