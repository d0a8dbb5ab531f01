"""The status endpoint: a local stream socket. A client sends one request line and gets one
answer, then the connection closes:

- ``status`` (or nothing within 0.3 s): one JSON document, the loop's status;
- any other word: handed to the daemon's request handler (``snapshot`` answers PNG bytes,
  ``selftest`` and ``record SECONDS PATH`` answer JSON);
- anything unknown, malformed or failing: ``{"error": "..."}``; the daemon goes on.

``fieldguard status``/``watch``/``snapshot``/``selftest``/``record`` use it; none of them opens
hardware.
"""
from __future__ import annotations

import json
import logging
import os
import socket
import stat
import tempfile
import threading
import time
from pathlib import Path

from hal.errors import ConfigError, FieldguardError

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


MAX_REQUEST = 4096          # bytes in one request line
READ_S = 0.3                # the whole request must arrive within this (slow clients too)
SEND_S = 5.0                # the answer must be taken within this
MAX_CLIENTS = 4             # requests answered at once; more are told "busy"


class StatusServer:
    """The endpoint: a Unix stream socket only (no TCP: the status is local to the box), mode
    0660 in a directory of the daemon's own that group and others cannot write to.

    Every request gets an answer and the daemon goes on: an unknown, malformed (not text, too
    long) or failing request gets ``{"error": ...}``; a client that sends nothing within
    READ_S gets the status; one that sends part of a line gets that part taken as the
    request; at most MAX_CLIENTS are served at once (each in its own thread, so a client that
    reads its answer slowly holds up no one), the others get ``{"error": "busy ..."}`` at once.
    """

    def __init__(self, path: str, provider, handler=None):
        self.path = path or default_socket_path()
        self.provider = provider
        self.handler = handler      # f(words: list[str]) -> bytes | dict
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._slots = threading.BoundedSemaphore(MAX_CLIENTS)
        # connections whose answer is out, still ending (at most READ_S each; beyond these
        # many at once one is closed without taking its unread rest)
        self._ending = threading.BoundedSemaphore(4 * MAX_CLIENTS)
        self.served = 0
        self.refused = 0            # answered "busy"
        self.errors = 0             # requests answered with an error

    def start(self) -> None:
        p = Path(self.path)
        _private_dir(p.parent)
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
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        s.bind(str(p))
        self._bound = True          # only a socket this server bound is removed on stop
        os.chmod(str(p), 0o660)     # before listen(): no one connects while it is wider
        s.listen(8)
        s.settimeout(0.2)
        self._sock = s
        self._thread = threading.Thread(target=self._serve, name="status", daemon=True)
        self._thread.start()

    # -- answering ---------------------------------------------------------------------------
    def answer(self, raw: bytes) -> bytes:
        """The answer to one request line (without its newline; may be empty). Never raises."""
        try:
            doc = self._answer(raw)
        except Exception as exc:          # a bad request never hurts the daemon
            doc = {"error": f"{type(exc).__name__}: {exc}"}
        if isinstance(doc, (bytes, bytearray)):
            return bytes(doc)
        if isinstance(doc, dict) and "error" in doc:
            self.errors += 1
        try:
            return json.dumps(doc, default=str).encode() + b"\n"
        except (TypeError, ValueError) as exc:
            self.errors += 1
            return json.dumps({"error": f"answer not encodable: {exc}"}).encode() + b"\n"

    def _answer(self, raw: bytes):
        if len(raw) > MAX_REQUEST:
            return {"error": f"request longer than {MAX_REQUEST} bytes"}
        try:
            line = raw.decode("utf-8").strip()
        except UnicodeDecodeError:
            return {"error": "request is not UTF-8 text"}
        if not line.isprintable():
            return {"error": "request has control characters"}
        words = line.split()
        if not words or words[0] == "status":
            return self.provider()
        if self.handler is None:
            return {"error": f"unknown request {words[0][:40]!r}"}
        return self.handler(words)

    # -- the socket --------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            if not self._slots.acquire(blocking=False):
                self._refuse(conn)
                continue
            threading.Thread(target=self._client, args=(conn,), name="status-client",
                             daemon=True).start()

    def _refuse(self, conn: socket.socket) -> None:
        """Every slot is taken: say so at once (this holds the accept loop for at most
        ~0.1 s: the request is read, not left to reset the connection)."""
        self.refused += 1
        try:
            conn.settimeout(0.05)
            try:
                conn.recv(MAX_REQUEST + 1)
            except (socket.timeout, BlockingIOError):
                pass
            conn.send(json.dumps({"error": f"busy: {MAX_CLIENTS} requests are being "
                                           "answered, try again"}).encode() + b"\n")
            conn.shutdown(socket.SHUT_WR)
            conn.recv(65536)
        except OSError:
            pass
        finally:
            conn.close()

    def _client(self, conn: socket.socket) -> None:
        slot = True
        try:
            raw = _read_request(conn)
            conn.settimeout(SEND_S)
            conn.sendall(self.answer(raw))
            self.served += 1
            # the answer is out: its slot is free before the client can see the answer end
            # (a client that reads to the end and asks again at once is never told "busy"
            # by its own last request: found as a flaky test under load)
            self._slots.release()
            slot = False
            if self._ending.acquire(blocking=False):
                try:
                    _finish(conn)
                finally:
                    self._ending.release()
        except Exception as exc:          # the client went away, or was too slow to read
            log.warning("status request failed: %s", exc)
        finally:
            conn.close()
            if slot:
                self._slots.release()

    def stop(self) -> None:
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if getattr(self, "_bound", False):
            Path(self.path).unlink(missing_ok=True)


def _read_request(conn: socket.socket) -> bytes:
    """One request line: the bytes up to the first newline, or what came within READ_S
    (possibly nothing), at most MAX_REQUEST + 1 bytes (more: the request is refused)."""
    deadline = time.monotonic() + READ_S
    buf = b""
    while b"\n" not in buf and len(buf) <= MAX_REQUEST:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        conn.settimeout(left)
        try:
            chunk = conn.recv(MAX_REQUEST + 1 - len(buf))
        except (socket.timeout, BlockingIOError):
            break
        if not chunk:
            break
        buf += chunk
    return buf.split(b"\n", 1)[0].rstrip(b"\r")


def _finish(conn: socket.socket) -> None:
    """End the answer, then take (briefly) what the client sent beyond its request: closing
    with unread bytes would reset the connection and could lose the answer on its way."""
    try:
        conn.shutdown(socket.SHUT_WR)
        conn.settimeout(0.05)
        deadline = time.monotonic() + READ_S
        while time.monotonic() < deadline and conn.recv(65536):
            pass
    except OSError:
        pass


def _private_dir(d: Path) -> None:
    """The socket's directory: created 0750 if missing; refused if others could swap the socket
    (writable by group or others without the sticky bit, or owned by another user)."""
    d.mkdir(parents=True, exist_ok=True, mode=0o750)
    st = d.stat()
    if st.st_uid != os.geteuid() and st.st_uid != 0:
        raise ConfigError(f"{d} belongs to uid {st.st_uid}, not to this daemon "
                          f"(uid {os.geteuid()}): choose another [status] socket",
                          key="status.socket")
    if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
        raise ConfigError(f"{d} is writable by others (mode {st.st_mode & 0o777:o}): someone "
                          f"could replace the status socket; choose another [status] socket "
                          f"or chmod g-w,o-w it", key="status.socket")


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
    except (ConnectionResetError, BrokenPipeError) as exc:
        raise ConnectionError(f"the daemon on {p} closed the connection ({exc.strerror}): "
                              f"try again") from None
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
