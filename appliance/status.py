"""The status endpoint: a local stream socket. A client sends one request line and gets one
answer, then the connection closes:

- ``status`` (or nothing within 0.3 s): one JSON document, the loop's status;
- any other word: handed to the daemon's request handler (``snapshot`` answers PNG bytes,
  ``selftest`` and ``record SECONDS PATH`` answer JSON).

``fieldguard status``/``watch``/``snapshot``/``selftest``/``record`` use it; none of them opens
hardware.
"""
from __future__ import annotations

import json
import logging
import os
import socket
import tempfile
import threading
from pathlib import Path

from hal.errors import FieldguardError

log = logging.getLogger("fieldguard.status")

# where the installed box keeps its config, and where systemd puts the daemon's socket
# (RuntimeDirectory=fieldguard in deploy/fieldguard.service)
SYSTEM_CONFIG = "/etc/fieldguard/fieldguard.toml"
SYSTEM_SOCKET = "/run/fieldguard/status.sock"


class StatusSocketInUse(FieldguardError):
    """Another daemon answers on the status socket this one was to listen on."""


def default_socket_path() -> str:
    """Where a daemon listens when neither --socket nor ``[status] socket`` says."""
    base = os.environ.get("RUNTIME_DIRECTORY") or os.environ.get("FIELDGUARD_RUN_DIR")
    if base:
        return str(Path(base.split(":")[0]) / "status.sock")
    return str(Path(tempfile.gettempdir()) / f"fieldguard-{os.getuid()}" / "status.sock")


def _system_config_socket() -> str | None:
    """``[status] socket`` of the installed box's config, if it sets one."""
    try:
        import tomllib
        with open(SYSTEM_CONFIG, "rb") as f:
            sock = tomllib.load(f).get("status", {}).get("socket", "")
    except (OSError, ValueError, AttributeError):
        return None
    return sock if isinstance(sock, str) and sock else None


def socket_candidates() -> list[str]:
    """Where a client looks for the daemon, in this order: $RUNTIME_DIRECTORY (or
    $FIELDGUARD_RUN_DIR), ``[status] socket`` of /etc/fieldguard/fieldguard.toml, systemd's
    /run/fieldguard/status.sock, and /tmp/fieldguard-UID/status.sock (a daemon run by hand)."""
    out = []
    base = os.environ.get("RUNTIME_DIRECTORY") or os.environ.get("FIELDGUARD_RUN_DIR")
    if base:
        out.append(str(Path(base.split(":")[0]) / "status.sock"))
    sock = _system_config_socket()
    if sock:
        out.append(sock)
    out.append(SYSTEM_SOCKET)
    out.append(str(Path(tempfile.gettempdir()) / f"fieldguard-{os.getuid()}" / "status.sock"))
    return list(dict.fromkeys(out))


def find_socket(path: str | None = None) -> tuple[str, list[str]]:
    """(the socket to ask, the places looked). An explicit path wins; else the first candidate
    that exists as a socket; else the first candidate (to name in the error)."""
    if path:
        return path, [path]
    cands = socket_candidates()
    for c in cands:
        try:
            if Path(c).is_socket():
                return c, cands
        except OSError:
            continue
    return cands[0], cands


class StatusServer:
    def __init__(self, path: str, provider, handler=None):
        self.path = path or default_socket_path()
        self.provider = provider
        self.handler = handler      # f(words: list[str]) -> bytes | dict
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> None:
        p = Path(self.path)
        p.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        if p.exists() or p.is_socket():
            # a socket left by a dead daemon; refuse if a live one answers
            try:
                probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                probe.settimeout(0.5)
                probe.connect(str(p))
                probe.close()
                raise StatusSocketInUse(
                    f"another fieldguard daemon is answering on {p}: stop it first "
                    f"(`fieldguard status --socket {p}` shows it), or give this one its own "
                    f"--socket PATH")
            except (ConnectionRefusedError, FileNotFoundError, socket.timeout, OSError):
                p.unlink(missing_ok=True)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.bind(str(p))
        self._bound = True          # only a socket this server bound is removed on stop
        os.chmod(str(p), 0o660)
        s.listen(8)
        s.settimeout(0.2)
        self._sock = s
        self._thread = threading.Thread(target=self._serve, name="status", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                conn.settimeout(0.3)
                try:
                    line = conn.makefile("rb").readline(4096).decode(errors="replace").strip()
                except (socket.timeout, OSError):
                    line = ""
                conn.settimeout(5.0)
                words = line.split()
                if not words or words[0] == "status":
                    answer = self.provider()
                elif self.handler is not None:
                    try:
                        answer = self.handler(words)
                    except Exception as exc:          # a bad request never hurts the daemon
                        answer = {"error": f"{type(exc).__name__}: {exc}"}
                else:
                    answer = {"error": f"unknown request {words[0]!r}"}
                if isinstance(answer, (bytes, bytearray)):
                    conn.sendall(bytes(answer))
                else:
                    conn.sendall(json.dumps(answer, default=str).encode() + b"\n")
            except Exception as exc:
                log.warning("status request failed: %s", exc)
            finally:
                conn.close()

    def stop(self) -> None:
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if getattr(self, "_bound", False):
            Path(self.path).unlink(missing_ok=True)


def request(path: str | None, line: str, timeout_s: float = 5.0) -> bytes:
    """Send one request line to the daemon and return its whole answer. ConnectionError with a
    clear message if no daemon answers."""
    p, looked = find_socket(path)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(p)
        s.sendall(line.encode() + b"\n")
        chunks = []
        while True:
            b = s.recv(1 << 16)
            if not b:
                break
            chunks.append(b)
    except (FileNotFoundError, ConnectionRefusedError):
        where = p if len(looked) == 1 else f"{p} (looked in {', '.join(looked)})"
        raise ConnectionError(f"no fieldguard daemon is answering on {where}: is it running? "
                              f"`systemctl status fieldguard`, or pass --socket PATH") from None
    except PermissionError:
        raise ConnectionError(f"not allowed to open {p}: run as root or as a member of the "
                              f"fieldguard group") from None
    except socket.timeout:
        raise ConnectionError(f"the daemon on {p} did not answer within {timeout_s} s") from None
    finally:
        s.close()
    return b"".join(chunks)


def read_status(path: str | None = None, timeout_s: float = 2.0) -> dict:
    """Read the daemon's status. Raises ConnectionError with a clear message if none answers."""
    return json.loads(request(path, "status", timeout_s))


def request_json(path: str | None, line: str, timeout_s: float = 10.0) -> dict:
    doc = json.loads(request(path, line, timeout_s))
    if isinstance(doc, dict) and "error" in doc and len(doc) == 1:
        raise RuntimeError(doc["error"])
    return doc
