"""The web console: served by the daemon, read-only, cheap for the loop, never fatal.

These run a real daemon on the simulated field with the console on an ephemeral loopback port
and talk HTTP to it (urllib); the last test drives it with a real browser (Debian's chromium,
headless, through selenium) against `fieldguard run --sim`."""
import dataclasses
import io
import json
import socket
import tarfile
import time
import urllib.error
import urllib.request

import pytest

from appliance.config import ConsoleConfig, StatusConfig, default_config, parse_config
from appliance.console.tap import FrameTap
from appliance.daemon import Daemon, sim_config
from hal.errors import ConfigError
from hal.types import GateState


def get(url, method="GET", data=None, timeout=10):
    req = urllib.request.Request(url, method=method, data=data)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers, exc.read()


def console_daemon(tmp_path, listen="127.0.0.1:0", scene=None, **status):
    cfg = dataclasses.replace(default_config(), console=ConsoleConfig(listen=listen, rate_hz=10),
                              status=StatusConfig(**status))
    d = Daemon(sim_config(cfg, scene), mode="sim", pace=0.0,
               status_socket=str(tmp_path / "status.sock"))
    d.start()
    return d


def wait_for_view(d, timeout=30.0):
    """Run two cycles (the first is always handed over), then give the encoder thread time."""
    d.run(max_cycles=2)
    t0 = time.monotonic()
    while d.console.tap.latest is None:
        assert time.monotonic() - t0 < timeout, "the console never got a picture"
        time.sleep(0.05)
    return d.console.tap.latest


# -- config ---------------------------------------------------------------------------------------
def test_console_is_on_by_default_on_loopback_8080_and_off_with_empty_listen():
    assert default_config().console.listen == "127.0.0.1:8080"
    assert parse_config({"console": {"listen": ""}}).console.listen == ""
    assert parse_config({"console": {"listen": "0.0.0.0:9000"}}).console.listen == "0.0.0.0:9000"
    assert default_config().foxglove.listen == ""        # Foxglove: off unless configured


@pytest.mark.parametrize("bad", ["8080", "127.0.0.1", "127.0.0.1:http", "127.0.0.1:70000",
                                 ":8080", "my host:80"])
def test_a_bad_listen_address_is_a_config_error_naming_the_key(bad):
    with pytest.raises(ConfigError) as e:
        parse_config({"console": {"listen": bad}}, "box.toml")
    msg = str(e.value)
    assert "console.listen" in msg and ("HOST:PORT" in msg or "not a host" in msg)
    with pytest.raises(ConfigError) as e:
        parse_config({"foxglove": {"listen": bad}}, "box.toml")
    assert "foxglove.listen" in str(e.value)


# -- serving ----------------------------------------------------------------------------------------
def test_console_serves_page_status_grid_and_snapshot(tmp_path):
    from appliance.status import read_status
    d = console_daemon(tmp_path)
    try:
        url = d.console.console.url
        assert url.startswith("http://127.0.0.1:")
        wait_for_view(d)
        code, h, body = get(url)
        assert code == 200 and h["Content-Type"].startswith("text/html")
        assert b"/app.js" in body and b'id="state"' in body
        code, _, js = get(url + "app.js")
        assert code == 200 and b"/api/status" in js
        code, h, body = get(url + "api/status")
        assert code == 200 and h["Content-Type"] == "application/json"
        doc = json.loads(body)
        sock = read_status(str(tmp_path / "status.sock"))      # what `status --json` shows
        assert set(doc) == set(sock)
        assert doc["state"] == sock["state"] and doc["devices"].keys() == sock["devices"].keys()
        assert doc["devices"]["laser"]["state"] == "ok"
        from appliance.cli import format_status               # `fieldguard status` names it
        assert f"console {url}" in format_status(sock)
        code, h, body = get(url + "api/grid.jpg")
        assert code == 200 and h["Content-Type"] == "image/jpeg" and body[:2] == b"\xff\xd8"
        code, _, body = get(url + "api/view.jpg")       # laser only: no camera to show
        assert code == 404 and b"no camera" in body
        code, h, body = get(url + "api/snapshot.png")
        assert code == 200 and body.startswith(b"\x89PNG")
        code, _, _ = get(url + "api/nothing")
        assert code == 404
    finally:
        d.shutdown()
    with pytest.raises(OSError):                          # shut down with the daemon
        get(url, timeout=2)


def _real_image_run(path, frames):
    """A run folder of the Middlebury 'aloe' pair (tests/data/real, its licence beside it) as
    a forward camera, and a laser that sees nothing: cheap to make, real pixels."""
    import cv2
    import numpy as np
    from pathlib import Path
    from drivers.runfolder import RunWriter
    from hal.types import (LaserGeometry, LaserScan, Mount, PinholeCalibration,
                           StereoCalibration, StereoFrame)
    real = Path(__file__).parent / "data" / "real" / "middlebury_aloe"
    left, right = (cv2.imread(str(real / n)) for n in ("aloeL.jpg", "aloeR.jpg"))
    h, w = left.shape[:2]
    cal = StereoCalibration(camera=PinholeCalibration(w, h, 0.8 * w, 0.8 * w, w / 2, h / 2),
                            baseline_m=0.3, mount=Mount(x_m=1.2, z_m=1.5, pitch_deg=15.0))
    geom = LaserGeometry(angle_min_deg=-135.0, angle_step_deg=0.5, beams=541,
                         range_max_m=50.0, mount=Mount(x_m=1.3, z_m=0.7))
    with RunWriter(path, "aloe", stereo=cal, laser=geom) as wr:
        for i in range(frames):
            t = i * 100_000_000
            wr.write_frame(i, t, stereo=StereoFrame(stamp_ns=t, seq=i, left=left, right=right,
                                                    calib=cal),
                           laser=LaserScan(stamp_ns=t, seq=i, geometry=geom,
                                           ranges_m=np.full(541, np.nan, np.float32)))
    return path


def test_camera_view_has_the_pipelines_drawing_and_tracks(tmp_path):
    """A replay of a short run of a real stereo pair (laser pipeline: the picture, not the
    perception, is under test): the camera view is served, and a track is drawn on it and on
    the grid."""
    import cv2
    import numpy as np
    from appliance.console.views import camera_view, grid_view
    from appliance.daemon import replay_config
    run = _real_image_run(tmp_path / "run", 4)
    cfg = dataclasses.replace(default_config(), console=ConsoleConfig(listen="127.0.0.1:0"))
    d = Daemon(replay_config(cfg, str(run)), mode="replay", replay_path=str(run), pace=0.0,
               status_socket=str(tmp_path / "s.sock"))
    d.start()
    try:
        v = wait_for_view(d)
        assert v.camera_jpeg is not None
        code, h, body = get(d.console.console.url + "api/view.jpg")
        assert code == 200 and body[:2] == b"\xff\xd8"
        img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape[0] == 420 and img.shape[1] > 400
        # a track ahead of the vehicle is drawn on the camera view and on the grid
        track = {"id": 7, "x_m": 4.0, "y_m": 0.0, "length_m": 0.6, "width_m": 0.6,
                 "label": "person"}
        plain, drawn = camera_view(v.res, []), camera_view(v.res, [track])
        assert (np.abs(plain.astype(int) - drawn).sum(axis=2) > 0).sum() > 50
        g0, g1 = grid_view(v.res, v.evidence, d.cfg), grid_view(v.res, v.evidence, d.cfg, [track])
        assert (np.abs(g0.astype(int) - g1).sum(axis=2) > 0).sum() > 50
    finally:
        d.shutdown()


def test_console_refuses_every_method_that_could_write(tmp_path):
    d = console_daemon(tmp_path)
    try:
        d.run(max_cycles=5)
        before = d.status()["state"], d.loop.gate.reason
        for method in ("POST", "PUT", "DELETE", "PATCH"):
            for path in ("", "api/status", "api/snapshot.png", "api/incidents", "api/x"):
                code, h, body = get(d.console.console.url + path, method=method,
                                    data=b"state=CLEAR")
                assert code == 405, (method, path)
                assert h["Allow"] == "GET, HEAD" and b"read-only" in body
        assert (d.status()["state"], d.loop.gate.reason) == before
    finally:
        d.shutdown()


def test_a_taken_port_is_one_log_line_and_the_box_runs_on(tmp_path, caplog):
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen(1)
    port = blocker.getsockname()[1]
    try:
        with caplog.at_level("ERROR", logger="fieldguard.console"):
            d = console_daemon(tmp_path, listen=f"127.0.0.1:{port}")
        try:
            d.run(max_cycles=10)
            st = d.status()
        finally:
            d.shutdown()
    finally:
        blocker.close()
    msgs = [r.getMessage() for r in caplog.records if r.name == "fieldguard.console"]
    assert len(msgs) == 1
    assert f"cannot listen on 127.0.0.1:{port}" in msgs[0] and "runs on without" in msgs[0]
    assert st["console"]["console"] is None and "cannot listen" in st["console"]["errors"][0]
    assert st["cycles"] == 10
    assert not any("console" in f for f in st.get("faults", []))
    assert st["state"] != "STOP" or "console" not in st["reason"]


def test_listen_empty_means_no_console_thread_and_no_port(tmp_path):
    import threading
    d = console_daemon(tmp_path, listen="")
    try:
        d.run(max_cycles=5)
        assert d.console.console is None and d.console.tap is None
        assert not [t for t in threading.enumerate() if t.name.startswith("console")]
    finally:
        d.shutdown()


def test_incidents_are_listed_and_downloaded_and_nothing_else_is(tmp_path):
    from drivers.sim.record import write_sim_run
    inc = tmp_path / "incidents"
    write_sim_run("stubble-day", 2, inc / "20261201-120000-obstacle-4-m", sensors=("laser",))
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "run.toml").write_text("[run]\n")
    d = console_daemon(tmp_path, incident_dir=str(inc))
    try:
        url = d.console.console.url
        code, _, body = get(url + "api/incidents")
        doc = json.loads(body)
        assert [i["name"] for i in doc["incidents"]] == ["20261201-120000-obstacle-4-m"]
        code, h, body = get(url + doc["incidents"][0]["download"].lstrip("/"))
        assert code == 200 and h["Content-Type"] == "application/x-tar"
        names = tarfile.open(fileobj=io.BytesIO(body)).getnames()
        assert "20261201-120000-obstacle-4-m/run.toml" in names
        assert "20261201-120000-obstacle-4-m/laser/000001.csv" in names
        for bad in ("..%2Fsecret.tar", "../secret.tar", "secret.tar", "%2e%2e.tar", ".tar"):
            code, _, _ = get(url + "api/incidents/" + bad)
            assert code == 404, bad
    finally:
        d.shutdown()


def test_entering_stop_keeps_a_picture_of_that_stop(tmp_path):
    d = console_daemon(tmp_path)
    try:
        d.run(max_cycles=15)                         # out of the boot STOP (hold-off 1 s)
        assert d.loop.gate.state is not GateState.STOP
        d.devices["laser"].unplugged = True          # the laser goes silent: STOP
        d.run(max_cycles=5)
        t0 = time.monotonic()
        while not any("laser" in v.reason for v in d.console.tap.stops):
            assert time.monotonic() - t0 < 30
            time.sleep(0.1)
        code, _, body = get(d.console.console.url + "api/stops")
        stops = json.loads(body)
        hit = [s for s in stops if "laser" in s["reason"]]
        assert hit
        code, h, img = get(d.console.console.url + hit[-1]["image"].lstrip("/"))
        assert code == 200 and img[:2] == b"\xff\xd8"
        # a kept stop holds its pictures, not the cycle's frames (memory stays bounded)
        assert all(v.res is None and v.evidence is None and v.grid_jpeg
                   for v in d.console.tap.stops)
    finally:
        d.shutdown()


# -- cheap for the loop -------------------------------------------------------------------------
class _Res:
    def __init__(self, i, state=GateState.CLEAR):
        self.index, self.stamp_ns = i, i * 100_000_000
        self.output = type("O", (), {"state": state, "reason": "r"})()


def test_tap_hands_over_at_the_bounded_rate_and_never_queues():
    import numpy as np
    ev = np.zeros((320, 300), np.float32)
    tap = FrameTap(default_config(), lambda: ev, rate_hz=2.0)
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < 1.0:            # the loop, as fast as it can go
        tap.on_cycle(_Res(n))
        n += 1
    assert n > 1000
    assert 1 <= tap.handed <= 3                     # 2 Hz over one second (+ the first)
    # one slot: whatever was handed over, at most one item waits for the encoder
    assert tap._slot is not None and tap._stop_slot is None
    tap.on_cycle(_Res(n, GateState.STOP))            # entering STOP is always handed over
    assert tap.handed <= 4 and tap._stop_slot is not None


# -- a real browser -------------------------------------------------------------------------------
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


def _browser(profile_dir):
    """Headless chromium with its profile in ``profile_dir`` (the test's tmp_path: pytest
    removes old ones; a tempfile.mkdtemp profile was left in /tmp by every run)."""
    import os
    from conftest import missing_tool
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        missing_tool("chromium and chromium-driver (Debian) are not installed")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        missing_tool("selenium is not installed (test extra)")
    o = webdriver.ChromeOptions()
    o.binary_location = CHROMIUM
    for f in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              "--disable-dev-shm-usage", "--window-size=1400,1200"):
        o.add_argument(f)
    o.add_argument(f"--user-data-dir={profile_dir}")
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=o)


def test_browser_shows_state_and_device_health_of_fieldguard_run_sim(tmp_path):
    """`fieldguard run --sim` in its own process, its console on a free loopback port, the page
    opened in headless chromium: the banner shows the box's state and reason, the device table
    each device's health as `status` reports it."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    from appliance.status import read_status
    root = Path(__file__).resolve().parents[1]
    conf = tmp_path / "box.toml"
    conf.write_text('[console]\nlisten = "127.0.0.1:0"\n')
    sock = str(tmp_path / "status.sock")
    proc = subprocess.Popen([sys.executable, "-m", "appliance.cli", "run", "--sim", "--config",
                             str(conf), "--socket", sock, "--duration", "120"], cwd=root,
                            stdout=subprocess.DEVNULL, stderr=open(tmp_path / "daemon.log", "w"))
    driver = None
    try:
        t0 = time.monotonic()
        while True:
            try:
                st = read_status(sock)
                if st.get("cycles", 0) >= 3 and st.get("console", {}).get("console"):
                    break
            except (ConnectionError, OSError, ValueError):
                pass
            assert proc.poll() is None, (tmp_path / "daemon.log").read_text()
            assert time.monotonic() - t0 < 120, "the daemon did not come up"
            time.sleep(0.3)
        url = st["console"]["console"]["url"]
        driver = _browser(tmp_path / "chromium-profile")
        driver.get(url)
        # The page polls once a second and the box's reason moves with it (a distance, a
        # count): the page shows a (state, reason) the box reported in the last few seconds,
        # as read from its status socket. (An exact match with one read taken after the
        # page's text needed the two to fall in the same cycle: 5 s usually, 30 s once, in
        # the whole suite of 2026-12-08, its limit being 30.)
        seen: list[tuple[float, str, str]] = []
        t0 = time.monotonic()
        while True:
            st = read_status(sock)
            now = time.monotonic()
            seen = [x for x in seen if x[0] >= now - 3.0] + [(now, st["state"], st["reason"])]
            shown = driver.find_element("id", "state").text
            reason = driver.find_element("id", "reason").text
            if (shown, reason) in {(a, b) for _, a, b in seen}:
                break
            assert now - t0 < 30, (shown, reason, seen[-5:])
            time.sleep(0.1)
        assert shown in ("STOP", "SLOW", "CLEAR")
        banner = driver.find_element("id", "banner")
        assert banner.get_attribute("class") == f"state-{shown}"
        assert int(driver.execute_script(
            "return parseInt(getComputedStyle(document.getElementById('state')).fontSize)")) >= 64
        rows = {}
        t0 = time.monotonic()
        while set(rows) != set(st["devices"]):
            rows = {r.get_attribute("data-device"): r.find_elements("tag name", "td")
                    for r in driver.find_elements("css selector", "#devices tbody tr")}
            assert time.monotonic() - t0 < 10
        for name, h in read_status(sock)["devices"].items():
            assert rows[name][2].text == h["state"] == "ok"
            assert rows[name][3].text.endswith(" s")
        # the grid picture loaded (naturalWidth > 0 only for a decoded image)
        t0 = time.monotonic()
        while not driver.execute_script("return document.getElementById('grid').naturalWidth"):
            assert time.monotonic() - t0 < 10
            time.sleep(0.2)
        shot = Path(os.environ.get("FIELDGUARD_CONSOLE_SHOT", tmp_path / "console.png"))
        assert driver.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
    finally:
        if driver is not None:
            driver.quit()
        proc.terminate()
        proc.wait(timeout=20)
    assert proc.returncode == 0
