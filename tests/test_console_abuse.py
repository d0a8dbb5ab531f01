"""The web console and the Foxglove server as network surfaces: whatever a client sends over a
raw socket (garbage, huge or endless requests, slow or idle or non-reading clients, other
protocols, other methods, paths out of the incident folder) is answered with an HTTP error or a
closed connection, never a traceback or a 500, and the daemon goes on cycling within its budget.

A real daemon on the simulated field (laser pipeline, real time) runs in a thread with the
console on an ephemeral loopback port; each test ends by checking that its status socket
answers with fresh cycles, the console still serves the page, and the loop's cycles during the
test kept to their budget."""
import dataclasses
import json
import random
import socket
import statistics
import threading
import time

import pytest

from appliance.config import ConsoleConfig, FoxgloveConfig, StatusConfig, default_config
from appliance.console import server as console_server
from appliance.daemon import Daemon, sim_config
from appliance.status import read_status

INCIDENT = "20261201-120000-obstacle-4-m"
SECRET = "fieldguard-secret-marker-7f3a"


def _start(tmp_path, console="127.0.0.1:0", foxglove=""):
    from drivers.sim.record import write_sim_run
    inc = tmp_path / "incidents"
    write_sim_run("stubble-day", 2, inc / INCIDENT, sensors=("laser",))
    # a folder beside the incidents that looks like one: nothing may serve it
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "run.toml").write_text(f"# {SECRET}\n")
    cfg = default_config()
    cfg = dataclasses.replace(
        cfg, console=ConsoleConfig(listen=console, rate_hz=10),
        foxglove=FoxgloveConfig(listen=foxglove),
        status=StatusConfig(incident_dir=str(inc)),
        perception=dataclasses.replace(cfg.perception, pipelines=("laser",)))
    sock = str(tmp_path / "run" / "status.sock")
    d = Daemon(sim_config(cfg), mode="sim", pace=1.0, status_socket=sock)
    d.start()
    d.cycle_wall_ms = []
    d.loop.on_cycle.append(lambda res: d.cycle_wall_ms.append(sum(res.wall_ms.values())))
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 60
    while d.loop.cycles < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert d.loop.cycles >= 3
    return d, th, sock


def _stop(d, th):
    d.request_stop()
    th.join(10)
    d.shutdown()


# The whole request must arrive within REQUEST_S (5 s in the product). Here 2 s: the three
# tests that wait for a cut-off (slowloris, idle clients, a request that never ends) wait for
# this same deadline in the same code, 9 s less of the suite; every client here sends its
# request at once, so 2 s cuts off no honest one.
TEST_REQUEST_S = 2.0


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setattr(console_server, "REQUEST_S", TEST_REQUEST_S)
    tmp = tmp_path_factory.mktemp("abuse")
    d, th, sock = _start(tmp)
    c = d.console.console
    yield d, sock, c.host, c.port, tmp
    _stop(d, th)
    mp.undo()


@pytest.fixture()
def checked(box, capfd):
    """After each test: the daemon cycles (fresh cycles on its status socket), the console
    serves its page and nothing printed a traceback. (The loop's timing is checked over all
    the tests at once, last: a few cycles of one short test say nothing on a loaded machine.)"""
    d, sock, host, port, tmp = box
    yield box
    _still_cycling(sock)
    code, _, body = _http(host, port, b"GET / HTTP/1.0\r\n\r\n")
    assert code == 200 and b'id="state"' in body
    _, err = capfd.readouterr()
    assert "Traceback" not in err and "Exception occurred" not in err, err[-2000:]


def _still_cycling(sock, more=2, within_s=15.0):
    """Fresh cycles on the status socket (a loaded test machine may run the loop slowly)."""
    c0 = read_status(sock, timeout_s=5)["cycles"]
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if read_status(sock, timeout_s=5)["cycles"] >= c0 + more:
            return
        time.sleep(0.1)
    raise AssertionError(f"the daemon stopped cycling (still {c0} after {within_s} s)")


def _conn(host, port, timeout=10.0):
    s = socket.create_connection((host, port), timeout=timeout)
    return s


def _http(host, port, data: bytes, timeout=10.0):
    """Send ``data`` raw, read until the server closes: (status or None, head, body). A server
    that closes (or resets) while we still send is a closed connection: (None, b"", b"")."""
    s = _conn(host, port, timeout)
    out = b""
    try:
        try:
            s.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass
        while True:
            b = s.recv(65536)
            if not b:
                break
            out += b
    except ConnectionResetError:
        pass
    finally:
        s.close()
    if not out.startswith(b"HTTP/"):
        return None, b"", out
    head, _, body = out.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), head, body


def _assert_refused(code, head, body, what):
    """An HTTP error that is the client's fault (or 501/505: a method or version this
    server does not implement, as RFC 9110 asks), or a closed connection; no internals."""
    if code is None:
        # closed without an HTTP answer: nothing at all, or (HTTP/0.9) a bare error body
        assert body == b"" or b"error" in body.lower(), (what, body[:200])
    else:
        assert 400 <= code < 500 or code in (501, 503, 505), (what, code, body[:200])
    text = head + body
    for leak in (b"Traceback", b'File "', b"/work/", b"site-packages", SECRET.encode(),
                 b"root:"):
        assert leak not in text, (what, leak, text[:300])


# -- malformed requests ---------------------------------------------------------------------------
rng = random.Random(1)
MALFORMED = {
    "binary garbage": bytes(rng.randrange(256) for _ in range(4096)),
    "garbage then CRLF": bytes(rng.randrange(256) for _ in range(300)) + b"\r\n\r\n",
    "request line of 100 kB": b"GET /" + b"A" * 100_000 + b" HTTP/1.1\r\n\r\n",
    "10 000 headers": b"GET / HTTP/1.1\r\n" + b"".join(b"X-H%d: v\r\n" % i
                                                      for i in range(10_000)) + b"\r\n",
    "a header of 1 MB": b"GET / HTTP/1.1\r\nX-Big: " + b"B" * (1 << 20) + b"\r\n\r\n",
    "HTTP/0.9": b"GET /\r\n",
    "HTTP/0.9 POST": b"POST /\r\n",
    "HTTP/2 preface": b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00",
    "HTTP/3.0": b"GET / HTTP/3.0\r\n\r\n",
    "bad version": b"GET / HTTP/x.y\r\n\r\n",
    "lower-case method": b"get / HTTP/1.1\r\n\r\n",
    "unknown method": b"FROB / HTTP/1.1\r\n\r\n",
    "NUL in the method": b"G\x00T / HTTP/1.1\r\n\r\n",
    "four words": b"GET / / HTTP/1.1\r\n\r\n",
    "only CRLF": b"\r\n",
    "header without colon": b"GET / HTTP/1.1\r\nno colon here\r\n\r\n",
    "header folded": b"GET / HTTP/1.1\r\nX: a\r\n folded\r\n\r\n",
    "non-UTF-8 header": b"GET / HTTP/1.1\r\nX: \xff\xfe\xc3\x28\r\n\r\n",
    "TLS hello": bytes.fromhex("16030100a5010000a10303") + bytes(rng.randrange(256)
                                                               for _ in range(160)),
}
for m in ("POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "CONNECT"):
    MALFORMED[f"method {m}"] = (f"{m} /api/status HTTP/1.1\r\nContent-Length: 5\r\n\r\n"
                                "state").encode()
MALFORMED["CONNECT authority"] = b"CONNECT 127.0.0.1:22 HTTP/1.1\r\n\r\n"


def test_malformed_requests_get_an_error_or_a_close(checked):
    d, sock, host, port, tmp = checked
    for what in sorted(MALFORMED):
        code, head, body = _http(host, port, MALFORMED[what])
        if code == 200:
            # the stdlib's header parser tolerates a bad header line after a valid request
            # line (nothing here reads a header): the answer is then the page, nothing else
            assert MALFORMED[what].startswith(b"GET / HTTP/1.1\r\n"), what
            assert b'id="state"' in body, what
            continue
        _assert_refused(code, head, body, what)
        if what.startswith("method "):
            assert code == 405 and b"read-only" in body, (what, code)


TRAVERSAL = [
    "/incidents/../../etc/passwd", "/api/incidents/../../etc/passwd",
    "/api/incidents/../../../../etc/passwd.tar", "/api/incidents/..%2f..%2fetc%2fpasswd.tar",
    "/api/incidents/%2e%2e%2f%2e%2e%2fetc%2fpasswd.tar", "/api/incidents/..%252fsecret.tar",
    "/api/incidents/%252e%252e%252fsecret.tar", "/api/incidents/..%5csecret.tar",
    "/api/incidents/..\\secret.tar", "/api/incidents/../secret.tar", "/api/incidents/...tar",
    "/api/incidents/%2e%2e.tar", "/api/incidents/..tar", "/api/incidents/secret.tar",
    "/api/incidents//etc/passwd.tar", "/api/incidents/%2fetc%2fpasswd.tar",
    "/api/incidents/etc/passwd.tar", "//etc/passwd", "/etc/passwd",
    "http://127.0.0.1/etc/passwd", "file:///etc/passwd",
    f"/api/incidents/{INCIDENT}%00.tar", f"/api/incidents/{INCIDENT}\x00.tar",
    f"/api/incidents/{INCIDENT}\x00/../../secret.tar", f"/api/incidents/{INCIDENT}/../secret.tar",
    f"/api/incidents/{INCIDENT}/run.toml", f"/api/incidents/{INCIDENT}.tar/../../secret.tar",
    "/api/incidents/%c0%ae%c0%ae%c0%afsecret.tar", "/api/incidents/\xc0\xae\xc0\xae.tar",
    "/static/../server.py", "/../appliance/console/server.py", "/app.js/../../server.py",
    "/api/stops/0/../../../etc/passwd", "/api/stops/-1.jpg", "/api/stops/99999999999999999.jpg",
]


def test_nothing_outside_the_incident_folder_is_served(checked):
    d, sock, host, port, tmp = checked
    for path in TRAVERSAL:
        for version in (b" HTTP/1.0", b" HTTP/1.1"):
            code, head, body = _http(host, port, b"GET " + path.encode("latin-1") + version
                                     + b"\r\nHost: x\r\n\r\n")
            _assert_refused(code, head, body, path)
            assert code in (400, 404), (path, code)
    # the absolute path of the folder beside the incidents, too
    code, head, body = _http(host, port, f"GET /api/incidents/{tmp}/secret.tar HTTP/1.0\r\n\r\n"
                             .encode())
    _assert_refused(code, head, body, "absolute")


def test_the_real_incident_is_still_served(checked):
    d, sock, host, port, tmp = checked
    code, head, body = _http(host, port, f"GET /api/incidents/{INCIDENT}.tar HTTP/1.0\r\n\r\n"
                             .encode())
    assert code == 200 and f"{INCIDENT}/run.toml".encode() in body


QUERIES = ["/?" + "A" * 8000, "/api/status?\x00\x01\x02", "/api/status?%zz%00%ff=&&&==",
           "/api/status?a=" + "%" * 500, "/?\xff\xfe", "/api/status#frag", "/api/status?;;;",
           "/\xff\xfe\xc3\x28", "/api/\xc3\x28status", "/%ff%fe", "/api/status%00",
           "/api/status\x00", "/" + "%00" * 1000, "*", "", "?", "/api/stops/\u00e9.jpg"]


def test_garbage_in_paths_and_query_strings(checked):
    d, sock, host, port, tmp = checked
    for path in QUERIES:
        code, head, body = _http(host, port, b"GET " + path.encode("latin-1", "replace")
                                 + b" HTTP/1.0\r\n\r\n")
        if code == 200:         # a real page with a garbage query is that page
            assert path.split("?")[0] in ("/", "/api/status"), path
            continue
        _assert_refused(code, head, body, path)


def test_http_0_9_is_refused_not_served(checked):
    """Regression: an HTTP/0.9 request (no version) got the page as a bare body, with no
    status line to say what it is; it is refused now."""
    d, sock, host, port, tmp = checked
    code, head, body = _http(host, port, b"GET /\r\n\r\n")
    assert code is None and b'id="state"' not in body and b"HTTP/0.9" in body


# -- slow, idle and non-reading clients -------------------------------------------------------
def _handler_threads():
    return [t for t in threading.enumerate() if "process_request_thread" in t.name]


def test_a_slowloris_client_is_cut_off(checked):
    """Regression: a client sending one byte a second kept its connection (and a thread) for
    ever: the 10 s timeout was per read. The whole request must now arrive in REQUEST_S."""
    d, sock, host, port, tmp = checked
    s = _conn(host, port, timeout=2.0)
    t0 = time.monotonic()
    closed_after = None
    try:
        s.sendall(b"GET / HTTP/1.1\r\n")
        for i in range(int(console_server.REQUEST_S) + 8):
            try:
                s.sendall(b"X-%d: y\r\n" % i)
            except (BrokenPipeError, ConnectionResetError):
                closed_after = time.monotonic() - t0
                break
            s.settimeout(1.0)
            try:
                if s.recv(4096) == b"":
                    closed_after = time.monotonic() - t0
                    break
            except socket.timeout:
                pass
            except ConnectionResetError:
                closed_after = time.monotonic() - t0
                break
    finally:
        s.close()
    assert closed_after is not None, "a one-byte-a-second client kept its connection"
    assert closed_after < console_server.REQUEST_S + 3.0


def test_many_idle_connections_hold_a_bounded_number_of_threads(checked):
    """50 clients connect and send nothing: at most MAX_CONNECTIONS of them get a thread
    (the rest are closed at once), each is cut off after REQUEST_S, and then the page is
    served again while the 50 sockets are still open."""
    d, sock, host, port, tmp = checked
    base = len(_handler_threads())
    idle = []
    try:
        for _ in range(50):
            idle.append(_conn(host, port))
        time.sleep(0.5)
        held = len(_handler_threads()) - base
        assert held <= console_server.MAX_CONNECTIONS, held
        t0 = time.monotonic()
        while True:
            code, _, body = _http(host, port, b"GET / HTTP/1.0\r\n\r\n")
            if code == 200:
                break
            assert code in (None, 503), code
            assert time.monotonic() - t0 < console_server.REQUEST_S + 5.0, \
                "idle clients kept the console from serving"
            time.sleep(0.25)
    finally:
        for c in idle:
            c.close()
    deadline = time.monotonic() + console_server.REQUEST_S + 3.0
    while len(_handler_threads()) > base and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(_handler_threads()) <= base


def test_clients_that_never_read_the_snapshot_hold_up_no_one(checked):
    d, sock, host, port, tmp = checked
    base = len(_handler_threads())
    hogs = []
    try:
        for _ in range(4):
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
            s.settimeout(5)
            s.connect((host, port))
            s.sendall(b"GET /api/snapshot.png HTTP/1.0\r\n\r\n")
            hogs.append(s)
        time.sleep(0.5)
        t = time.monotonic()
        code, _, body = _http(host, port, b"GET /api/status HTTP/1.0\r\n\r\n")
        assert code == 200 and "cycles" in json.loads(body)
        assert time.monotonic() - t < 3.0
    finally:
        for s in hogs:
            s.close()
    # their threads end (the write times out, or fails on the closed socket)
    deadline = time.monotonic() + console_server._Handler.timeout + 3.0
    while len(_handler_threads()) > base and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(_handler_threads()) <= base


def test_clients_that_reset_mid_request_leave_no_traceback(checked):
    """Regression: a client resetting its connection (RST) while its request was read made
    socketserver print a traceback on the daemon's stderr (the journal); one debug line now.
    (The ``checked`` fixture fails the test on any traceback.)"""
    d, sock, host, port, tmp = checked
    import struct
    for part in (b"GET / HT", b"GET / HTTP/1.1\r\nHost: x\r\n", b"\x16\x03\x01"):
        s = _conn(host, port)
        s.sendall(part)
        time.sleep(0.3)                     # the handler is now blocked reading the rest
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()                           # RST, not FIN
    time.sleep(0.5)


def _assert_kept_budget(d, doc):
    """The loop's cycle (sum of its stages' wall times) kept, at the median, to the sum of the
    stage budgets: the median, because on a shared test machine any single cycle can be
    preempted for hundreds of ms by other processes, which says nothing about the console."""
    deadline = time.monotonic() + 30
    while len(d.cycle_wall_ms) < 23 and time.monotonic() < deadline:
        time.sleep(0.1)
    walls = d.cycle_wall_ms[3:]
    budget = sum(doc["budget_ms"].values())
    assert len(walls) >= 20, len(walls)
    assert statistics.median(walls) <= budget, (statistics.median(walls), budget, len(walls))


def test_zz_the_loop_kept_its_budget_through_all_of_it(checked):
    """Runs last in this module (pytest keeps file order): every cycle since the daemon
    started, i.e. under all the abuse above."""
    d, sock, host, port, tmp = checked
    _assert_kept_budget(d, read_status(sock))


# -- the Foxglove WebSocket server ----------------------------------------------------------------
def test_foxglove_server_survives_garbage_and_half_open_handshakes(tmp_path):
    pytest.importorskip("foxglove", reason="the foxglove SDK is not installed in this venv")
    websocket = pytest.importorskip("websocket", reason="websocket-client is not installed")
    with socket.socket() as probe:                      # a free port for the SDK to bind
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    d, th, sock = _start(tmp_path, console="", foxglove=f"127.0.0.1:{port}")
    try:
        fx = d.console.foxglove
        assert fx is not None, d.console.errors
        host, port = fx.host, fx.port
        c0 = read_status(sock)["cycles"]
        payloads = [bytes(random.Random(2).randrange(256) for _ in range(4096)),
                    b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n",
                    b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    b"Sec-WebSocket-Key: AAAAAAAAAAAAAAAAAAAAAA==\r\nSec-WebSocket-Version: 13"
                    b"\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
                    + bytes(random.Random(3).randrange(256) for _ in range(2048)),
                    b"GET / HTTP/1.1\r\nX: " + b"A" * (1 << 20) + b"\r\n\r\n",
                    b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"]
        half_open = []
        for p in payloads:
            s = _conn(host, port, timeout=3)
            try:
                s.sendall(p)
            except OSError:
                pass
            half_open.append(s)                     # left open, never read
        for _ in range(30):                         # idle connections, never a byte
            half_open.append(_conn(host, port, timeout=3))
        time.sleep(1.0)
        # a real client still gets the server's info while all those are open
        ws = websocket.create_connection(f"ws://{host}:{port}", subprotocols=["foxglove.sdk.v1"],
                                         timeout=10)
        try:
            assert json.loads(ws.recv())["op"] == "serverInfo"
        finally:
            ws.close()
        for s in half_open:
            s.close()
        _still_cycling(sock)
        doc = read_status(sock)
        assert doc["cycles"] > c0
        _assert_kept_budget(d, doc)
    finally:
        _stop(d, th)

