"""systemd integration: the sd_notify protocol and journal logging.

With systemd-python installed (the ``systemd`` extra; Debian's python3-systemd, or the pip
package where libsystemd's headers exist) the box uses it: ``systemd.daemon.notify`` for the
notify protocol and ``systemd.journal.JournalHandler`` for logging, which gives every entry its
priority, logger name, source file/line and thread as journal fields. Without it, or when a
caller gives its own environment (tests), the fallback speaks the protocols directly: one
datagram per message on $NOTIFY_SOCKET, as sd_notify(3) documents, and log lines on stderr with
a syslog priority prefix ("<3>...") that journald turns into the entry's priority.
``Notifier.backend`` and ``logging_backend()`` say which is in use (``fieldguard status`` shows
it under "systemd").

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


JOURNAL_SOCKET = "/run/systemd/journal/socket"


def _systemd_daemon():
    try:
        from systemd import daemon
    except ImportError:
        return None
    return daemon


def _systemd_journal():
    try:
        from systemd import journal
    except ImportError:
        return None
    return journal


class Notifier:
    """sd_notify. ``backend``: "systemd" (systemd.daemon.notify, when importable and the
    environment is the process's own, which is the one libsystemd reads), "socket" (the
    protocol spoken here), or None (not under systemd: nothing is sent)."""

    def __init__(self, env: dict | None = None, use_library: bool = True):
        own_env = env is None
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
        self._lib = _systemd_daemon() if (use_library and own_env) else None
        self.backend = None if self.address is None else ("systemd" if self._lib else "socket")

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, text: str) -> bool:
        if self.address is None:
            return False
        if self._lib is not None:
            try:
                ok = bool(self._lib.notify(text))
            except (OSError, ValueError):
                ok = False
            if not ok:
                self.errors += 1
                return False
            self.sent.append(text.split("\n", 1)[0])
            del self.sent[:-20]
            return True
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


_logging_backend = "stderr"


def logging_backend() -> str:
    """How log records leave the process: "journal" (systemd.journal), "stderr-journal"
    (priority-prefixed lines on a stderr journald reads) or "stderr"."""
    return _logging_backend


def setup_logging(verbose: bool = False, env: dict | None = None, use_library: bool = True,
                  journal_socket: str = JOURNAL_SOCKET) -> None:
    global _logging_backend
    env = os.environ if env is None else env
    handler = logging.StreamHandler(sys.stderr)
    journal = _systemd_journal() if use_library else None
    if env.get("JOURNAL_STREAM") and journal is not None and _is_socket(journal_socket):
        # native journal entries: priority, logger, file/line, thread as fields
        handler = journal.JournalHandler(SYSLOG_IDENTIFIER="fieldguard")
        handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
        _logging_backend = "journal"
    elif env.get("JOURNAL_STREAM"):
        # journald stamps the time and the unit itself
        handler.setFormatter(_JournalFormatter("%(name)s: %(message)s"))
        _logging_backend = "stderr-journal"
    else:
        _logging_backend = "stderr"
        handler.setFormatter(logging.Formatter(
            "%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)


def _is_socket(path: str) -> bool:
    import stat
    try:
        return stat.S_ISSOCK(os.stat(path).st_mode)
    except OSError:
        return False
