"""GigE stereo through Aravis: debayering, pairing and rectification on recorded frames (the
real OpenCV chessboard pairs), and the real driver against two of Aravis's own fake GigE Vision
cameras (``arv-fake-gv-camera-0.8``) in a network namespace the test creates, inside the daemon:
streaming, packet resends in health, a camera pulled out -> STOP, plugged back -> CLEAR.

The namespace part runs this file as a child process under ``ip netns exec`` (a process joins a
network namespace as a whole; pytest itself stays outside)."""
from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from drivers.aravis_stereo import DEBAYER, REAPER, FramePairer, to_bgr  # noqa: E402
from drivers.calibration import (Rectifier, StereoCalibrationResult, calibrate_stereo,  # noqa: E402
                                 find_chessboard, load_stereo_calibration,
                                 save_stereo_calibration)
from hal.types import Mount  # noqa: E402

CAL_DIR = ROOT / "tests/data/real/stereo_calib"


def _pairs():
    import cv2
    ls = sorted(glob.glob(str(CAL_DIR / "left*.jpg")))
    rs = sorted(glob.glob(str(CAL_DIR / "right*.jpg")))
    return [(cv2.imread(a), cv2.imread(b)) for a, b in zip(ls, rs)]


@pytest.fixture(scope="module")
def pairs():
    return _pairs()


@pytest.fixture(scope="module")
def calibration(pairs):
    return calibrate_stereo(pairs, (9, 6), 0.025)


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", sorted(DEBAYER))
def test_debayer_follows_genicam_naming(pairs, fmt):
    img = pairs[0][0].astype(np.uint8)
    b, g, r = img[..., 0], img[..., 1], img[..., 2]
    pat = fmt[5:7]                                   # e.g. "RG": row 0 = R G, row 1 = G B
    chan = {"R": r, "G": g, "B": b}
    order = {"RG": "RGGB", "BG": "BGGR", "GR": "GRBG", "GB": "GBRG"}[pat]
    raw = np.zeros(img.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        raw[dy::2, dx::2] = chan[order[k]][dy::2, dx::2]
    out = to_bgr(raw.tobytes(), raw.shape[1], raw.shape[0], fmt)
    # demosaicing blurs edges; the colour channels must land in the right places
    err = np.abs(out.astype(int) - img.astype(int))[4:-4, 4:-4].mean(axis=(0, 1))
    assert err.max() < 12, (fmt, err)


def test_pairing_on_recorded_frames(pairs):
    """The chessboard pairs as two streams at 10 Hz with arrival jitter, one right frame lost
    and one left frame late beyond the tolerance: every pair that comes out is a true pair."""
    rng = np.random.default_rng(1)
    p = FramePairer(tolerance_ns=15_000_000)
    out = []
    events = []
    for i in range(len(pairs)):
        t = i * 100_000_000
        if i != 4:
            events.append((t + int(rng.integers(0, 8e6)), 0, i))
        if i != 7:
            events.append((t + int(rng.integers(0, 8e6)), 1, i))
        if i == 4:
            events.append((t + 40_000_000, 0, i))    # 40 ms late: no partner within 15 ms
    for t, side, i in sorted(events):
        out += p.add(side, t, i)
    got = [(a, b) for _, a, b in out]
    assert all(a == b for a, b in got)
    assert sorted(a for a, _ in got) == [i for i in range(len(pairs)) if i not in (4, 7)]
    assert p.unmatched == 3                          # right 4, the late left 4, left 7


def test_calibration_and_rectification_on_real_chessboards(pairs, calibration, tmp_path):
    import cv2
    cal = calibration
    assert cal.pairs_used == len(pairs) == 13 and cal.rms_px < 0.6
    path = tmp_path / "cal.json"
    save_stereo_calibration(cal, path)
    back = load_stereo_calibration(path)
    np.testing.assert_allclose(back.K1, cal.K1)
    rect = Rectifier(back, Mount(x_m=1.0))
    sc = rect.stereo_calibration
    assert sc.baseline_m == pytest.approx(np.linalg.norm(cal.T), rel=0.02)
    assert (sc.camera.width, sc.camera.height) == (640, 480)
    before, after = [], []
    for left, right in pairs:
        cl = find_chessboard(cv2.cvtColor(left, cv2.COLOR_BGR2GRAY), (9, 6))
        cr = find_chessboard(cv2.cvtColor(right, cv2.COLOR_BGR2GRAY), (9, 6))
        before.append(np.abs(cl.reshape(-1, 2)[:, 1] - cr.reshape(-1, 2)[:, 1]).mean())
        rl, rr = rect.rectify(left, right)
        cl = find_chessboard(cv2.cvtColor(rl, cv2.COLOR_BGR2GRAY), (9, 6))
        cr = find_chessboard(cv2.cvtColor(rr, cv2.COLOR_BGR2GRAY), (9, 6))
        if cl is not None and cr is not None:
            after.append(np.abs(cl.reshape(-1, 2)[:, 1] - cr.reshape(-1, 2)[:, 1]).mean())
    assert len(after) >= 10
    assert np.mean(after) < 0.3 < np.mean(before)    # rows line up after rectification
    with pytest.raises(Exception, match="not a stereo calibration"):
        StereoCalibrationResult.from_json({"format": "fieldguard-stereo-calibration/1"})


def test_calibrate_stereo_tool(tmp_path):
    out = tmp_path / "cal.json"
    r = subprocess.run([sys.executable, str(ROOT / "tools/calibrate_stereo.py"),
                        "--left", str(CAL_DIR / "left*.jpg"), "--right", str(CAL_DIR / "right*.jpg"),
                        "--square-m", "0.025", "--out", str(out)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert "pairs used 13/13" in r.stdout
    assert json.loads(out.read_text())["image_size"] == [640, 480]


# ---------------------------------------------------------------------------------------------
def _need(tool):
    if shutil.which(tool) is None:
        from tests.conftest import missing_tool
        missing_tool(f"{tool} is not installed (tools/hw_system_deps.sh installs it)")


@pytest.fixture
def netns():
    _need("ip")
    _need("arv-fake-gv-camera-0.8")
    try:
        import gi
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        from tests.conftest import missing_tool
        missing_tool(f"Aravis from Python: {exc} (PyGObject<3.51 + gir1.2-aravis-0.8)")
    name = f"fgarv{os.getpid()}"
    r = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if r.returncode:
        from tests.conftest import missing_tool
        missing_tool(f"cannot create a network namespace: {r.stderr.strip()}")
    try:
        for cmd in (["ip", "link", "set", "lo", "up"],
                    ["ip", "addr", "add", "127.0.0.2/32", "dev", "lo"]):
            subprocess.run(["ip", "netns", "exec", name, *cmd], check=True)
        yield name
    finally:
        subprocess.run(["ip", "netns", "pids", name], capture_output=True)
        out = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True).stdout
        for pid in out.split():
            try:
                os.kill(int(pid), 9)
            except OSError:
                pass
        subprocess.run(["ip", "netns", "del", name])


def test_fake_gige_pair_through_the_daemon(netns, calibration, tmp_path):
    cal = tmp_path / "cal.json"
    save_stereo_calibration(calibration, cal)
    # never beside the soak (its own fake GigE pair, daemon and emulators at nice -10 in a
    # session of its own): this pair drops frames when the host is busy, and in the whole
    # suite the soak ran beside this test at random (one failure at cb6809e: the daemon STOP
    # for stale stereo through the 5 s wait before the kill, the right camera reopened, 4025
    # packets missing; the thirty-eighth session)
    from tests.conftest import hold_wallclock_lock
    lock, waited = hold_wallclock_lock()
    try:
        r = subprocess.run(["ip", "netns", "exec", netns, sys.executable, __file__, "--child",
                            str(cal)], capture_output=True, text=True, timeout=90,
                           cwd=str(ROOT))
    finally:
        if lock is not None:
            lock.close()
    lines = [x for x in r.stdout.splitlines() if x.startswith("{")]
    assert r.returncode == 0 and lines, r.stdout[-2000:] + r.stderr[-3000:]
    res = json.loads(lines[-1])
    # said with a failure below: the fake pair drops most frames when the host is busy (the
    # twenty-ninth session's note), and one failure in a whole run came with nothing else of
    # the suite's left running that could be found afterwards: what else this process ran
    res["host"] = {"loadavg": os.getloadavg(),
                   "pytest_threads": sorted(t.name for t in threading.enumerate()),
                   "waited_for_the_soak_s": round(waited, 1), "beside_the_soak": lock is None}
    # streaming through the real driver, both cameras found (one by serial, one by address)
    assert res["first_state"] == "CLEAR", res
    assert res["frame_shape"] == [480, 640, 3]
    assert res["pairs"] >= 5
    # the right camera loses 0.2 % of its packets; Aravis asks for resends, the fake camera
    # cannot resend, so frames are dropped: all of it shows in health
    assert res["resent_packets"] > 0 and res["counters"]["dropped_frames"] > 0
    # the self-test waits up to a second for a fresh pair when the newest is stale at first
    # look (one lost right frame makes it so for a period): before, it failed once in a CI run
    # at 8518f4e with nothing printed; what it said is printed now with the counters
    assert res["selftest"][0] and "pairs" in res["selftest"][1], json.dumps(
        {k: res.get(k) for k in ("selftest", "counters", "host")})
    assert res["socket_buffer"] == ["auto", "auto"], res
    # camera pulled out: silent; stale 60 ms after its next pair was due (timeout_s 0.16 s = one
    # 10 Hz period + 60 ms), STOP within two cycles of that moment (and so within three of the
    # kill, which can come up to a period before the missing pair was due)
    assert res["clear_before_kill"], json.dumps({k: res.get(k) for k in (
        "states_before_kill", "driver_trace_before_kill", "counters", "host")})
    assert res["stop_cycles_after_due"] is not None and res["stop_cycles_after_due"] <= 2, res
    assert res["stop_cycles_after_kill"] <= 3
    assert "stereo" in res["stop_reason"]
    # plugged back in: reconnected with back-off, CLEAR again
    assert res["clear_after_restart"], json.dumps({k: res.get(k) for k in (
        "states_after_restart", "driver_trace", "counters", "host")})
    assert res["reconnects"] >= 1


# ---------------------------------------------------------------------------------------------
def _trace_driver(dev) -> list:
    """(loop-clock s, what) for each connect, drop and reap of the driver, with how long the
    call took: said when the replug check fails (diagnosis of a flaky failure)."""
    trace = []
    clock = dev.clock

    def wrap(obj, name, label):
        f = getattr(obj, name)

        def traced(*a, **k):
            t = clock.now_ns() / 1e9
            w = time.monotonic()
            try:
                r = f(*a, **k)
            except Exception as exc:
                trace.append((t, f"{label} raised after {time.monotonic() - w:.2f} s: {exc}"))
                raise
            took = time.monotonic() - w
            if not label.startswith("reap") or r or took > 0.05:
                trace.append((t, f"{label} -> {r!r} in {took:.2f} s"))
            return r
        setattr(obj, name, traced)

    wrap(dev, "_start", "start")
    wrap(dev, "_drop", "drop")
    for c in dev.cams:
        wrap(c, "reap", f"reap {c.side}")
        wrap(c, "open", f"open {c.side}")
    return trace


def _child(cal_path: str) -> int:
    """Runs inside the namespace: two fake cameras, the daemon with the aravis stereo driver and
    a SICK emulator laser; prints one JSON result line."""
    from drivers.emulators.sick_lms1xx import SickLms1xxEmulator, sim_scans
    from tests.test_hw_sick import DaemonRig, wait_for

    def cam(addr, serial, extra=()):
        return subprocess.Popen(["arv-fake-gv-camera-0.8", "-i", addr, "-s", serial, *extra],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    left, right = cam("127.0.0.1", "GV01"), cam("127.0.0.2", "GV02", ("-r", "2"))
    time.sleep(0.5)
    geo, scans = sim_scans("stubble-empty", 2)
    laser = SickLms1xxEmulator(geo, scans).start()
    res = {}
    rig = None
    try:
        rig = DaemonRig({"laser": {"type": "sick-lms1xx", "host": "127.0.0.1",
                                   "port": laser.port},
                         "stereo": {"type": "aravis", "left": "GV01", "right": "127.0.0.2",
                                    "calibration": cal_path, "trigger": "Software",
                                    "pixel_format": "BayerRG8", "exposure_us": 5000.0,
                                    "lost_after_s": 0.6, "backoff_max_s": 0.5,
                                    # a fixed packet size: with Aravis's automatic one the
                                    # count of packets per frame (and so of losses at 2 in
                                    # 1000) varied ~7x between runs on loopback. 8192 (jumbo:
                                    # lo's MTU is 65536): ~38 packets a frame, ~7 % of the
                                    # right camera's frames lost. At 1500 (~205 packets) it
                                    # lost 14-47 % of them, and a second of fresh pairs in a
                                    # row, which the gate's 1-s clear hold needs before the
                                    # kill, came by luck: 1 run in 6 with the simulated part
                                    # of the suite beside it never got there in 5 s (the
                                    # forty-second session; once in a fresh-clone CI run)
                                    "packet_size": 8192}})
        dev = rig.daemon.devices["stereo"]
        trace = _trace_driver(dev)
        wait_for(lambda: rig.state == "CLEAR", 10.0)
        res["first_state"] = rig.state
        res["first_faults"] = rig.cycles[-1][2] if rig.cycles else None
        time.sleep(1.0)
        wait_for(lambda: dev.latest() is not None, 2.0)
        s = dev.latest()
        res["frame_shape"] = list(s.left.shape) if s is not None else None
        # The right camera loses 2 packets in 1000 at random: over a fixed second or two that is
        # only a few losses expected, and now and then none came (resent_packets was 0: the
        # flaky failure). Wait for the first loss to show in health (the driver polls the
        # stream statistics every 0.5 s) instead of sampling at a fixed moment.
        t_loss = time.monotonic()
        wait_for(lambda: (dev.counters.get("resent_packets", 0) +
                          dev.counters.get("missing_packets", 0)) > 0 and
                 dev.counters.get("dropped_frames", 0) > 0, 20.0)
        res["loss_seen_after_s"] = round(time.monotonic() - t_loss, 2)
        # The same for the pairs: the right camera's losses drop some of its frames (none
        # resent), so the pairs made by a fixed moment vary (8-19 in four runs of ~2 s at 1500-
        # byte packets; 4 once in CI, the flaky failure of the twentieth session). Wait for
        # five pairs to have come through instead of sampling at once.
        t_pairs = time.monotonic()
        wait_for(lambda: dev.counters.get("pairs", 0) >= 5, 20.0)
        res["pairs_seen_after_s"] = round(time.monotonic() - t_pairs, 2)
        c = dev.counters
        res.update(pairs=c.get("pairs", 0), unmatched=c.get("unmatched", 0),
                   resent_packets=c.get("resent_packets", 0) + c.get("missing_packets", 0),
                   selftest=list(dev.selftest()))
        # each stream asked the kernel for a frame's worth of receive buffer (Aravis's AUTO)
        res["socket_buffer"] = [c.stream.get_property("socket-buffer").value_nick
                                for c in dev.cams if c.stream is not None]
        res["clear_before_kill"] = wait_for(lambda: rig.state == "CLEAR", 5.0)
        if not res["clear_before_kill"]:                # why not: what the daemon said
            res["states_before_kill"] = sorted({(c[1], " ".join(c[2])[:160])
                                                for c in list(rig.cycles)[-30:]})
            res["driver_trace_before_kill"] = [(round(t, 2), w) for t, w in list(trace)[-20:]]
        t_kill = rig.now()
        left.kill()
        left.wait()
        wait_for(lambda: rig.cycles_until(t_kill, "STOP") is not None, 3.0)
        res["stop_cycles_after_kill"] = rig.cycles_until(t_kill, "STOP")
        # from the moment the first missing pair was due (the newest pair + one 0.1 s period)
        res["stop_cycles_after_due"] = rig.silence_stop_cycles("stereo", 0.1, t_kill)
        res["stop_reason"] = " ".join(next((c[2] for c in list(rig.cycles)
                                            if c[0] >= t_kill and c[1] == "STOP"), []))
        time.sleep(1.0)
        left = cam("127.0.0.1", "GV01")
        t_back = rig.now()
        res["clear_after_restart"] = wait_for(
            lambda: rig.cycles_until(t_back, "CLEAR") is not None, 15.0)
        res["reconnects"] = dev.counters.get("reconnects", 0)
        if not res["clear_after_restart"]:      # why not: the reasons the daemon gave since
            after = [c for c in list(rig.cycles) if c[0] >= t_back]
            res["states_after_restart"] = sorted({(c[1], " ".join(c[2])[:160])
                                                  for c in after[-30:]})
            t0 = t_back / 1e9
            res["driver_trace"] = [(round(t - t0, 2), w) for t, w in list(trace)[-40:]]
        res["counters"] = dict(dev.counters)
    finally:
        if rig:
            rig.close()
        laser.stop()
        for p in (left, right):
            p.kill()
    print(json.dumps(res), flush=True)
    return 0


if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[1] == "--child":
    sys.exit(_child(sys.argv[2]))


def test_a_wall_clock_step_between_arrival_and_take_drops_the_frame_not_stamps_it_old():
    """Aravis stamps a buffer's arrival on the wall clock. The hour-long soak stepped the wall
    clock +400 days between a buffer's arrival and the driver taking it: the frame was read as
    34 560 000 s old and the box stopped for 'stereo: stale'. A step either way now drops that
    one frame; an ordinary age (a few ms in the queue) is kept."""
    from drivers.aravis_stereo import MAX_FRAME_AGE_NS, frame_age_ns
    t = 1_800_000_000 * 10**9
    assert frame_age_ns(t + 7_000_000, t) == 7_000_000
    assert frame_age_ns(t, t + 500_000) == 0                  # sub-ms slew: no step
    assert frame_age_ns(t + 400 * 86400 * 10**9, t) is None   # stepped forwards
    assert frame_age_ns(t - 3600 * 10**9, t) is None          # stepped back
    assert frame_age_ns(t + MAX_FRAME_AGE_NS + 1, t) is None


def test_a_closed_camera_is_let_go_by_the_acquisition_thread_after_its_handler_is_off():
    """The soak's daemon died (SIGTRAP, "g_system_thread_wait: Resource deadlock avoided") after
    a GigE unplug: the last reference to the closed ArvCamera went in Aravis's own heartbeat
    thread (the control-lost callback's arguments), whose finalisation joined that thread from
    itself. close() now disconnects the handler and keeps the camera; reap() lets it go
    RELEASE_AFTER_S later, from the acquisition thread. (The whole path against the fake GigE
    camera, unplugged and back, is test_fake_gige_pair_through_the_daemon.)"""
    import gc
    import weakref
    from drivers.aravis_stereo import _Cam

    class Obj:                         # stands for a GObject: weakly referencable
        pass

    class Dev(Obj):
        def __init__(self):
            self.handlers = {}

        def disconnect(self, hid):
            del self.handlers[hid]

    class Cam(Obj):
        stopped = False

        def stop_acquisition(self):
            self.stopped = True

    c = _Cam(None, "127.0.0.2", "right")
    cam, dev = Cam(), Dev()
    dev.handlers[7] = lambda *_: c.lost.set()
    c.cam, c.stream, c.dev, c.handler = cam, Obj(), dev, 7
    ref = weakref.ref(cam)
    c.close()
    assert cam.stopped and dev.handlers == {} and c.cam is None and c.dev is None
    del cam, dev
    gc.collect()
    assert ref() is not None                    # held: not let go wherever a ref drops
    t_closed = c.graveyard[0][0]                # (the clock given, not read: a loaded host
    # took longer than RELEASE_AFTER_S between close() and the first reap())
    assert c.reap(now=t_closed + 0.1) == 0 and ref() is not None  # not before RELEASE_AFTER_S
    assert c.reap(now=t_closed + c.RELEASE_AFTER_S + 0.1) == 1
    assert REAPER.wait_idle(5.0)
    gc.collect()
    assert ref() is None and c.graveyard == []


def test_letting_a_camera_go_never_blocks_the_acquisition_thread():
    """Finalising a closed ArvCamera joins Aravis's threads: 5 s a camera here. reap() ran it in
    the acquisition thread, which then took no frames from the cameras it had just reconnected
    for 10 s (the replug check of test_fake_gige_pair_through_the_daemon failed now and then
    inside the full suite: its trace showed 'reap left -> 1 in 5.03 s', 'reap right -> 1 in
    5.03 s' right after the reconnect). reap() now hands the camera to the reaper thread."""
    import gc
    from drivers.aravis_stereo import _Cam

    finalised = []

    class SlowCam:                     # stands for an ArvCamera whose finalisation is slow
        def stop_acquisition(self):
            pass

        def __del__(self):
            time.sleep(1.0)
            finalised.append(threading.current_thread().name)

    c = _Cam(None, "127.0.0.1", "left")
    c.cam = SlowCam()
    c.close()
    gc.collect()
    t0 = time.monotonic()
    assert c.reap(force=True) == 1
    took = time.monotonic() - t0
    assert took < 0.5, f"reap() blocked {took:.2f} s"
    assert REAPER.wait_idle(10.0)
    assert finalised == ["aravis-reaper"]
