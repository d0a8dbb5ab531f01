"""status: request lines on the daemon's status socket.

The input is what a local client writes on the socket. It goes through the server's request
reading rules (first line, at most MAX_REQUEST + 1 bytes) into ``StatusServer.answer`` with a
real daemon behind it (the simulated box, started, three cycles run, so ``snapshot`` has a
picture; then shut down, so no device thread runs behind the fuzzer): ``status``,
``snapshot``, ``selftest``, ``record SECONDS PATH``, ``record-status`` and anything else.
``answer`` must return bytes for every input (a PNG for a snapshot, else one JSON document)
and never raise. ``record`` jobs are dropped after each input and the
loop does not run again, so no recording is written anywhere. The real socket (slow,
oversized, many clients, a running daemon) is tests/test_status_socket.py."""
from __future__ import annotations

import dataclasses
import json

from appliance.config import default_config
from appliance.daemon import Daemon, sim_config
from appliance.status import MAX_REQUEST, StatusServer

from tests.fuzz.common import scratch_dir

_server = None
_daemon = None


def setup():
    global _server, _daemon
    if _server is not None:
        return _server
    cfg = sim_config(default_config())
    if hasattr(cfg, "console"):           # no web console on a port for this
        cfg = dataclasses.replace(cfg, console=dataclasses.replace(cfg.console, listen=""))
    _daemon = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    _daemon.start()
    _daemon.run(max_cycles=3)
    # its devices and threads stop; what answers requests (the last cycle, the status, the
    # handler) stays, and nothing keeps a CPU busy behind the fuzzer
    _daemon.shutdown()
    _server = StatusServer(str(scratch_dir("status") / "status.sock"), _daemon.status,
                           _daemon.handle)
    return _server


def one_input(data: bytes) -> None:
    server = setup()
    raw = data[:MAX_REQUEST + 1].split(b"\n", 1)[0].rstrip(b"\r")
    out = server.answer(raw)
    assert isinstance(out, bytes) and out
    with _daemon.recorder._lock:
        _daemon.recorder._live.clear()
    if out.startswith(b"\x89PNG"):
        return
    doc = json.loads(out)
    assert isinstance(doc, dict)
