"""Strobe/trigger controller at the wire: the driver and the controller emulator on the two ends
of a socat pty pair, with garbage bytes, half lines, bad checksums, a silent controller, a
trigger that stops firing, a reported fault and a port that disappears; the daemon's gate in
STOP within two cycles of a trigger fault and recovering. Plus the day/night rule."""
from __future__ import annotations

import os
import shutil
import subprocess
import time

import numpy as np
import pytest

from drivers.emulators.strobe import StrobeControllerEmulator
from drivers.strobe_serial import (DAY, NIGHT, StrobeSerialTrigger, checksum, frame_line,
                                   next_illumination, parse_line, parse_status, scene_brightness)
from hal.clock import MonotonicClock
from hal.health import Health
from tests.test_hw_sick import DaemonRig, wait_for


def test_line_protocol():
    assert frame_line("PING") == b"PING*" + checksum("PING").encode() + b"\n"
    assert checksum("RATE 10.00") == f"{np.bitwise_xor.reduce(np.frombuffer(b'RATE 10.00', np.uint8)):02X}"
    assert parse_line(frame_line("OK ARM")) == "OK ARM"
    for bad in (b"OK ARM*00", b"OK ARM", b"\xff\xfe*12", b"*00", b"OK\x01ARM*" + checksum("OK\x01ARM").encode()):
        with pytest.raises(ValueError):
            parse_line(bad)
    st = parse_status("STATUS rate=10.00 armed=1 strobe=0 pulses=1234 fault=0")
    assert st == {"rate_hz": 10.0, "armed": True, "strobe": False, "pulses": 1234, "fault": 0}
    with pytest.raises(ValueError):
        parse_status("STATUS rate=10.00 armed=1")


def test_day_night_hysteresis():
    ambient = [120, 80, 50, 40, 34, 36, 50, 59, 61, 50, 30]
    mode, modes = DAY, []
    for a in ambient:
        mode = next_illumination(mode, a, night_below=35, day_above=60)
        modes.append(mode)
    assert modes == [DAY] * 4 + [NIGHT] * 4 + [DAY, DAY, NIGHT]
    with pytest.raises(ValueError):
        next_illumination(DAY, 50, night_below=60, day_above=60)


def test_scene_brightness_undoes_auto_exposure():
    import cv2
    from pathlib import Path
    img = cv2.imread(str(Path(__file__).parent / "data/real/stereo_calib/left01.jpg"))
    assert img is not None
    b1 = scene_brightness(img, exposure_us=1000, gain_db=0)
    # the same scene at 1/4 the light, exposed 4x longer by auto-exposure, looks the same;
    # the normalised brightness says 1/4
    dark = scene_brightness(img, exposure_us=4000, gain_db=0)
    assert dark == pytest.approx(b1 / 4, rel=1e-6)
    assert scene_brightness(img, 1000, gain_db=20) == pytest.approx(b1 / 10, rel=1e-6)
    assert 20 < scene_brightness(img, 1000, ref_exposure_us=1000) < 235


# ---------------------------------------------------------------------------------------------
class PtyPair:
    """socat pty pair: /tmp/...A for the driver, /tmp/...B for the emulator."""

    def __init__(self, tmp):
        if shutil.which("socat") is None:
            from tests.conftest import missing_tool
            missing_tool("socat is not installed (tools/hw_system_deps.sh installs it)")
        self.a, self.b = str(tmp / "ttyA"), str(tmp / "ttyB")
        self.start()

    def start(self):
        self.proc = subprocess.Popen(["socat", "-d", "-d", f"pty,rawer,link={self.a}",
                                      f"pty,rawer,link={self.b}"], stderr=subprocess.DEVNULL)
        assert wait_for(lambda: os.path.exists(self.a) and os.path.exists(self.b), 3.0)

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(3)


@pytest.fixture
def wire(tmp_path):
    pair = PtyPair(tmp_path)
    fd = os.open(pair.b, os.O_RDWR | os.O_NOCTTY)
    emu = StrobeControllerEmulator(fd).start()
    dev = StrobeSerialTrigger("trigger", MonotonicClock(), port=pair.a, backoff_max_s=0.4)
    dev.open()
    dev.start_acquisition()
    yield pair, emu, dev
    dev.close()
    dev.close()
    emu.stop()
    os.close(fd)
    pair.kill()


def test_configures_and_streams_status(wire):
    pair, emu, dev = wire
    assert wait_for(lambda: dev.health().ok, 3.0), dev.health()
    assert emu.armed and emu.rate_hz == 10.0 and not emu.strobe
    assert {"RATE 10.00", "STROBE OFF", "ARM"} <= set(emu.received)
    p0 = dev.newest()["pulses"]
    time.sleep(0.35)
    assert dev.newest()["pulses"] >= p0 + 2          # the trigger is firing at 10 Hz
    dev.set_strobe(True)
    assert wait_for(lambda: emu.strobe and dev.newest()["strobe"], 2.0)
    dev.set_rate(12.5)
    assert wait_for(lambda: emu.rate_hz == 12.5 and dev.newest()["rate_hz"] == 12.5, 2.0)
    ok, msg = dev.selftest()
    assert ok and "12.5 Hz" in msg and "strobe on" in msg


@pytest.mark.parametrize("fault, reason", [("garbage 40", "bad data on the serial line"),
                                           ("half", "bad data on the serial line"),
                                           ("badsum", "bad checksum"),
                                           ("stall", "stopped firing"),
                                           ("fault 2 strobe lamp open circuit", "lamp open")])
def test_faults_mark_fault_then_recover(wire, fault, reason):
    pair, emu, dev = wire
    assert wait_for(lambda: dev.health().ok, 3.0)
    emu.command(fault)
    assert wait_for(lambda: dev.health().state is Health.FAULT, 1.5), dev.health()
    assert reason in dev.health().reason or reason in str(dev.counters)
    if fault == "stall":
        emu.command("fire")
    if fault.startswith("fault"):
        time.sleep(0.3)
        assert dev.health().state is Health.FAULT       # the controller still reports it
        emu.command("fault 0")
    assert wait_for(lambda: dev.health().ok, 2.0), dev.health()


def test_silent_controller_goes_stale(wire):
    pair, emu, dev = wire
    assert wait_for(lambda: dev.health().ok, 3.0)
    emu.command("silent")
    t0 = time.monotonic()
    assert wait_for(lambda: not dev.health().ok, 1.0)
    assert time.monotonic() - t0 < dev.timeout_s + 0.15
    emu.command("resume")
    assert wait_for(lambda: dev.health().ok, 2.0)


def test_port_disappears_then_comes_back(wire):
    pair, emu, dev = wire
    assert wait_for(lambda: dev.health().ok, 3.0)
    pair.kill()
    assert wait_for(lambda: dev.health().state in (Health.FAULT, Health.NO_DATA), 1.0)
    assert wait_for(lambda: dev.counters.get("reopens", 0) >= 1, 2.0)
    assert not dev.selftest()[0]
    pair.start()                                      # plugged back in: a fresh pty pair
    fd = os.open(pair.b, os.O_RDWR | os.O_NOCTTY)
    emu2 = StrobeControllerEmulator(fd).start()
    try:
        assert wait_for(lambda: dev.health().ok, 4.0), dev.health()
        assert emu2.armed                             # re-configured from scratch
    finally:
        emu2.stop()
        os.close(fd)


def test_daemon_stops_when_the_trigger_stops_firing(tmp_path):
    from drivers.emulators.sick_lms1xx import SickLms1xxEmulator, sim_scans
    pair = PtyPair(tmp_path)
    fd = os.open(pair.b, os.O_RDWR | os.O_NOCTTY)
    emu = StrobeControllerEmulator(fd).start()
    geo, scans = sim_scans("stubble-empty", 2)
    laser = SickLms1xxEmulator(geo, scans).start()
    rig = None
    try:
        rig = DaemonRig({"laser": {"type": "sick-lms1xx", "host": "127.0.0.1",
                                   "port": laser.port},
                         "trigger": {"type": "serial", "port": pair.a}})
        assert wait_for(lambda: rig.state == "CLEAR", 5.0), rig.cycles[-3:]
        t0 = rig.now()
        emu.command("fault 3 trigger output short circuit")
        assert wait_for(lambda: rig.cycles_until(t0, "STOP") is not None, 2.0)
        assert rig.cycles_until(t0, "STOP") <= 2
        assert "short circuit" in " ".join(rig.cycles[-1][2])
        emu.command("fault 0")
        assert wait_for(lambda: rig.state == "CLEAR", 4.0)
        t1 = rig.now()
        emu.command("stall")
        assert wait_for(lambda: rig.cycles_until(t1, "STOP") is not None, 2.0)
        # a stall is only visible after 2.5 pulse periods (0.25 s) plus one status poll
        assert rig.cycles_until(t1, "STOP") <= 5
        emu.command("fire")
        assert wait_for(lambda: rig.state == "CLEAR", 4.0)
    finally:
        if rig:
            rig.close()
        laser.stop()
        emu.stop()
        os.close(fd)
        pair.kill()
