"""The daemon as systemd runs it: its own NOTIFY_SOCKET and WATCHDOG_USEC, READY, regular
WATCHDOG pings, STATUS changes, STOPPING on SIGTERM; a hung loop stops the pings."""
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from appliance.config import default_config
from appliance.daemon import Daemon, sim_config
from appliance.perception import register_pipeline
from appliance.service import Notifier, setup_logging
from tests.fakes import HangPipeline

ROOT = Path(__file__).resolve().parents[1]


class Listener:
    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.msgs: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self.th = threading.Thread(target=self._run, daemon=True)
        self.th.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            for line in data.decode().split("\n"):
                self.msgs.append((time.monotonic(), line))

    def lines(self, prefix):
        return [(t, m) for t, m in self.msgs if m.startswith(prefix)]

    def close(self):
        self._stop.set()
        self.th.join(1)
        self.sock.close()


def test_daemon_under_systemd_protocol(tmp_path):
    lst = Listener(tmp_path / "notify.sock")
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"),
           "WATCHDOG_USEC": "800000", "JOURNAL_STREAM": "8:1234", "PYTHONPATH": str(ROOT)}
    env.pop("WATCHDOG_PID", None)
    p = subprocess.Popen([sys.executable, "-m", "appliance.cli", "run", "--sim",
                          "--socket", str(tmp_path / "status.sock")], env=env, cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not lst.lines("READY=1"):
            time.sleep(0.1)
        assert lst.lines("READY=1"), "no READY=1 within 30 s"
        time.sleep(2.5)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=15)
    finally:
        if p.poll() is None:
            p.kill()
        lst.close()
    assert p.returncode == 0, err
    ready_t = lst.lines("READY=1")[0][0]
    pings = [t for t, _ in lst.lines("WATCHDOG=1")]
    assert len(pings) >= 8                      # 0.8 s watchdog: a ping at least every 0.2 s
    assert all(t >= ready_t for t in pings)
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert max(gaps) < 0.8                      # never long enough for systemd to kill us
    statuses = [m for _, m in lst.lines("STATUS=")]
    assert statuses[0].startswith("STATUS=STOP")          # boots in STOP
    assert any(s.startswith("STATUS=CLEAR") or s.startswith("STATUS=SLOW") for s in statuses)
    assert lst.lines("STOPPING=1")
    # journald priority prefixes on stderr (where no journald listens: with one, the records
    # go to it through systemd.journal instead, test_journal_handler_sends_native_entries)
    from appliance.service import JOURNAL_SOCKET, _is_socket, _systemd_journal
    if not (_systemd_journal() and _is_socket(JOURNAL_SOCKET)):
        assert any(line.startswith("<6>fieldguard") for line in err.splitlines()), err[:500]


def test_hung_loop_stops_the_watchdog_pings(tmp_path):
    register_pipeline("hang-test", "tests.fakes:HangPipeline")
    lst = Listener(tmp_path / "n.sock")
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "n.sock"), "WATCHDOG_USEC": "400000"})
    cfg = default_config()
    cfg = cfg.__class__(**{**cfg.__dict__, "perception": cfg.perception.__class__(
        pipelines=("laser", "hang-test"))})
    cfg = sim_config(cfg)
    d = Daemon(cfg, mode="sim", pace=1.0, serve_status=False, notifier=notifier)
    d.start()
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    try:
        # the loop pings once it is up and healthy (start-up takes longer on a busy machine)
        deadline = time.monotonic() + 30
        while len(lst.lines("WATCHDOG=1")) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        before = len(lst.lines("WATCHDOG=1"))
        assert before >= 3
        HangPipeline.hang.set()
        time.sleep(0.3)
        n_hung = len(lst.lines("WATCHDOG=1"))
        time.sleep(1.2)                       # three watchdog periods with the loop hung
        assert len(lst.lines("WATCHDOG=1")) == n_hung
        HangPipeline.hang.clear()
        HangPipeline.release.set()
        time.sleep(1.0)
    finally:
        d.request_stop()
        HangPipeline.release.set()
        th.join(5)
        d.shutdown()
        lst.close()


def test_notifier_is_silent_without_systemd_and_honours_watchdog_pid():
    n = Notifier({})
    assert not n.enabled and not n.notify("READY=1")
    n2 = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"})
    assert n2.watchdog_s is None                # the watchdog is for another process
    n3 = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000000",
                   "WATCHDOG_PID": str(os.getpid())})
    assert n3.watchdog_s == 1.0


def test_abstract_socket_address(tmp_path):
    name = f"fg-test-{os.getpid()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(1)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.notify("READY=1")
        assert s.recv(100) == b"READY=1"
    finally:
        s.close()


def test_journal_logging_prefix(capsys):
    import logging
    setup_logging(False, {"JOURNAL_STREAM": "1:2"})
    logging.getLogger("fieldguard.x").error("boom")
    assert "<3>fieldguard.x: boom" in capsys.readouterr().err
    setup_logging(False, {})


# ---- systemd-python (the library path) and the fallback, both ----------------------------
def test_notify_through_systemd_python_when_it_is_installed(tmp_path, monkeypatch):
    from appliance import service
    if service._systemd_daemon() is None:
        from tests.conftest import missing_tool
        missing_tool("systemd-python is not installed (pip install '.[systemd]'; needs "
                     "libsystemd-dev, tools/hw_system_deps.sh)")
    lst = Listener(tmp_path / "lib.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "lib.sock"))
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    try:
        n = Notifier()
        assert n.backend == "systemd"
        n.ready("STOP: booting")
        n.status("CLEAR: zone clear")
        n.healthy_cycle()
        n.stopping()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not lst.lines("STOPPING=1"):
            time.sleep(0.02)
        assert lst.lines("READY=1") and lst.lines("MAINPID=")
        assert [m for _, m in lst.lines("STATUS=")] == ["STATUS=STOP: booting",
                                                         "STATUS=CLEAR: zone clear",
                                                         "STATUS=stopping"]
        assert lst.lines("WATCHDOG=1") and lst.lines("STOPPING=1")
        assert n.errors == 0 and n.sent[0] == "READY=1"
    finally:
        lst.close()
    # a socket nobody listens on: counted, never raised
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody.sock"))
    n2 = Notifier()
    assert not n2.notify("READY=1") and n2.errors == 1


def test_notify_fallback_without_systemd_python(tmp_path, monkeypatch):
    from appliance import service
    monkeypatch.setattr(service, "_systemd_daemon", lambda: None)      # as if not installed
    lst = Listener(tmp_path / "fb.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "fb.sock"))
    try:
        n = Notifier()
        assert n.backend == "socket"
        n.ready("STOP: booting")
        n.stopping()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not lst.lines("STOPPING=1"):
            time.sleep(0.02)
        assert lst.lines("READY=1") and lst.lines("STOPPING=1")
    finally:
        lst.close()
    assert Notifier({}).backend is None                                 # not under systemd


def test_journal_handler_sends_native_entries(tmp_path):
    """systemd.journal's handler, to a journald peer: the native protocol's datagrams on the
    journal socket, with the priority and the logger as fields."""
    import logging

    from appliance import service
    journal = service._systemd_journal()
    if journal is None:
        from tests.conftest import missing_tool
        missing_tool("systemd-python is not installed (pip install '.[systemd]')")
    path = Path(service.JOURNAL_SOCKET)
    if service._is_socket(str(path)):
        pytest.skip("a journald is running here; its entries are read with journalctl")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        peer = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        peer.bind(str(path))
    except OSError as exc:
        pytest.skip(f"cannot stand in for journald at {path}: {exc}")
    peer.settimeout(5)
    try:
        setup_logging(False, {"JOURNAL_STREAM": "8:1"})
        assert service.logging_backend() == "journal"
        logging.getLogger("fieldguard.test").error("lamp overtemperature")
        fields = {}
        for line in peer.recv(65536).decode(errors="replace").split("\n"):
            k, _, v = line.partition("=")
            fields[k] = v
    finally:
        setup_logging(False, {})
        peer.close()
        path.unlink(missing_ok=True)
    assert fields["MESSAGE"] == "fieldguard.test: lamp overtemperature"
    assert fields["PRIORITY"] == "3" and fields["SYSLOG_IDENTIFIER"] == "fieldguard"
    assert fields["LOGGER"] == "fieldguard.test" and fields["CODE_FILE"].endswith(".py")
    assert service.logging_backend() == "stderr"


def test_journal_fallback_without_systemd_python(capsys):
    import logging

    from appliance import service
    setup_logging(False, {"JOURNAL_STREAM": "1:2"}, use_library=False)
    assert service.logging_backend() == "stderr-journal"
    logging.getLogger("fieldguard.x").warning("late")
    assert "<4>fieldguard.x: late" in capsys.readouterr().err
    setup_logging(False, {})
