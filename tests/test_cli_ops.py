"""Each technician command against a running daemon on the simulated field."""
import csv
import dataclasses
import json
import threading
import time

import cv2
import numpy as np
import pytest

from appliance.cli import main
from appliance.config import default_config
from appliance.daemon import Daemon, sim_config
from drivers.runfolder import RunReader


# ---- whole drives, each a `fieldguard run` process of its own (a real daemon: its signal
# handlers, its status socket, the logging it sets up at start). First in the module: the
# module fixture's daemon below runs in real time in this process until the module ends,
# and these ~15 s of drives would be as many seconds of its CPU.
def _run(*args, timeout=300):
    import subprocess
    import sys
    from pathlib import Path
    return subprocess.run([sys.executable, "-m", "appliance.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          cwd=Path(__file__).resolve().parents[1])


def test_the_closing_summary_is_in_words(tmp_path):
    r = _run("run", "--sim", "--fast", "--duration", "10", "--print-every", "5",
             "--socket", tmp_path / "s.sock")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "summary: 100 cycles (sim)" in out
    assert "stops for obstacles: 1: 1 true (something really ahead), 0 false" in out, out
    assert "overrides: none" in out and "collisions: none" in out
    assert "the simulator's rendering (not the box's time) p50" in out


def test_greenhouse_runs_the_rgbd_pipeline_and_drives(tmp_path):
    r = _run("run", "--sim", "greenhouse", "--fast", "--duration", "3", "--print-every", "2",
             "--socket", tmp_path / "s.sock", timeout=900)
    assert r.returncode == 0, r.stderr
    assert "pipelines=rgbd" in r.stderr and "devices=rgbd,link" in r.stderr, r.stderr[-2000:]
    import re
    m = re.search(r"drove (\d+\.\d) m", r.stdout)
    assert m and float(m.group(1)) > 0.3, r.stdout      # the greenhouse sprayer's zones


# ---- against a running daemon ------------------------------------------------------------
@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("daemon")
    sock = str(tmp / "status.sock")
    cfg = default_config()
    cfg = dataclasses.replace(cfg, perception=dataclasses.replace(
        cfg.perception, pipelines=("laser",)))
    d = Daemon(sim_config(cfg), mode="sim", pace=1.0, status_socket=sock)
    d.start()
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    # up once every device has fresh data (a wall-time sleep raced a loaded host's first cycles)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (
            d.loop.last is not None and all(dev.health().state.value == "ok"
                                            for dev in d.devices.values())):
        time.sleep(0.1)
    yield d, sock, tmp
    d.request_stop()
    th.join(5)
    d.shutdown()


def test_watch_draws_the_status_screen(daemon, capsys):
    d, sock, _ = daemon
    assert main(["watch", "--socket", sock, "--count", "2", "--interval", "0.2"]) == 0
    out = capsys.readouterr().out
    assert out.count("fieldguard watch") == 2 and "laser" in out and "loop" in out


def test_snapshot_is_a_readable_picture(daemon, tmp_path, capsys):
    d, sock, _ = daemon
    png = tmp_path / "snap.png"
    assert main(["snapshot", "-o", str(png), "--socket", sock]) == 0
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 300
    # the header is coloured by the state (STOP red, SLOW amber, CLEAR green)
    b, g, r = img[5, 5]
    assert (r > 150 and g < 100) or (g > 150)


def test_selftest_asks_the_running_daemon(daemon, capsys):
    d, sock, _ = daemon
    rc = main(["selftest", "--socket", sock])
    out = capsys.readouterr().out
    assert "asked the running daemon" in out
    assert "PASS  laser" in out and "PASS  link" in out
    assert rc == 0


def test_selftest_fails_a_dead_device_with_a_fix(daemon, capsys):
    d, sock, _ = daemon
    d.devices["laser"].unplugged = True
    try:
        # stale once the SIM clock has passed its timeout: on a loaded host the lock-step
        # loop runs slower than real time, so wait for that, not for wall time
        deadline = time.monotonic() + 20
        while d.devices["laser"].health().state.value == "ok" and time.monotonic() < deadline:
            time.sleep(0.1)
        rc = main(["selftest", "--socket", sock])
        out = capsys.readouterr().out
    finally:
        d.devices["laser"].unplugged = False
    assert rc == 1 and "FAIL  laser" in out and "fix:" in out and "power" in out


def test_record_then_replay(daemon, tmp_path, capsys):
    d, sock, _ = daemon
    out = tmp_path / "rec"
    # the test before this one unplugs the laser: record only once it streams again, so the
    # first recorded frame has a scan (a stale device is recorded as no scan, rightly)
    from hal.health import Health
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and \
            d.devices["laser"].health(d.clock.now_ns()).state is not Health.OK:
        time.sleep(0.1)
    time.sleep(0.3)
    # record waits until the daemon says the folder is written (a guess from frames.csv
    # not growing for 0.5 s raced a loaded host), printing progress, then "done"
    assert main(["record", "--seconds", "1.0", "--out", str(out), "--socket", sock]) == 0
    text = capsys.readouterr().out
    assert "recording: " in text and "frames written" in text
    r = RunReader(out)
    assert f"done: {len(r)} frames in {out}" in text
    assert 8 <= len(r) <= 12
    assert r.laser(0) is not None and r.info.laser is not None
    with open(out / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    assert {row["gate_state"] for row in rows} <= {"STOP", "SLOW", "CLEAR"}
    # never overwritten
    assert main(["record", "--seconds", "1", "--out", str(out), "--socket", sock]) == 1
    assert "not empty" in capsys.readouterr().err
    # and it plays back through the loop
    assert main(["replay", str(out), "--fast", "--socket", str(tmp_path / "r.sock")]) == 0


def test_selftest_without_daemon_opens_the_config(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[devices.laser]\ntype = 'sim'\n[devices.link]\ntype = 'sim'\n")
    rc = main(["selftest", "--config", str(cfg), "--sim", "--seconds", "0.5"])
    out = capsys.readouterr().out
    assert rc == 0 and "opened the devices" in out and "PASS  laser" in out


def test_commands_without_daemon_say_so(tmp_path, capsys):
    sock = str(tmp_path / "none.sock")
    assert main(["snapshot", "-o", str(tmp_path / "x.png"), "--socket", sock]) == 2
    assert "no fieldguard daemon" in capsys.readouterr().err
    assert main(["record", "--seconds", "1", "--out", str(tmp_path / "r"), "--socket", sock]) == 2


def test_sim_rendering_is_reported_apart_from_the_loop(daemon):
    """--sim renders the world while its clock advances between cycles: the loop's acquire
    reads a finished frame, and status shows the rendering on its own (issue #16)."""
    d, sock, _ = daemon
    from appliance.status import read_status
    st = read_status(sock, timeout_s=10)
    r, acq = st["sim_render_ms"], st["timing_ms"]["acquire"]
    assert r["p50"] is not None and acq["p50"] is not None
    # a laser scan and the vehicle take milliseconds to render; acquire only hands them over
    assert acq["p50"] < r["p50"], (acq, r)
    from appliance.cli import format_status
    assert "rendering p50" in format_status(st)
