"""The web console's HTTP server: read-only, its own threads, never in the loop's way.

The standard library's ThreadingHTTPServer serves it (no framework: a handful of GET routes
need none, and it adds no dependency to the box). Only GET and HEAD exist; every other method
is answered 405, so nothing here can change what the box decides. At most ``MAX_CONNECTIONS``
connections have a thread at once (more get 503 and are closed at accept), the request line
and headers must arrive within ``REQUEST_S``, at most ``MAX_INFLIGHT`` requests are served at
once (others get 503), each read or write times out, HTTP/0.9 is refused, and every answer is
built from what the loop already handed over (``FrameTap``) or from the daemon's status
provider (the same document as ``fieldguard status --json``).
"""
from __future__ import annotations

import io
import json
import logging
import re
import socket
import tarfile
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from appliance.console.tap import FrameTap

log = logging.getLogger("fieldguard.console")

STATIC = Path(__file__).resolve().parent / "static"
_STATIC_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
                 "/app.js": ("app.js", "text/javascript; charset=utf-8"),
                 "/style.css": ("style.css", "text/css; charset=utf-8")}
MAX_INFLIGHT = 8
# A thread per connection, but never more than this many: idle, slow or non-reading clients
# cannot grow the daemon's threads (a browser opens about 6 connections per host).
MAX_CONNECTIONS = 16
# The request line and headers must all arrive within this (a one-byte-a-second client is
# cut off), whatever the per-read timeout.
REQUEST_S = 5.0
_BUSY = (b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\n"
         b"Connection: close\r\n\r\n{\"error\": \"busy: too many connections\"}\n")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def server_activate(self):
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.refused = 0
        super().server_activate()

    def process_request(self, request, client_address):
        if not self._slots.acquire(blocking=False):
            self.refused += 1                 # no thread for it: a short answer and close
            try:
                request.send(_BUSY, socket.MSG_DONTWAIT)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def handle_error(self, request, client_address):
        # a client that resets or misbehaves: one debug line, not a traceback on stderr
        log.debug("console: connection from %s ended by an error", client_address[0],
                  exc_info=True)


class _DeadlineReader(io.RawIOBase):
    """The connection's reads, each bounded by what is left of the request's deadline."""

    def __init__(self, sock: socket.socket, deadline: float, timeout: float):
        self._sock, self._deadline, self._timeout = sock, deadline, timeout

    def readable(self):
        return True

    def readinto(self, b):
        left = self._deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("request not complete in time")
        self._sock.settimeout(min(left, self._timeout))
        try:
            return self._sock.recv_into(b)
        finally:
            self._sock.settimeout(self._timeout)


class _Server6(_Server):
    address_family = socket.AF_INET6


class Console:
    """``Console(listen, tap, status_fn, cfg, incident_dir).start()`` -> True when serving,
    False (and one clear log line) when it cannot listen: the box runs on without it."""

    def __init__(self, host: str, port: int, tap: FrameTap, status_fn, cfg,
                 incident_dir: str = "", incidents_fn=None):
        self.host, self.port = host, port
        self.tap = tap
        self.status_fn = status_fn
        self.cfg = cfg
        self.incident_dir = Path(incident_dir) if incident_dir else None
        self.incidents_fn = incidents_fn        # () -> the recorder's incident list (reasons)
        self.error: str | None = None
        self._httpd: _Server | None = None
        self._thread: threading.Thread | None = None
        self._inflight = threading.BoundedSemaphore(MAX_INFLIGHT)
        self._status_cache = (0.0, b"")
        self._snap_cache = (-1, b"")
        self._lock = threading.Lock()
        self.requests = 0

    @property
    def url(self) -> str | None:
        if self._httpd is None:
            return None
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{host}:{self.port}/"

    def start(self) -> bool:
        cls = _Server6 if ":" in self.host else _Server
        console = self

        class Handler(_Handler):
            pass
        Handler.console = console
        try:
            self._httpd = cls((self.host, self.port), Handler)
        except OSError as exc:
            self.error = f"cannot listen on {self.host}:{self.port}: {exc.strerror or exc}"
            log.error("console: %s; the box runs on without its web console (set [console] "
                      "listen to a free address, or \"\" for off)", self.error)
            self._httpd = None
            return False
        self.port = self._httpd.server_address[1]
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={
            "poll_interval": 0.25}, name="console-http", daemon=True)
        self._thread.start()
        log.info("console: %s (read-only)", self.url)
        return True

    def stop(self) -> None:
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._httpd = None
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def info(self) -> dict:
        return {"url": self.url, "error": self.error, "requests": self.requests,
                **self.tap.info()}

    # -- answers ---------------------------------------------------------------------------
    def status_json(self) -> bytes:
        with self._lock:
            t, body = self._status_cache
            if time.monotonic() - t < 0.2 and body:
                return body
            body = json.dumps(self.status_fn(), default=str).encode()
            self._status_cache = (time.monotonic(), body)
            return body

    def snapshot_png(self) -> bytes | None:
        v = self.tap.latest
        if v is None:
            return None
        with self._lock:
            if self._snap_cache[0] == v.index:
                return self._snap_cache[1]
        from appliance.snapshot import compose, encode_png
        png = encode_png(compose(v.res, v.evidence, self.cfg, json.loads(self.status_json())))
        with self._lock:
            self._snap_cache = (v.index, png)
        return png

    def incidents(self) -> list[dict]:
        if self.incident_dir is None or not self.incident_dir.is_dir():
            return []
        reasons = {i.get("name"): i for i in (self.incidents_fn() if self.incidents_fn else [])}
        out = []
        for p in sorted(self.incident_dir.iterdir(), reverse=True):
            if p.is_dir() and (p / "run.toml").exists() and _NAME.match(p.name):
                size = sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
                info = reasons.get(p.name, {})
                out.append({"name": p.name, "reason": info.get("reason"),
                            "stamp_s": info.get("stamp_s"), "bytes": size,
                            "download": f"/api/incidents/{p.name}.tar"})
        return out

    def incident_path(self, name: str) -> Path | None:
        if self.incident_dir is None or not _NAME.match(name):
            return None
        p = self.incident_dir / name
        if p.parent != self.incident_dir or not (p / "run.toml").exists():
            return None
        return p

    def stops(self) -> list[dict]:
        return [{"n": n, "index": v.index, "stamp_s": round(v.stamp_ns / 1e9, 3),
                 "wall": time.strftime("%H:%M:%S", time.localtime(v.wall_s)),
                 "reason": v.reason, "image": f"/api/stops/{n}.jpg"}
                for n, v in enumerate(self.tap.stops)]


class _Handler(BaseHTTPRequestHandler):
    console: Console
    server_version = "fieldguard-console"
    sys_version = ""
    timeout = 10

    def setup(self):
        super().setup()
        self.rfile.close()                        # the plain reader: replaced by one with a deadline
        self.rfile = io.BufferedReader(_DeadlineReader(
            self.connection, time.monotonic() + REQUEST_S, self.timeout))

    def parse_request(self):
        if not super().parse_request():
            return False
        if self.request_version == "HTTP/0.9":     # no status line to say what a body is
            self.send_error(HTTPStatus.BAD_REQUEST, "HTTP/0.9 is not served")
            return False
        return True

    def log_message(self, fmt, *args):          # keep the journal quiet: debug only
        log.debug("console %s: " + fmt, self.address_string(), *args)

    # every method but GET and HEAD is refused: the console cannot change anything
    def _refuse(self):
        self.send_response(HTTPStatus.METHOD_NOT_ALLOWED)
        self.send_header("Allow", "GET, HEAD")
        self.send_header("Content-Type", "application/json")
        body = b'{"error": "the console is read-only: only GET and HEAD"}\n'
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_TRACE = do_CONNECT = _refuse

    def do_HEAD(self):
        self._get(head=True)

    def do_GET(self):
        self._get(head=False)

    def _send(self, body: bytes, ctype: str, code=HTTPStatus.OK, head=False, extra=()):
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy",
                         "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'")
        for k, v in extra:
            self.send_header(k, v)
        self.end_headers()
        if not head:
            self.wfile.write(body)

    def _error(self, code, msg, head=False):
        self._send(json.dumps({"error": msg}).encode() + b"\n", "application/json", code, head)

    def _get(self, head: bool):
        c = self.console
        if not c._inflight.acquire(blocking=False):
            self._error(HTTPStatus.SERVICE_UNAVAILABLE, "busy: too many requests at once", head)
            return
        try:
            c.requests += 1
            self._route(self.path.split("?", 1)[0], head)
        except (BrokenPipeError, ConnectionResetError, socket.timeout):
            pass
        except Exception as exc:             # a bad request never hurts the daemon
            log.warning("console: %s failed: %s: %s", self.path, type(exc).__name__, exc)
            try:
                self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(exc).__name__}", head)
            except OSError:
                pass
        finally:
            c._inflight.release()

    def _route(self, path: str, head: bool):
        c = self.console
        if path in _STATIC_FILES:
            name, ctype = _STATIC_FILES[path]
            return self._send((STATIC / name).read_bytes(), ctype, head=head)
        if path == "/api/status":
            return self._send(c.status_json(), "application/json", head=head)
        if path in ("/api/view.jpg", "/api/grid.jpg"):
            v = c.tap.latest
            body = None if v is None else (v.camera_jpeg if path == "/api/view.jpg"
                                           else v.grid_jpeg)
            if body is None:
                what = "no picture yet" if v is None else "no camera in this configuration"
                return self._error(HTTPStatus.NOT_FOUND, what, head)
            return self._send(body, "image/jpeg", head=head,
                              extra=(("X-Fieldguard-Cycle", str(v.index)),))
        if path == "/api/snapshot.png":
            png = c.snapshot_png()
            if png is None:
                return self._error(HTTPStatus.SERVICE_UNAVAILABLE, "no cycle has run yet", head)
            return self._send(png, "image/png", head=head)
        if path == "/api/stops":
            return self._send(json.dumps(c.stops()).encode(), "application/json", head=head)
        m = re.fullmatch(r"/api/stops/(\d+)\.jpg", path)
        if m:
            stops = list(c.tap.stops)
            n = int(m.group(1))
            if n >= len(stops):
                return self._error(HTTPStatus.NOT_FOUND, "no such stop", head)
            v = stops[n]
            return self._send(v.camera_jpeg or v.grid_jpeg, "image/jpeg", head=head)
        m = re.fullmatch(r"/api/stops/(\d+)/grid\.jpg", path)
        if m:
            stops = list(c.tap.stops)
            n = int(m.group(1))
            if n >= len(stops):
                return self._error(HTTPStatus.NOT_FOUND, "no such stop", head)
            return self._send(stops[n].grid_jpeg, "image/jpeg", head=head)
        if path == "/api/incidents":
            return self._send(json.dumps({"dir": str(c.incident_dir or ""),
                                          "incidents": c.incidents()}).encode(),
                              "application/json", head=head)
        m = re.fullmatch(r"/api/incidents/([^/]+)\.tar", path)
        if m:
            p = c.incident_path(m.group(1))
            if p is None:
                return self._error(HTTPStatus.NOT_FOUND, "no such incident", head)
            return self._send_tar(p, head)
        return self._error(HTTPStatus.NOT_FOUND, f"no such page: {path}", head)

    def _send_tar(self, p: Path, head: bool):
        """The incident's run folder as an (uncompressed: PNGs do not shrink) tar, streamed;
        HTTP/1.0, so the end of the connection ends the file."""
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "application/x-tar")
        self.send_header("Content-Disposition", f'attachment; filename="{p.name}.tar"')
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if head:
            return
        with tarfile.open(fileobj=self.wfile, mode="w|") as tar:
            tar.add(str(p), arcname=p.name)
