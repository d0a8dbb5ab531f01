"""Kinect-class RGB-D through libfreenect, tested at the wire with libfreenect's own playback
(fakenect): dumps written by drivers/emulators/fakenect_dump.py are played by Debian's
fakenect library through the real Python binding in the driver's helper process. Frames
arrive, depth round-trips in millimetres, invalid depth stays 0, a silent device goes stale and
is restarted, the end of the dump is a fault, closing twice is safe, selftest; and the daemon
(`fieldguard run` with a hardware config) drives the rgbd pipeline from it."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.emulators.fakenect_dump import (DumpWriter, build_stub, depth_to_mm, fakenect_libdir,
                                              read_frame, sim_dump, with_gap)
from hal.clock import MonotonicClock
from hal.health import Health
from tests.test_hw_sick import DaemonRig, wait_for

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------
def test_dump_format_is_what_fakenect_reads(tmp_path):
    """INDEX.txt lists r-/d- files named <type>-<time>-<timestamp>.<ext> in order; PGM/PPM
    headers on one line (fakenect skips to the first newline); depth in host byte order."""
    c = np.zeros((480, 640, 3), np.uint8)
    c[..., 2] = 200                                     # BGR: red
    d = np.arange(480 * 640, dtype=np.uint32).reshape(480, 640).astype(np.uint16)
    with DumpWriter(tmp_path / "dump", fps=10) as w:
        w.add(c, d)
        w.add(c, d, gap_s=2.0)
    names = (tmp_path / "dump/INDEX.txt").read_text().split()
    assert [n[0] for n in names] == ["r", "d", "r", "d"]
    times = [float(n.split("-")[1]) for n in names]
    assert times[2] - times[0] == pytest.approx(2.1)       # 1/fps + the gap
    for n in names:                                        # fakenect's sscanf("%c-%lf-%u-%*s")
        kind, t, rest = n.split("-", 2)
        int(rest.split(".")[0])
    raw = (tmp_path / "dump" / names[1]).read_bytes()
    assert raw.startswith(b"P5 640 480 65535\n") and len(raw) == 17 + 640 * 480 * 2
    np.testing.assert_array_equal(read_frame(tmp_path / "dump" / names[1]), d)
    np.testing.assert_array_equal(read_frame(tmp_path / "dump" / names[0])[0, 0], [200, 0, 0])
    with pytest.raises(FileExistsError):
        DumpWriter(tmp_path / "dump")
    g = with_gap(tmp_path / "dump", tmp_path / "gap", 0, 5.0)
    gnames = (g / "INDEX.txt").read_text().split()
    gtimes = [float(n.split("-")[1]) for n in gnames]
    assert gtimes[2] - gtimes[0] == pytest.approx(7.1) and gtimes[:2] == times[:2]
    np.testing.assert_array_equal(read_frame(g / gnames[3]), d)
    with pytest.raises(ValueError):
        DumpWriter(tmp_path / "d2").add(c[:10], d)


def test_depth_to_mm():
    m = np.array([[0.0, 0.5, 1.2344, np.nan], [-1.0, 4.9996, 12.0, np.inf]], np.float32)
    mm = depth_to_mm(m)
    assert mm.dtype == np.uint16
    assert mm.tolist() == [[0, 500, 1234, 0], [0, 5000, 10000, 0]]


# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stub(tmp_path_factory):
    if fakenect_libdir() is None:
        from tests.conftest import missing_tool
        missing_tool("fakenect (libfreenect-bin) is not installed (tools/hw_system_deps.sh)")
    if shutil.which("gcc") is None or not Path("/usr/include/libfreenect.h").exists():
        from tests.conftest import missing_tool
        missing_tool("gcc + libfreenect-dev are needed to build the fakenect stub")
    r = subprocess.run([sys.executable, "-c", "import freenect"], capture_output=True, text=True,
                       env={**os.environ, **_bare_env()})
    if r.returncode != 0:
        from tests.conftest import missing_tool
        missing_tool(f"the freenect Python binding does not import: {r.stderr.strip()[-200:]} "
                     f"(pip install freenect; needs libfreenect-dev)")
    return build_stub(tmp_path_factory.mktemp("stub"))


def _bare_env():
    return {"LD_PRELOAD": "", "FAKENECT_PATH": ""}


def ramp_dump(path, frames=6, fps=15.0, gap_after=None, gap_s=0.0):
    """Frame i: colour (B, G, R) = (i, 100, 200); depth = 500 + (x + y) mod 4000 + i mm, with
    holes (0) on every 7th column. Returns the expected depth per frame."""
    yy, xx = np.mgrid[0:480, 0:640]
    base = (500 + (xx + yy) % 4000).astype(np.uint16)
    expect = []
    with DumpWriter(path, fps=fps) as w:
        for i in range(frames):
            c = np.zeros((480, 640, 3), np.uint8)
            c[..., 0], c[..., 1], c[..., 2] = i, 100, 200
            d = base + np.uint16(i)
            d[:, ::7] = 0
            w.add(c, d, gap_s=gap_s if i == gap_after else 0.0)
            expect.append(d)
    return expect


def make_dev(dump, stub, **kw):
    from drivers.freenect_rgbd import FreenectDepthCamera
    kw.setdefault("backoff_max_s", 0.4)
    d = FreenectDepthCamera("rgbd", MonotonicClock(), fakenect=str(dump),
                            fakenect_preload=str(stub), **kw)
    d.open()
    d.start_acquisition()
    return d


def test_frames_arrive_depth_round_trips_end_of_dump_is_a_fault(tmp_path, stub):
    expect = ramp_dump(tmp_path / "dump", frames=8)
    d = make_dev(tmp_path / "dump", stub)
    seen = {}
    try:
        assert wait_for(lambda: d.health().ok, 8.0), d.health()
        ok, msg = d.selftest()
        assert ok and "streaming registered depth" in msg, msg
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and len(seen) < 4:
            f = d.latest()
            if f is not None:
                seen[int(f.color[0, 0, 0])] = f
            time.sleep(0.01)
        assert len(seen) >= 4, seen.keys()
        for i, f in seen.items():
            assert f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8
            assert f.color[5, 5].tolist() == [i, 100, 200]          # RGB on the wire -> BGR
            assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (480, 640)
            mm = np.rint(f.depth_m / f.calib.depth_unit_m).astype(np.int64)
            np.testing.assert_array_equal(mm, expect[i])            # exact, in millimetres
            assert np.all(f.depth_m[:, ::7] == 0)                   # invalid stays 0
            assert f.depth_m[0, 1] == pytest.approx(0.501 + i * 0.001)
        # the end of the dump: libfreenect returns an error, the helper ends: FAULT, restart
        assert wait_for(lambda: d.health().state is Health.FAULT, 4.0), d.health()
        assert "process_events returned -1" in d.health().reason
        assert not d.selftest()[0]
        assert wait_for(lambda: d.counters.get("restarts", 0) >= 1 and d.health().ok, 4.0)
        assert d.counters["starts"] >= 2
    finally:
        d.close()
        d.close()                                                    # twice is safe
    assert d.health().state is Health.CLOSED
    assert d._proc is None


def test_silent_device_goes_stale_then_is_restarted(tmp_path, stub):
    ramp_dump(tmp_path / "dump", frames=6, gap_after=3, gap_s=3.0)
    d = make_dev(tmp_path / "dump", stub, lost_after_s=0.8)
    try:
        assert wait_for(lambda: d.health().ok, 8.0), d.health()
        # frames 0-3, then fakenect sleeps 3 s inside libfreenect: no frames, no error
        assert wait_for(lambda: d.health().state is Health.NO_DATA, 3.0), d.health()
        h = d.health()
        assert h.age_s <= d.timeout_s + 0.1
        assert d.latest() is None
        # the driver's own thread never blocked: it gives up after lost_after_s and restarts
        assert wait_for(lambda: "no frames for" in (d.health().reason or ""), 3.0)
        assert wait_for(lambda: d.health().ok, 4.0)                  # replayed from the start
        assert d.counters["restarts"] >= 1
    finally:
        d.close()


def test_missing_device_is_a_fault_with_backoff(tmp_path, stub):
    """A dump folder without INDEX.txt: fakenect exit()s inside the library (as a crash would):
    only the helper dies; the driver reports it and backs off."""
    (tmp_path / "empty").mkdir()
    d = make_dev(tmp_path / "empty", stub)
    try:
        assert wait_for(lambda: d.counters.get("restarts", 0) >= 2, 8.0), d.health()
        h = d.health()
        assert h.state is Health.FAULT and "stopped (helper exit" in h.reason
        assert "INDEX.txt" in h.reason                 # fakenect's own message, from stderr
        assert d.backoff.delay_s > 0.2
    finally:
        d.close()


# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def greenhouse_dump(tmp_path_factory, stub):
    """16 frames of the simulated greenhouse at 15 fps, three times over (3.2 s)."""
    out = tmp_path_factory.mktemp("gh") / "dump"
    return sim_dump(out, scene="greenhouse", frames=16, fps=15.0, repeat=3)


def _rgbd_options(info, stub):
    return {"type": "freenect", "fakenect": info["dump"], "fakenect_preload": str(stub),
            "backoff_max_s": 0.4, **info["calibration"]}


def test_daemon_runs_the_rgbd_pipeline_from_the_kinect(greenhouse_dump, stub, tmp_path):
    # the first 16 frames, silent for 0.6 s after the 8th
    gap = {**greenhouse_dump, "dump": str(with_gap(greenhouse_dump["dump"], tmp_path / "gap", 8,
                                                   0.6, keep=16))}
    rig = DaemonRig({"rgbd": _rgbd_options(gap, stub)}, pipelines=("rgbd",))
    dev = rig.daemon.devices["rgbd"]
    period = 1 / 15.0

    def first_fault(since, text):
        return next((c for c in list(rig.cycles) if c[0] >= since
                     and any(f.startswith("rgbd:") and text in f for f in c[2])), None)

    try:
        # the pipeline runs on the Kinect's frames: fault-free cycles on fresh frames
        assert wait_for(lambda: len({c[3]["rgbd"] for c in rig.cycles if not c[2]}) >= 3,
                        10.0), rig.cycles[-3:]
        t_ok = next(c[0] for c in rig.cycles if not c[2])
        # (under load the first fault-free cycle can come after the gap: each event is looked
        # for by its own fault text, in this replay or the next one after the restart)
        # the Kinect goes silent (the dump's 0.6 s gap, inside libfreenect): STOP within two
        # cycles of the frame that did not come
        assert wait_for(lambda: rig.silence_stop_cycles("rgbd", period, t_ok, "stale")
                        is not None, 6.0), rig.cycles[-1][:3]
        assert rig.silence_stop_cycles("rgbd", period, t_ok, "stale") <= 2
        first = first_fault(t_ok, "stale")
        assert first[1] == "STOP"
        assert wait_for(lambda: first_fault(first[0] + 300_000_000, "stale") is not None,
                        2.0)                                    # it lasts: the gap
        # the end of the dump (libfreenect returns an error): STOP within two cycles
        ended = "process_events returned -1"
        assert wait_for(lambda: rig.silence_stop_cycles("rgbd", period, t_ok, ended)
                        is not None, 6.0), rig.cycles[-1][:3]
        assert rig.silence_stop_cycles("rgbd", period, t_ok, ended) <= 2
        end = first_fault(t_ok, ended)
        assert end[1] == "STOP"
        # frames again after each: the faults clear (after the end: replayed from the start)
        for t in (first[0], end[0]):
            assert wait_for(lambda: any(not c[2] for c in list(rig.cycles) if c[0] > t), 6.0)
        assert dev.counters["restarts"] >= 1
    finally:
        rig.close()


def test_daemon_gate_clears_again_after_the_kinect_recovers(greenhouse_dump, stub, tmp_path):
    """The same silence and end of dump with no pipeline, so only the Kinect's health decides
    (the greenhouse's bushes keep the rgbd pipeline's gate in STOP above): each fault puts the
    gate in STOP within two cycles, and once frames come again the gate is CLEAR."""
    gap = {**greenhouse_dump, "dump": str(with_gap(greenhouse_dump["dump"], tmp_path / "gap", 8,
                                                   0.6, keep=16))}
    rig = DaemonRig({"rgbd": _rgbd_options(gap, stub)}, pipelines=())
    period = 1 / 15.0
    try:
        t = rig.now()
        for text in ("stale", "process_events returned -1"):
            assert wait_for(lambda: rig.silence_stop_cycles("rgbd", period, t, text)
                            is not None, 6.0), (text, rig.cycles[-1][:3])
            assert rig.silence_stop_cycles("rgbd", period, t, text) <= 2
            bad = next(c for c in list(rig.cycles) if c[0] >= t
                       and any(f.startswith("rgbd:") and text in f for f in c[2]))
            assert bad[1] == "STOP"
            assert wait_for(lambda: rig.cycles_until(bad[0], "CLEAR") is not None, 6.0), \
                (text, rig.cycles[-1][:3])
            t = next(c[0] for c in list(rig.cycles) if c[0] >= bad[0] and c[1] == "CLEAR")
        assert rig.daemon.devices["rgbd"].counters["restarts"] >= 1
    finally:
        rig.close()


def test_fieldguard_run_with_a_hardware_config(greenhouse_dump, stub, tmp_path):
    """`fieldguard run --config hw.toml` with the freenect device and the rgbd pipeline."""
    opts = _rgbd_options(greenhouse_dump, stub)
    lines = ["[perception]", 'pipelines = ["rgbd"]', "", "[devices.rgbd]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in opts.items()]
    lines += ["", "[devices.link]", 'type = "log"', "", "[status]",
              f'socket = "{tmp_path}/s.sock"']
    (tmp_path / "hw.toml").write_text("\n".join(lines) + "\n")
    exe = ROOT / ".venv/bin/fieldguard"
    exe = str(exe) if exe.exists() else "fieldguard"
    r = subprocess.run([exe, "run", "--config", str(tmp_path / "hw.toml"), "--duration", "2.5",
                        "--print-every", "0.5"],
                       capture_output=True, text=True, timeout=60, cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout.splitlines()
    # the closing summary is in words now: "summary: N cycles (hardware); the last cycle ..."
    final = [x for x in out if x.startswith("summary: ")]
    assert final, out[-8:]
    assert int(final[-1].split()[1]) >= 20, final[-1]
    states = [x for x in out if x.startswith("[")]
    # booted in STOP while the helper started; then the gate decided on what the rgbd pipeline
    # found in the Kinect's frames (the greenhouse's bushes are close: obstacle or clear)
    assert "rgbd: no data yet" in states[0] or "booting" in states[0], states[0]
    assert any("obstacle" in x or "| clear" in x.lower() for x in states), states
    assert "fieldguard up: mode=hardware devices=rgbd,link pipelines=rgbd" in r.stderr
    # `fieldguard selftest --config`: opens the devices itself and reports the Kinect (asked
    # 1 s after start: the helper is up in ~0.35 s, the dump lasts 3.2 s)
    r = subprocess.run([exe, "selftest", "--config", str(tmp_path / "hw.toml"), "--seconds",
                        "1.0"], capture_output=True, text=True, timeout=60, cwd=str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr[-2000:]
    assert "PASS  rgbd" in r.stdout and "streaming registered depth + colour" in r.stdout


def test_stream_check_reports_figures(tmp_path, stub):
    """`python -m drivers.freenect_rgbd --stream` (the technician's check, and the figures in
    docs/hardware.md) on a 30 fps dump: throttled to 15 pairs/s, every pair timed."""
    from drivers.freenect_rgbd import stream_check
    # 2.5 s of dump for a 1.2 s check: the selftest at the end must find it still streaming
    # (a 1 s dump could end before the check did when the helper starts fast)
    ramp_dump(tmp_path / "dump", frames=75, fps=30.0)
    r = stream_check(1.2, fakenect=str(tmp_path / "dump"), fakenect_preload=str(stub))
    assert r["pairs"] >= 5 and r["counters"]["throttled"] >= 5
    assert r["pairs_per_s"] <= 15.5
    assert 0 <= r["publish_age_ms"]["p50"] <= r["publish_age_ms"]["max"] < 200
    assert r["driver_cpu_ms_per_pair"] > 0 and r["helper_cpu_ms_per_pair"] > 0
    assert r["selftest"][0]
