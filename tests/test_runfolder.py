"""Run-folder reader/writer (docs/run-format.md) and the replay devices."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from hal import (DepthCalibration, DepthFrame, GateOutput, GateState, Health, LaserGeometry,
                 LaserScan, ManualClock, Mount, PinholeCalibration, RunFormatError,
                 StereoCalibration, StereoFrame, VehicleState)
from drivers.runfolder import RunReader, RunWriter, scored_zone_for
from drivers.replay import (ReplayDepthCamera, ReplayLaser, ReplayStereoCamera,
                            ReplayVehicleLink, RunPlayer, replay_devices)

MOUNT = "mount = { x_m = 1.3, y_m = 0.0, z_m = 0.7, roll_deg = 0.0, pitch_deg = 0.0, yaw_deg = 0.0 }"
LASER_TOML = f"""
[laser]
angle_min_deg = -2.0
angle_step_deg = 1.0
beams = 5
range_max_m = 50.0
{MOUNT}
"""


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip())
    return path


def minimal_run(root: Path) -> Path:
    """Only [run] + laser, frames.csv with only `index`, written by hand as anyone could."""
    run = root / "minimal"
    write(run / "run.toml", '[run]\nname = "minimal"\nrate_hz = 5\n' + LASER_TOML)
    write(run / "frames.csv", "index\n0\n1\n2\n")
    write(run / "laser/000000.csv", "1.5\n\n3.25\n4\n5\n")
    write(run / "laser/000001.csv", "1\n2\n3\n4\n\n")          # last beam: no return
    # 000002 laser missing: a dropped frame
    return run


def full_run(root: Path) -> Path:
    """Everything in the contract, written by hand (images via cv2 as any tool would)."""
    run = root / "full"
    write(run / "run.toml", """
        [run]
        name = "full-01"
        rate_hz = 10
        reference_point = "rear-axle"
        scored_zone = { x_min_m = 2.5, x_max_m = 15.0 }
        project_key = "kept"

        [stereo]
        width = 8
        height = 6
        fx = 10.0
        fy = 10.0
        cx = 4.0
        cy = 3.0
        baseline_m = 0.75
        mount = { x_m = 1.2, y_m = 0.0, z_m = 1.55, roll_deg = 0.0, pitch_deg = 15.0, yaw_deg = 0.0 }

        [rgbd]
        width = 4
        height = 3
        fx = 5.0
        fy = 5.0
        cx = 2.0
        cy = 1.5
        depth_unit_m = 0.001
        mount = { x_m = 1.0, y_m = 0.0, z_m = 0.9, roll_deg = 0.0, pitch_deg = 10.0, yaw_deg = 0.0 }

        [laser]
        angle_min_deg = -2.0
        angle_step_deg = 1.0
        beams = 5
        range_max_m = 50.0
        mount = { x_m = 1.3, y_m = 0.0, z_m = 0.7, roll_deg = 0.0, pitch_deg = 0.0, yaw_deg = 0.0 }

        [thermal]
        note = "a project extension table"
        """)
    write(run / "frames.csv", """
        index,stamp_ns,speed_mps,yaw_rate_radps,roll_rad,pitch_rad,yaw_rad,illumination,gps_fix
        0,1000000000,1.5,0.01,0.0,0.02,0.3,day,3
        1,1100000000,1.6,,,,,night-strobe,3
        """)
    rng = np.random.default_rng(1)
    for i in range(2):
        for side in ("left", "right"):
            (run / "stereo" / side).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(run / f"stereo/{side}/{i:06d}.png"),
                        rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
        (run / "rgbd/color").mkdir(parents=True, exist_ok=True)
        (run / "rgbd/depth").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(run / f"rgbd/color/{i:06d}.png"),
                    rng.integers(0, 256, (3, 4, 3), dtype=np.uint8))
        cv2.imwrite(str(run / f"rgbd/depth/{i:06d}.png"),
                    np.array([[0, 1000, 2500, 65535]] * 3, dtype=np.uint16))
        write(run / f"laser/{i:06d}.csv", "1\n2\n3\n4\n5\n")
    write(run / "truth/000000.json", """
        {"obstacles": [
          {"id": "p1", "class": "person", "x_m": 9.5, "y_m": -0.4, "z_m": 0.0,
           "length_m": 0.4, "width_m": 0.5, "height_m": 1.8, "yaw_deg": 0.0, "note": "x"}
        ]}""")
    return run


# ---- reading folders written by hand ------------------------------------------------------------
def test_minimal_run(tmp_path):
    r = RunReader(minimal_run(tmp_path))
    assert len(r) == 3
    assert r.info.name == "minimal" and r.info.rate_hz == 5.0
    assert r.info.sensors == ("laser",) and r.info.stereo is None and r.info.rgbd is None
    assert r.info.scored_zone is None and r.info.reference_point is None
    assert [f.stamp_ns for f in r.frames] == [0, 200_000_000, 400_000_000]   # index / rate
    assert r.stereo(0) is None and r.rgbd(0) is None and r.truth(0) is None
    s0 = r.laser(0)
    assert s0.ranges_m.dtype == np.float32 and s0.ranges_m.shape == (5,)
    assert s0.ranges_m[0] == 1.5 and math.isnan(s0.ranges_m[1]) and s0.ranges_m[2] == 3.25
    assert math.isnan(r.laser(1).ranges_m[4]) and r.laser(1).ranges_m[3] == 4
    assert r.laser(2) is None                      # dropped frame: nothing, not an error
    assert s0.stamp_ns == 0 and s0.seq == 0 and s0.geometry.beams == 5
    v = r.vehicle(1)
    assert (v.speed_mps, v.yaw_rate_radps, v.roll_rad, v.pitch_rad, v.yaw_rad) == (0,) * 5
    assert v.stamp_ns == 200_000_000 and v.seq == 1
    with pytest.raises(RunFormatError, match="no camera"):
        scored_zone_for(r.info)


def test_minimal_run_defaults_name_and_rate(tmp_path):
    run = tmp_path / "bare"
    write(run / "run.toml", LASER_TOML)
    write(run / "frames.csv", "index\n3\n")
    r = RunReader(run)
    assert r.info.name == "bare" and r.info.rate_hz == 10.0
    assert r.frames[0].index == 3 and r.frames[0].stamp_ns == 300_000_000


def test_full_run(tmp_path):
    run = full_run(tmp_path)
    r = RunReader(run)
    info = r.info
    assert info.name == "full-01" and info.reference_point == "rear-axle"
    assert info.scored_zone == (2.5, 15.0) and scored_zone_for(info) == (2.5, 15.0)
    assert info.extra["run"]["project_key"] == "kept" and "thermal" in info.extra
    assert info.stereo.baseline_m == 0.75 and info.stereo.mount.pitch_deg == 15.0
    assert info.stereo.camera.width == 8 and info.rgbd.depth_unit_m == 0.001
    f0, f1 = r.frames
    assert f0.stamp_ns == 1_000_000_000 and f0.speed_mps == 1.5 and f0.yaw_rad == 0.3
    assert f0.extra == {"gps_fix": "3"} and f0.illumination == "day"
    assert f1.yaw_rate_radps is None and f1.illumination == "night-strobe"
    assert r.vehicle(1).yaw_rate_radps == 0.0 and r.vehicle(1).speed_mps == 1.6
    s = r.stereo(1)
    assert s.left.shape == (6, 8, 3) and s.left.dtype == np.uint8
    assert s.illumination == "night-strobe" and s.stamp_ns == 1_100_000_000 and s.seq == 1
    assert np.array_equal(s.left, cv2.imread(str(run / "stereo/left/000001.png")))
    d = r.rgbd(0)
    assert d.depth_m.dtype == np.float32
    np.testing.assert_allclose(d.depth_m[0], [0.0, 1.0, 2.5, 65.535], rtol=1e-6)
    assert d.depth_m[0, 0] == 0.0
    t = r.truth(0)
    assert t[0]["id"] == "p1" and t[0]["class"] == "person" and t[0]["x_m"] == 9.5
    assert t[0]["note"] == "x"
    assert r.truth(1) is None


def test_scored_zone_defaults(tmp_path):
    run = full_run(tmp_path)
    toml = (run / "run.toml").read_text().replace(
        "scored_zone = { x_min_m = 2.5, x_max_m = 15.0 }", "")
    (run / "run.toml").write_text(toml)
    assert scored_zone_for(RunReader(run).info) == (2.0, 20.0)
    start = toml.index("[stereo]")
    (run / "run.toml").write_text(toml[:start] + toml[toml.index("[rgbd]"):])
    info = RunReader(run).info
    assert info.stereo is None and scored_zone_for(info) == (1.5, 6.0)


# ---- round trip ----------------------------------------------------------------------------------
def _calibs():
    st = StereoCalibration(PinholeCalibration(64, 48, 50.0, 50.0, 32.0, 24.0), 0.5,
                           Mount(1.2, 0.0, 1.5, 0.0, 15.0, 0.0))
    rg = DepthCalibration(PinholeCalibration(32, 24, 30.0, 30.0, 16.0, 12.0),
                          Mount(1.0, 0.1, 0.9, 0.0, 10.0, 2.0), depth_unit_m=0.001)
    la = LaserGeometry(-90.0, 0.5, 361, 40.0, Mount(1.3, 0.0, 0.7))
    return st, rg, la


def test_round_trip(tmp_path):
    st, rg, la = _calibs()
    rng = np.random.default_rng(7)
    written = []
    with RunWriter(tmp_path / "rt", "rt", rate_hz=10, stereo=st, rgbd=rg, laser=la,
                   extra_run={"scored_zone": {"x_min_m": 1.0, "x_max_m": 9.0}}) as w:
        for i in range(3):
            left = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
            right = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
            depth = rng.uniform(0.3, 8.0, (24, 32)).astype(np.float32)
            depth[0, :5] = 0.0
            depth[1, 0] = np.nan
            ranges = rng.uniform(0.1, 39.0, 361).astype(np.float32)
            ranges[::10] = np.nan
            veh = VehicleState(0, i, speed_mps=1.25 * i, yaw_rate_radps=-0.1, roll_rad=0.01,
                               pitch_rad=-0.02, yaw_rad=3.0)
            truth = [{"id": "c1", "class": "cow", "x_m": 7.0, "y_m": 0.5, "length_m": 2.0,
                      "width_m": 0.8, "yaw_deg": 30.0}] if i != 1 else None
            w.write_frame(i, 5_000_000_000 + i * 100_000_000, veh,
                          stereo=StereoFrame(0, i, left, right, st),
                          rgbd=DepthFrame(0, i, left[:24, :32].copy(), depth, rg),
                          laser=LaserScan(0, i, ranges, la), truth=truth,
                          illumination="night-strobe" if i == 2 else None,
                          extra_columns={"lap": i} if i == 2 else None)
            written.append((left, right, depth, ranges, veh, truth))
    r = RunReader(tmp_path / "rt")
    assert r.info.stereo == st and r.info.rgbd == rg and r.info.laser == la
    assert r.info.scored_zone == (1.0, 9.0) and len(r) == 3
    for i, (left, right, depth, ranges, veh, truth) in enumerate(written):
        s = r.stereo(i)
        assert np.array_equal(s.left, left) and np.array_equal(s.right, right)
        d = r.rgbd(i)
        assert np.array_equal(d.color, left[:24, :32])
        expect = np.nan_to_num(depth, nan=0.0)
        assert np.all(np.abs(d.depth_m - expect) <= 0.0005 + 1e-6)    # exact to the unit
        assert d.depth_m[0, 0] == 0.0 and d.depth_m[1, 0] == 0.0
        got = r.laser(i).ranges_m
        assert np.array_equal(np.isnan(got), np.isnan(ranges))
        assert np.array_equal(got[~np.isnan(got)], ranges[~np.isnan(ranges)])   # bit-exact
        v = r.vehicle(i)
        assert (v.speed_mps, v.yaw_rate_radps, v.roll_rad, v.pitch_rad, v.yaw_rad) == \
               (veh.speed_mps, veh.yaw_rate_radps, veh.roll_rad, veh.pitch_rad, veh.yaw_rad)
        assert v.stamp_ns == 5_000_000_000 + i * 100_000_000
        assert (r.truth(i) is None) == (truth is None)
    assert r.truth(0)[0]["yaw_deg"] == 30.0
    assert r.frames[2].extra == {"lap": "2"} and r.frames[0].extra == {"lap": ""}
    assert r.stereo(2).illumination == "night-strobe"


def test_writer_refuses_non_empty_folder(tmp_path):
    _, _, la = _calibs()
    keep = tmp_path / "old" / "notes.txt"
    write(keep, "precious")
    with pytest.raises(RunFormatError, match="not empty"):
        RunWriter(tmp_path / "old", "x", laser=la)
    with RunWriter(tmp_path / "old", "x", laser=la, overwrite=True) as w:
        w.write_frame(0, 0)
    assert keep.read_text() == "precious"           # only run-format entries are replaced
    assert len(RunReader(tmp_path / "old")) == 1


def test_writer_flushes_each_row(tmp_path):
    _, _, la = _calibs()
    w = RunWriter(tmp_path / "f", "f", laser=la)
    w.write_frame(0, 0, laser=LaserScan(0, 0, np.ones(361, np.float32), la))
    r = RunReader(tmp_path / "f")                   # readable while still open
    assert len(r) == 1 and r.laser(0).ranges_m[0] == 1.0
    with pytest.raises(ValueError, match="length_m"):        # the writer writes only valid truth
        w.write_frame(1, 1, truth=[{"id": "a", "class": "cow", "x_m": 1, "y_m": 0,
                                    "width_m": 1}])
    with pytest.raises(ValueError, match="361"):
        w.write_frame(1, 1, laser=LaserScan(0, 1, np.ones(5, np.float32), la))
    w.close()
    assert len(RunReader(tmp_path / "f")) == 1                # nothing half-written


# ---- errors name the file -------------------------------------------------------------------------
def _err(path) -> str:
    with pytest.raises(RunFormatError) as ei:
        RunReader(path)
    return str(ei.value)


def test_error_missing_run_toml(tmp_path):
    write(tmp_path / "r/frames.csv", "index\n0\n")
    assert "run.toml" in _err(tmp_path / "r") and "missing" in _err(tmp_path / "r")


def test_error_not_a_folder(tmp_path):
    assert "no such directory" in _err(tmp_path / "nope")


def test_error_bad_toml(tmp_path):
    write(tmp_path / "r/run.toml", "[run\n")
    write(tmp_path / "r/frames.csv", "index\n0\n")
    assert "run.toml" in _err(tmp_path / "r") and "TOML" in _err(tmp_path / "r")


def test_error_missing_index_column(tmp_path):
    run = minimal_run(tmp_path)
    write(run / "frames.csv", "stamp_ns\n0\n")
    msg = _err(run)
    assert "frames.csv" in msg and "'index'" in msg


def test_error_missing_frames_csv(tmp_path):
    run = minimal_run(tmp_path)
    (run / "frames.csv").unlink()
    assert "frames.csv" in _err(run)


@pytest.mark.parametrize("body, words", [
    ("index\nx\n", ["line 2", "'index'"]),
    ("index,speed_mps\n0,fast\n", ["line 2", "'speed_mps'"]),
    ("index,illumination\n0,dusk\n", ["'illumination'"]),
    ("index\n0\n0\n", ["repeats"]),
    ("index,stamp_ns\n0,10\n1,5\n", ["backwards"]),
    ("index,stamp_ns\n0\n", ["line 2", "fields"]),
])
def test_error_bad_frames_rows(tmp_path, body, words):
    run = minimal_run(tmp_path)
    write(run / "frames.csv", body)
    msg = _err(run)
    assert "frames.csv" in msg
    for w in words:
        assert w in msg


def test_error_sensor_table_without_mount(tmp_path):
    run = minimal_run(tmp_path)
    write(run / "run.toml", LASER_TOML.replace(MOUNT, ""))
    msg = _err(run)
    assert "run.toml" in msg and "[laser] mount" in msg


@pytest.mark.parametrize("old, new, words", [
    ("beams = 5", "", ["[laser] beams", "missing"]),
    ("beams = 5", "beams = 2.5", ["[laser] beams", "integer"]),
    ("range_max_m = 50.0", 'range_max_m = "far"', ["[laser] range_max_m"]),
    ("pitch_deg = 0.0", "pitch = 0.0", ["[laser] mount", "unknown", "pitch"]),
    ("x_m = 1.3, ", "", ["[laser.mount] x_m", "missing"]),
])
def test_error_bad_sensor_keys(tmp_path, old, new, words):
    run = minimal_run(tmp_path)
    write(run / "run.toml", LASER_TOML.replace(old, new, 1))
    msg = _err(run)
    assert "run.toml" in msg
    for w in words:
        assert w in msg


def test_error_bad_image_size(tmp_path):
    run = full_run(tmp_path)
    cv2.imwrite(str(run / "stereo/right/000001.png"), np.zeros((6, 9, 3), np.uint8))
    r = RunReader(run)
    with pytest.raises(RunFormatError, match=r"stereo/right/000001\.png.*9x6.*8x6"):
        r.stereo(1)
    assert r.stereo(0) is not None


def test_error_corrupt_png(tmp_path):
    run = full_run(tmp_path)
    (run / "rgbd/depth/000000.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    r = RunReader(run)
    with pytest.raises(RunFormatError, match=r"rgbd/depth/000000\.png"):
        r.rgbd(0)


def test_error_depth_not_16_bit(tmp_path):
    run = full_run(tmp_path)
    cv2.imwrite(str(run / "rgbd/depth/000001.png"), np.zeros((3, 4), np.uint8))
    with pytest.raises(RunFormatError, match=r"000001\.png.*16-bit"):
        RunReader(run).rgbd(1)


def test_missing_image_is_a_dropped_frame(tmp_path):
    run = full_run(tmp_path)
    (run / "stereo/left/000001.png").unlink()
    (run / "rgbd/color/000000.png").unlink()
    r = RunReader(run)
    assert r.stereo(1) is None and r.stereo(0) is not None
    assert r.rgbd(0) is None and r.rgbd(1) is not None


@pytest.mark.parametrize("body, words", [
    ("1\n2\n3\n", ["3 lines", "5 beams"]),
    ("1\n2\nfar\n4\n5\n", ["line 3"]),
    ("1\n2\n-3\n4\n5\n", ["negative"]),
])
def test_error_bad_laser_file(tmp_path, body, words):
    run = minimal_run(tmp_path)
    write(run / "laser/000000.csv", body)
    with pytest.raises(RunFormatError) as ei:
        RunReader(run).laser(0)
    assert "laser/000000.csv" in str(ei.value)
    for w in words:
        assert w in str(ei.value)


@pytest.mark.parametrize("body, words", [
    ("{", ["JSON"]),
    ('[{"id": "a"}]', ["'obstacles'"]),
    ('{"obstacles": [{"id": "a", "class": "person", "x_m": 1, "y_m": 0}]}', ["length_m"]),
    ('{"obstacles": [{"id": "a", "class": "person", "x_m": "1", "y_m": 0, "length_m": 1,'
     ' "width_m": 1}]}', ["'x_m'"]),
])
def test_error_bad_truth(tmp_path, body, words):
    run = minimal_run(tmp_path)
    write(run / "truth/000001.json", body)
    with pytest.raises(RunFormatError) as ei:
        RunReader(run).truth(1)
    assert "truth/000001.json" in str(ei.value)
    for w in words:
        assert w in str(ei.value)


def test_empty_truth_is_scored_empty(tmp_path):
    run = minimal_run(tmp_path)
    write(run / "truth/000000.json", '{"obstacles": []}')
    r = RunReader(run)
    assert r.truth(0) == [] and r.truth(1) is None


# ---- replay -------------------------------------------------------------------------------------
def test_replay_lock_step(tmp_path):
    run = minimal_run(tmp_path)           # 5 Hz: frames at offsets 0, 200, 400 ms; 2 has no file
    reader = RunReader(run)
    clock = ManualClock(start_ns=50_000_000_000)
    player = RunPlayer(reader, clock, realtime=False)
    laser = ReplayLaser(player, timeout_s=0.3)
    link = ReplayVehicleLink(player, timeout_s=0.3)
    laser.open(), link.open()
    t0 = clock.now_ns()
    assert laser.latest() is None
    laser.service(clock.now_ns()), link.service(clock.now_ns())
    s = laser.latest()
    assert s is not None and s.stamp_ns == t0 and s.seq == 0 and s.ranges_m[0] == 1.5
    assert link.latest().stamp_ns == t0
    clock.advance(150_000_000)            # frame 1 not yet due
    laser.service(clock.now_ns())
    assert laser.latest().seq == 0
    clock.advance(50_000_000)             # 200 ms: frame 1 due
    laser.service(clock.now_ns()), link.service(clock.now_ns())
    s = laser.latest()
    assert s.seq == 1 and s.stamp_ns == t0 + 200_000_000 and math.isnan(s.ranges_m[4])
    assert link.latest().seq == 1
    clock.advance(200_000_000)            # frame 2 due, but its laser file is missing
    laser.service(clock.now_ns()), link.service(clock.now_ns())
    assert laser.latest().seq == 1 and link.latest().seq == 2
    assert not player.finished(clock.now_ns())
    clock.advance(199_000_000)
    assert not player.finished(clock.now_ns())
    clock.advance(1_000_000)              # one frame period after the last frame: over
    assert player.finished(clock.now_ns())
    clock.advance(200_000_000)
    laser.service(clock.now_ns()), link.service(clock.now_ns())
    assert laser.latest() is None and link.latest() is None          # stale: the gate stops
    assert laser.health().state is Health.NO_DATA
    assert link.send(GateOutput(0, 0, GateState.STOP, "test")) is True
    assert len(link.sent) == 1 and link.sent[0].reason == "test"
    laser.close(), link.close()


def test_replay_skips_to_newest_and_loops(tmp_path):
    run = full_run(tmp_path)              # 10 Hz, stamps 1.0 s and 1.1 s
    reader = RunReader(run)
    clock = ManualClock(start_ns=7)
    player = RunPlayer(reader, clock, realtime=False, loop=True)
    cams = replay_devices(player)
    assert set(cams) == {"stereo", "rgbd", "laser", "link"}
    stereo = cams["stereo"]
    assert isinstance(stereo, ReplayStereoCamera) and isinstance(cams["rgbd"], ReplayDepthCamera)
    assert stereo.calibration == reader.info.stereo
    stereo.service(clock.now_ns())
    assert stereo.latest().seq == 0 and stereo.latest().stamp_ns == 7
    clock.advance(350_000_000)            # period 0.2 s: second lap, frame 1 (offset 0.1)
    stereo.service(clock.now_ns())
    f = stereo.latest()
    assert f is not None and f.stamp_ns == 7 + 300_000_000
    assert not player.finished(clock.now_ns())


def test_replay_refuses_missing_sensor(tmp_path):
    reader = RunReader(minimal_run(tmp_path))
    player = RunPlayer(reader, ManualClock(), realtime=False)
    with pytest.raises(Exception, match="stereo"):
        ReplayStereoCamera(player)


def test_replay_realtime_thread(tmp_path):
    reader = RunReader(minimal_run(tmp_path))
    clock = ManualClock()
    player = RunPlayer(reader, clock, realtime=True)
    laser = ReplayLaser(player, timeout_s=0.3)
    laser.open()
    laser.service(clock.now_ns())         # realtime: the loop's service() does no I/O
    assert laser.newest() is None
    laser.start_acquisition()
    try:
        import time
        deadline = time.monotonic() + 2.0
        while laser.newest() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert laser.newest().seq == 0
        clock.advance(200_000_000)
        deadline = time.monotonic() + 2.0
        while laser.newest().seq != 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert laser.newest().seq == 1
    finally:
        laser.close()


# ---- the contract's own example, on disk (tests/data/contract-example) ----------------------------
DATA = Path(__file__).parent / "data" / "contract-example"


def test_contract_example_folder():
    """run.toml and truth copied verbatim from docs/run-format.md; no images (dropped frames),
    frame 1 has no laser file and no truth."""
    r = RunReader(DATA)
    info = r.info
    assert info.name == "stubble-day-01" and info.rate_hz == 10.0
    assert info.sensors == ("stereo", "rgbd", "laser")
    assert info.stereo.camera.width == 1280 and info.stereo.mount.pitch_deg == 15.0
    assert info.rgbd.depth_unit_m == 0.001 and info.rgbd.mount.x_m == 1.0
    assert info.laser.beams == 541 and info.laser.angle_min_deg == -135.0
    assert scored_zone_for(info) == (2.0, 20.0)
    assert [f.stamp_ns for f in r.frames] == [123_000_000_000, 123_100_000_000]
    assert r.stereo(0) is None and r.rgbd(0) is None
    scan = r.laser(0)
    assert scan.ranges_m.shape == (541,) and np.count_nonzero(np.isfinite(scan.ranges_m)) == 7
    assert r.laser(1) is None
    assert r.truth(0)[0]["id"] == "p1" and r.truth(1) is None
