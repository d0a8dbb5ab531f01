"""Recordings survive what happens to them (issue #16): a torn last line of frames.csv, deleted
and corrupt images, the end of a replay, the incident disk budget."""
import logging
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.evaluation import evaluate_run, format_table
from drivers.runfolder import RunReader
from drivers.sim.record import write_sim_run
from hal.errors import RunFormatError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def laser_run(tmp_path_factory):
    return write_sim_run("stubble-day", 12, tmp_path_factory.mktemp("l") / "run",
                         sensors=("laser",))


@pytest.fixture(scope="module")
def rgbd_run(tmp_path_factory):
    return write_sim_run("greenhouse", 14, tmp_path_factory.mktemp("g") / "run",
                         sensors=("rgbd",))


def copy_run(src: Path, dst: Path) -> Path:
    import shutil
    shutil.copytree(src, dst)
    return dst


# ---- a torn last line ----------------------------------------------------------------------
@pytest.mark.parametrize("tail", ["12,1200000", "12,12000000", "12,1200000000,0.5,0.0,0.0,0.",
                                  "1"])
def test_torn_last_line_is_dropped_with_a_warning(laser_run, tmp_path, caplog, tail):
    run = copy_run(laser_run, tmp_path / "r")
    csv = run / "frames.csv"
    csv.write_text(csv.read_text() + tail)          # a power cut in the middle of a row
    with caplog.at_level(logging.WARNING, logger="fieldguard.runfolder"):
        r = RunReader(run)
    assert len(r) == 12
    assert len(r.warnings) == 1 and "cut short" in r.warnings[0] and "line 14" in r.warnings[0]
    assert any("cut short" in m for m in caplog.messages)
    res = evaluate_run(run, "laser")
    assert res["frames_total"] == 12 and res["run_warnings"] == r.warnings
    assert "warning: " in format_table(res) and "cut short" in format_table(res)


def test_a_bad_line_that_is_not_the_torn_end_is_still_an_error(laser_run, tmp_path):
    run = copy_run(laser_run, tmp_path / "r")
    csv = run / "frames.csv"
    lines = csv.read_text().splitlines(keepends=True)
    lines[3] = "3,oops\n"
    csv.write_text("".join(lines))
    with pytest.raises(RunFormatError, match="line 4"):
        RunReader(run)
    # a whole last line (it ends in a newline) that is wrong is not a torn write either
    csv.write_text(laser_run.joinpath("frames.csv").read_text() + "12,x\n")
    with pytest.raises(RunFormatError, match="line 14"):
        RunReader(run)


# ---- missing and corrupt frames ------------------------------------------------------------
def test_missing_and_corrupt_frames_are_counted_named_and_not_scored(rgbd_run, tmp_path):
    run = copy_run(rgbd_run, tmp_path / "r")
    (run / "rgbd/color/000003.png").unlink()                        # deleted
    (run / "rgbd/depth/000007.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")  # corrupt
    (run / "rgbd/color/000009.png").write_bytes(b"")               # truncated to nothing
    res = evaluate_run(run, "rgbd")
    assert res["frames_total"] == 14
    assert res["frames"] == 11                      # scored: the 11 whole frames only
    assert res["frames_missing"] == 1 and res["frames_missing_indices"] == [3]
    assert res["frames_corrupt"] == 2 and res["frames_corrupt_indices"] == [7, 9]
    assert "000007.png" in res["frames_corrupt_errors"][0]
    table = format_table(res)
    assert "scored frames 11/14" in table
    assert "not scored: 1 frame(s) with a sensor file missing (index 3)" in table
    assert "not scored: 2 frame(s) with a corrupt file (index 7, 9)" in table


def test_eval_command_survives_a_corrupt_png(rgbd_run, tmp_path):
    run = copy_run(rgbd_run, tmp_path / "r")
    (run / "rgbd/depth/000002.png").write_bytes(b"garbage")
    r = subprocess.run([sys.executable, "-m", "appliance.cli", "eval", str(run), "--pipeline",
                        "rgbd"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "scored frames 13/14" in r.stdout and "corrupt file (index 2)" in r.stdout


# ---- the end of a replay -------------------------------------------------------------------
def test_replay_ends_with_end_of_recording(laser_run, tmp_path):
    r = subprocess.run([sys.executable, "-m", "appliance.cli", "replay", str(laser_run),
                        "--fast", "--print-every", "0.5", "--socket", str(tmp_path / "s.sock")],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("[")]
    assert "laser: end of recording (stubble-day-0)" in lines[-1], r.stdout
    assert "stale" not in lines[-1]
    assert "the last cycle said STOP (laser: end of recording (stubble-day-0)" in r.stdout
    assert "stops for faults" not in r.stdout


# ---- incidents: bounded on disk ------------------------------------------------------------
def test_incident_disk_budget_removes_the_oldest(tmp_path):
    from appliance.recorder import Recorder
    inc = tmp_path / "incidents"
    for k in range(5):                                  # 5 incidents of 0.4 MB each
        d = inc / f"2026120{k}-000000-stop"
        d.mkdir(parents=True)
        (d / "run.toml").write_text("[run]\n")
        (d / "blob").write_bytes(b"\0" * 400_000)
    rec = Recorder(10.0, str(inc), 1.0, incident_max=20, incident_max_mb=1.0)
    try:
        rec._prune_incidents()
    finally:
        rec.close()
    left = sorted(p.name for p in inc.iterdir())
    assert left == ["20261203-000000-stop", "20261204-000000-stop"]   # 0.8 MB <= 1 MB


def _cycles(rec, laser, states, t0_ns=10**9):
    """Feed the recorder one cycle per state, 0.1 s apart, with a fresh laser scan each."""
    from types import SimpleNamespace as NS
    from appliance.perception.base import SensorInputs
    from hal import GateState
    t = t0_ns
    for st in states:
        laser.service(t)
        inputs = SensorInputs(stamp_ns=t, laser=laser.latest(t))
        rec.on_cycle(NS(stamp_ns=t, inputs=inputs,
                        output=NS(state=GateState[st], reason="laser: bad data on the wire")))
        t += 100_000_000
    return t


def test_an_incident_that_cannot_be_written_says_so_once(tmp_path, caplog, monkeypatch):
    """The disk under the recorder fills up (the soak's disk_full): the incident's first frame
    fails. One error line for the incident, not one per remaining frame (the soak logged 20-30
    lines an incident), and the box's next incident is tried again."""
    import errno
    from appliance.recorder import Recorder
    from drivers import runfolder
    from hal import ManualClock
    from tests.fakes import HandLaser
    real = runfolder.RunWriter.write_frame
    full = {"on": True}

    def write_frame(self, *a, **kw):
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *a, **kw)
    monkeypatch.setattr(runfolder.RunWriter, "write_frame", write_frame)
    laser = HandLaser("laser", ManualClock(10**9))
    inc = tmp_path / "incidents"
    rec = Recorder(10.0, str(inc), incident_seconds=1.0)
    try:
        with caplog.at_level("ERROR", logger="fieldguard.recorder"):
            t = _cycles(rec, laser, ["CLEAR"] * 12 + ["STOP"] * 15)
            assert rec.incidents and wait_for_jobs(rec)
            errors = [r for r in caplog.records if "No space left" in r.getMessage()]
            assert len(errors) == 1, [r.getMessage() for r in caplog.records]
            assert "the rest of this incident is not recorded" in errors[0].getMessage()
            full["on"] = False                  # room again: the next incident is written
            _cycles(rec, laser, ["CLEAR"] * 12 + ["STOP"] * 15, t)
            assert wait_for_jobs(rec)
    finally:
        rec.close()
    assert len(rec.incidents) == 2
    written = [p for p in inc.iterdir() if (p / "frames.csv").exists()
               and len((p / "frames.csv").read_text().splitlines()) > 10]
    assert len(written) == 1


def test_two_incidents_never_share_a_folder(tmp_path, monkeypatch):
    """Two stops for the same reason within one second of the wall clock (or a wall clock
    stepped back onto an earlier incident's name): each incident gets its own folder, both
    complete; nothing is refused or overwritten."""
    import time as _time
    from appliance.recorder import Recorder
    from hal import ManualClock
    from tests.fakes import HandLaser
    monkeypatch.setattr(_time, "strftime", lambda fmt, *a: "20261202-120000")
    laser = HandLaser("laser", ManualClock(10**9))
    inc = tmp_path / "incidents"
    rec = Recorder(10.0, str(inc), incident_seconds=0.5)
    try:
        t = _cycles(rec, laser, ["CLEAR"] * 6 + ["STOP"] * 12)
        _cycles(rec, laser, ["CLEAR"] * 6 + ["STOP"] * 12, t)
        assert wait_for_jobs(rec)
    finally:
        rec.close()
    names = sorted(p.name for p in inc.iterdir())
    assert len(names) == 2 and names[1] == names[0] + "-2", names
    assert [i["name"] for i in rec.incidents] == names
    for n in names:
        assert (inc / n / "run.toml").exists()
        assert len((inc / n / "frames.csv").read_text().splitlines()) >= 10


def wait_for_jobs(rec, timeout=10.0):
    """Every incident job the recorder started has finished (written, or failed)."""
    import time as _time
    end = _time.monotonic() + timeout
    while _time.monotonic() < end:
        with rec._lock:
            live = list(rec._live)
        if not live and rec._q.empty():
            _time.sleep(0.3)                    # the writer's last item
            return True
        _time.sleep(0.05)
    return False
