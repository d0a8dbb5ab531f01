"""console: raw request bytes on the web console's HTTP port.

The input is everything a client writes on one connection. It goes through the console's own
request handler (``appliance.console.server._Handler``: the stdlib's request-line and header
parsing, the HTTP/0.9 refusal, the routes) with a real console behind it: the simulated box,
started, three cycles run and one view rendered (so the grid, the snapshot and the status
answer), one incident in its incident folder, and a folder beside it that looks like an
incident; then the daemon is shut down, so no thread runs behind the fuzzer. No socket: the
handler reads the input from memory and writes its answer to memory.

A defect: any exception out of the handler, a 500 (a route failed), a 200 for a path that is
not one of the console's pages, a tar of anything but the one incident, a traceback or a
file path in an answer. The real port (slow, idle, oversized, many clients, a running daemon)
is tests/test_console_abuse.py."""
from __future__ import annotations

import dataclasses
import io
import time

from appliance.config import StatusConfig, default_config
from appliance.console.server import Console, _Handler
from appliance.console.tap import FrameTap
from appliance.daemon import Daemon, sim_config

from tests.fuzz.common import scratch_dir

INCIDENT = "20261201-120000-obstacle-4-m"
PAGES = {"/", "/app.js", "/style.css", "/api/status", "/api/grid.jpg", "/api/snapshot.png",
         "/api/stops", "/api/incidents", f"/api/incidents/{INCIDENT}.tar"}
_console = None


class _MemHandler(_Handler):
    """The console's handler on a connection held in memory."""

    def setup(self):
        self.connection = None
        self.rfile = io.BytesIO(self.request)
        self.wfile = io.BytesIO()

    def finish(self):
        self.answer = self.wfile.getvalue()


def setup():
    global _console
    if _console is not None:
        return _console
    from drivers.sim.record import write_sim_run
    base = scratch_dir("console")
    inc = base / "incidents"
    if not (inc / INCIDENT / "run.toml").exists():
        write_sim_run("stubble-day", 2, inc / INCIDENT, sensors=("laser",))
    (base / "secret").mkdir(exist_ok=True)
    (base / "secret" / "run.toml").write_text("# not an incident\n")
    cfg = sim_config(default_config())
    cfg = dataclasses.replace(cfg, console=dataclasses.replace(cfg.console, listen=""),
                              status=StatusConfig(incident_dir=str(inc)))
    d = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    d.start()
    d.run(max_cycles=3)
    d.shutdown()
    tap = FrameTap(cfg, lambda: d.loop.grid.evidence)
    tap._publish(tap.render(d.loop.last, d.loop.grid.evidence.copy(), time.time()))
    _console = Console("127.0.0.1", 0, tap, d.status, cfg, str(inc), lambda: [])
    _MemHandler.console = _console
    return _console


def one_input(data: bytes) -> None:
    setup()
    h = _MemHandler(data, ("127.0.0.1", 1), None)
    out = h.answer
    for leak in (b"Traceback", b'File "', b"site-packages"):
        assert leak not in out, (leak, out[:200])
    if not out.startswith(b"HTTP/"):
        return                           # closed, or an HTTP/0.9 error body
    code = int(out.split(b" ", 2)[1])
    assert code != 500, out[:300]
    if code == 200:
        path = h.path.split("?", 1)[0]
        assert path in PAGES, path
        if path.endswith(".tar"):
            assert f"{INCIDENT}/run.toml".encode() in out or h.command == "HEAD"
