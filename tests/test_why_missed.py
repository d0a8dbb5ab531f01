"""tools/why_missed.py: a campaign drive replayed, per cycle what the stereo-novelty pipeline had
on one obstacle (docs/front-end.md "The blind corners")."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TOOL = ROOT / "tools" / "why_missed.py"


def _run(*args):
    return subprocess.run([sys.executable, str(TOOL), *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def test_a_window_of_a_training_drive_prints_a_line_per_cycle():
    # the pair at a tenth of 1280x1024, not the tool's half: the lines checked are the same
    # (at 0.5 the very same text), for 2 CPU-s, not 3
    p = _run("stubble-coverage", "1", "c1", "0.5", "1.0", "--stereo-scale", "0.1")
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    assert lines[0].startswith("stubble-coverage 1: c1 person-crouching")
    rows = [x for x in lines if x.startswith("t=")]
    assert len(rows) == 6                                  # 0.5, 0.6 ... 1.0 s
    for r in rows:
        assert any(f" {v} " in r for v in ("pair", "left", "right", "none"))
        assert "ahead" in r and "novel" in r
        assert "all h " in r and "(evidence " in r       # every near point's heights, the grid


def test_bad_requests_are_one_clear_line():
    p = _run("stubble-coverage", "1000", "c1", "1", "2")
    assert p.returncode == 2 and "training seeds only" in p.stderr and "Traceback" not in p.stderr
    p = _run("stubble-coverage", "1", "c1", "2", "1")
    assert p.returncode == 2 and "T1 must not be before T0" in p.stderr
    p = _run("stubble-coverage", "1", "c99", "0.1", "0.2")
    assert p.returncode == 2 and "no obstacle 'c99'" in p.stderr and "c1" in p.stderr


def test_an_rgbd_drive_prints_what_the_kinect_had(tmp_path):
    """The greenhouse (rgbd) drives: per cycle whether the obstacle is in the Kinect's view,
    the depth points and candidates near it, and the picture written when asked."""
    p = _run("greenhouse-coverage", "1", "g1", "0.5", "0.8", "--minutes", "3",
             "--picture", str(tmp_path))
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    assert lines[0].startswith("greenhouse-coverage 1: g1 ")
    rows = [x for x in lines if x.startswith("t=")]
    assert len(rows) == 4                                  # 0.5, 0.6, 0.7, 0.8 s
    for r in rows:
        assert any(f" {v} " in r for v in ("view", "out", "beside", "-"))
        assert "candidates" in r and "cells" in r
    assert len(list(tmp_path.glob("greenhouse-coverage-1-g1-t*.png"))) == 4


def test_kinect_view_tells_in_view_out_of_range_and_beside():
    sys.path.insert(0, str(ROOT / "tools"))
    sys.path.insert(0, str(ROOT))
    import numpy as np
    from why_missed import kinect_view

    from drivers.sim.field import depth_calibration
    cal = depth_calibration()                              # the simulated Kinect
    assert kinect_view(cal, np.array([0.0, 0.0, 3.0])) == "view"
    assert kinect_view(cal, np.array([0.0, 0.0, 9.0])) == "out"          # beyond the range
    assert kinect_view(cal, np.array([5.0, 0.0, 1.0])) == "out"          # off the image
    assert kinect_view(cal, np.array([1.0, 0.0, -0.2])) == "beside"
