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

log = logging.getLogger("fieldguard.status")


def default_socket_path() -> str:
    base = os.environ.get("RUNTIME_DIRECTORY") or os.environ.get("FIELDGUARD_RUN_DIR")
    if base:
        return str(Path(base.split(":")[0]) / "status.sock")
    return str(Path(tempfile.gettempdir()) / f"fieldguard-{os.getuid()}" / "status.sock")


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
        Path(self.path).unlink(missing_ok=True)


def request(path: str | None, line: str, timeout_s: float = 5.0) -> bytes:
    """Send one request line to the daemon and return its whole answer. ConnectionError with a
    clear message if no daemon answers."""
    p = path or default_socket_path()
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
        raise ConnectionError(f"no fieldguard daemon is answering on {p} (is it running? "
                              f"`systemctl status fieldguard`, or pass --socket)") from None
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
