"""The status endpoint: a local stream socket that answers every connection with one JSON
document (the loop's status) and closes. ``fieldguard status`` reads it; it never opens hardware.
"""
from __future__ import annotations

import json
import logging
import os
import socket
import tempfile
import threading
from pathlib import Path

log = logging.getLogger("fieldguard.status")


def default_socket_path() -> str:
    base = os.environ.get("RUNTIME_DIRECTORY") or os.environ.get("FIELDGUARD_RUN_DIR")
    if base:
        return str(Path(base.split(":")[0]) / "status.sock")
    return str(Path(tempfile.gettempdir()) / f"fieldguard-{os.getuid()}" / "status.sock")


class StatusServer:
    def __init__(self, path: str, provider):
        self.path = path or default_socket_path()
        self.provider = provider
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
                raise RuntimeError(f"another fieldguard daemon is answering on {p}")
            except (ConnectionRefusedError, FileNotFoundError, socket.timeout, OSError) as exc:
                if isinstance(exc, RuntimeError):
                    raise
                p.unlink(missing_ok=True)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.bind(str(p))
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
                conn.settimeout(1.0)
                doc = self.provider()
                conn.sendall(json.dumps(doc, default=str).encode() + b"\n")
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
        Path(self.path).unlink(missing_ok=True)


def read_status(path: str | None = None, timeout_s: float = 2.0) -> dict:
    """Read the daemon's status. Raises ConnectionError with a clear message if none answers."""
    p = path or default_socket_path()
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(p)
        chunks = []
        while True:
            b = s.recv(65536)
            if not b:
                break
            chunks.append(b)
    except (FileNotFoundError, ConnectionRefusedError):
        raise ConnectionError(f"no fieldguard daemon is answering on {p} (is it running? "
                              f"`systemctl status fieldguard`, or pass --socket)") from None
    except socket.timeout:
        raise ConnectionError(f"the daemon on {p} did not answer within {timeout_s} s") from None
    finally:
        s.close()
    return json.loads(b"".join(chunks))
