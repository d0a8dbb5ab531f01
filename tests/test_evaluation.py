"""Scoring as docs/run-format.md "Scoring" defines it, and the evaluation runner."""
from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

import appliance.perception as perception
from appliance.evaluation import (Aggregate, FrameScore, ObstacleScore, Zone, evaluate_run,
                                  footprint_distance, format_table, score_frame, zone_for_run)
from drivers.runfolder import RunReader
from hal import ConfigError, RunFormatError

ZONE = Zone(x_min_m=2.0, x_max_m=20.0, half_fov_rad=math.radians(30), apex_x_m=1.2, apex_y_m=0.0)
P1 = {"id": "p1", "class": "person", "x_m": 9.5, "y_m": -0.4, "length_m": 0.4, "width_m": 0.5,
      "yaw_deg": 0.0}


def cells(*xy) -> np.ndarray:
    return np.array(xy, dtype=float).reshape(-1, 2)


# ---- footprint ---------------------------------------------------------------------------------
def test_footprint_distance_axis_aligned_and_rotated():
    ob = {"x_m": 10.0, "y_m": 0.0, "length_m": 2.0, "width_m": 0.4, "yaw_deg": 0.0}
    d = footprint_distance(cells((10.0, 0.0), (11.5, 0.0), (10.0, 0.6), (11.3, 0.6)), ob)
    np.testing.assert_allclose(d, [0.0, 0.5, 0.4, math.hypot(0.3, 0.4)])
    turned = dict(ob, yaw_deg=90.0)       # now 2 m along y, 0.4 m along x
    d = footprint_distance(cells((10.0, 1.4), (10.65, 0.0), (11.5, 0.0)), turned)
    np.testing.assert_allclose(d, [0.4, 0.45, 1.3], atol=1e-9)


# ---- one frame ----------------------------------------------------------------------------------
def test_detected_within_half_metre():
    s = score_frame(cells((9.5 + 0.2 + 0.45, -0.4)), [P1], ZONE)   # 0.45 m beyond the front
    (o,) = s.obstacles
    assert o.in_zone and o.detected and o.nearest_cell_m == pytest.approx(0.45)
    assert s.fp_cells == 0 and not s.false_positive


def test_not_detected_at_0_6_m_and_that_cell_is_a_false_positive():
    s = score_frame(cells((9.5 + 0.2 + 0.6, -0.4)), [P1], ZONE)
    (o,) = s.obstacles
    assert o.in_zone and not o.detected
    assert s.fp_cells == 1 and s.false_positive


def test_lateral_distance_counts_too():
    s = score_frame(cells((9.5, -0.4 - 0.25 - 0.55)), [P1], ZONE)
    assert not s.obstacles[0].detected and s.fp_cells == 1


def test_fp_cells_counted_and_cells_outside_zone_ignored():
    c = cells((9.5, -0.4),        # on the person: not FP
              (6.0, 1.0),         # in zone, far from everything: FP
              (6.0, 1.1),         # another FP
              (25.0, 0.0),        # beyond x_max: ignored
              (1.5, 0.0),         # before x_min: ignored
              (5.0, 10.0))        # outside the camera's wedge: ignored
    s = score_frame(c, [P1], ZONE)
    assert s.obstacles[0].detected
    assert s.fp_cells == 2 and s.cells_in_zone == 3 and s.occupied_cells == 6


def test_empty_truth_every_zone_cell_is_fp():
    s = score_frame(cells((5.0, 0.0), (30.0, 0.0)), [], ZONE)
    assert s.obstacles == () and s.fp_cells == 1
    assert score_frame(np.zeros((0, 2)), [], ZONE).fp_cells == 0


def test_obstacle_outside_zone_not_counted_but_not_a_false_positive_either():
    far = {"id": "t", "class": "tree", "x_m": 20.3, "y_m": 0.0, "length_m": 1.0,
           "width_m": 1.0, "yaw_deg": 0.0}           # centre beyond 20 m, front edge at 19.8
    side = {"id": "w", "class": "person", "x_m": 5.0, "y_m": 6.0, "length_m": 0.4,
            "width_m": 0.4, "yaw_deg": 0.0}          # outside the 30 deg wedge
    s = score_frame(cells((19.9, 0.0), (5.0, 6.0)), [far, side], ZONE)
    assert [o.in_zone for o in s.obstacles] == [False, False]
    assert not any(o.detected for o in s.obstacles) and s.scored_obstacles == ()
    assert s.fp_cells == 0                           # (19.9, 0) is in zone but on the tree
    agg = Aggregate()
    agg.add(0, s, 1.0)
    r = agg.result()
    assert r["obstacle_frames"] == 0 and r["obstacles"] == 0 and r["recall"] is None


def test_zone_wedge_follows_camera_yaw():
    z = Zone(2.0, 20.0, math.radians(10), 1.0, 0.0, yaw_rad=math.radians(45))
    assert list(z.contains(cells((6.0, 5.0), (6.0, 0.0)))) == [True, False]


# ---- aggregate ----------------------------------------------------------------------------------
def ob(id_, cls, in_zone=True, detected=False):
    return ObstacleScore(id_, cls, in_zone, detected, None)


def test_aggregate_per_class_and_distinct_obstacles():
    agg = Aggregate()
    agg.add(0, FrameScore((ob("p1", "person", detected=True), ob("c1", "cow")), 5, 3, 0), 10.0)
    agg.add(1, FrameScore((ob("p1", "person"), ob("c1", "cow"), ob("x", "cow", in_zone=False)),
                          5, 3, 2), 20.0)
    agg.add(2, FrameScore((ob("p2", "person", detected=True),), 1, 1, 1), 30.0)
    agg.add(3, None, 40.0)                 # no truth file: timed, not scored
    r = agg.result()
    assert r["frames"] == 3
    assert r["obstacle_frames"] == 5 and r["detected_obstacle_frames"] == 2
    assert r["recall"] == pytest.approx(0.4)
    assert r["obstacles"] == 3 and r["obstacles_detected"] == 2
    assert r["false_positive_frames"] == 2 and r["fp_cells_per_frame"] == pytest.approx(1.0)
    assert r["per_class"]["person"] == {"obstacle_frames": 3, "detected_obstacle_frames": 2,
                                        "recall": pytest.approx(2 / 3), "obstacles": 2,
                                        "obstacles_detected": 2}
    assert r["per_class"]["cow"] == {"obstacle_frames": 2, "detected_obstacle_frames": 0,
                                     "recall": 0.0, "obstacles": 1, "obstacles_detected": 0}
    assert r["ms_per_frame"] == pytest.approx(25.0) and r["ms_p50"] == pytest.approx(25.0)
    assert r["ms_p99"] <= 40.0 and r["timed_frames"] == 4
    assert agg.missed == [(0, "c1"), (1, "p1"), (1, "c1")]
    json.dumps(r)                          # the evaluation command prints it as JSON
    table = format_table(r)
    assert "person" in table and "cow" in table and "2/3" in table and "40.0%" in table


def test_aggregate_empty():
    r = Aggregate().result()
    assert r["frames"] == 0 and r["recall"] is None and r["fp_cells_per_frame"] is None
    assert r["ms_per_frame"] is None and r["per_class"] == {}
    format_table(r)


# ---- zone of a run ------------------------------------------------------------------------------
def write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip())


STEREO = """
[stereo]
width = 1280
height = 1024
fx = 1100.0
fy = 1100.0
cx = 640.0
cy = 512.0
baseline_m = 0.75
mount = { x_m = 1.2, y_m = 0.1, z_m = 1.55, roll_deg = 0.0, pitch_deg = 15.0, yaw_deg = 0.0 }
"""
RGBD = """
[rgbd]
width = 640
height = 480
fx = 580.0
fy = 580.0
cx = 319.5
cy = 239.5
mount = { x_m = 1.0, y_m = 0.0, z_m = 0.9, roll_deg = 0.0, pitch_deg = 10.0, yaw_deg = 0.0 }
"""
LASER = """
[laser]
angle_min_deg = -10.0
angle_step_deg = 5.0
beams = 5
range_max_m = 50.0
mount = { x_m = 1.3, y_m = 0.0, z_m = 0.7, roll_deg = 0.0, pitch_deg = 0.0, yaw_deg = 0.0 }
"""


def run_with(tmp_path: Path, toml: str, name="r") -> RunReader:
    write(tmp_path / name / "run.toml", toml)
    write(tmp_path / name / "frames.csv", "index\n")
    return RunReader(tmp_path / name)


def test_zone_for_run(tmp_path):
    z = zone_for_run(run_with(tmp_path, STEREO + RGBD, "s").info)
    assert (z.x_min_m, z.x_max_m, z.apex_x_m, z.apex_y_m) == (2.0, 20.0, 1.2, 0.1)
    assert z.half_fov_rad == pytest.approx(math.atan(640 / 1100))
    z = zone_for_run(run_with(tmp_path, RGBD, "d").info)
    assert (z.x_min_m, z.x_max_m, z.apex_x_m) == (1.5, 6.0, 1.0)
    assert z.half_fov_rad == pytest.approx(math.atan(320 / 580))
    with pytest.raises(RunFormatError, match="scored zone"):
        zone_for_run(run_with(tmp_path, LASER, "l").info)
    z = zone_for_run(run_with(tmp_path, '[run]\nscored_zone = {x_min_m = 2, x_max_m = 9}\n'
                              + LASER, "lz").info)
    assert (z.x_min_m, z.x_max_m) == (2.0, 9.0) and z.half_fov_rad == pytest.approx(
        math.radians(10)) and z.yaw_rad == pytest.approx(0.0)


# ---- evaluate_run --------------------------------------------------------------------------------
def laser_run(tmp_path: Path) -> Path:
    """Laser + stereo calibration (no stereo images needed by a laser pipeline): 4 frames, a
    person straight ahead at 9.5 m whose near face the middle beam hits at 8.0 m from the laser.
    Frame 0 has no truth; frame 3 has a stray hit at 5 m off to the side."""
    run = tmp_path / "lr"
    write(run / "run.toml", '[run]\nname = "lr"\nrate_hz = 10\n' + STEREO + LASER)
    write(run / "frames.csv", "index,speed_mps\n0,0\n1,0\n2,0\n3,0\n")
    person = {"id": "p1", "class": "person", "x_m": 9.5, "y_m": 0.0, "z_m": 0.0,
              "length_m": 0.4, "width_m": 0.5, "height_m": 1.8, "yaw_deg": 0.0}
    for i in range(4):
        (run / "laser").mkdir(exist_ok=True)
        (run / f"laser/{i:06d}.csv").write_text("\n\n8.0\n\n\n" if i < 3 else "\n5.08\n8.0\n\n\n")
        if i:
            write(run / f"truth/{i:06d}.json", json.dumps({"obstacles": [person]}))
    return run


def test_evaluate_run_with_the_laser_pipeline(tmp_path):
    seen = []
    r = evaluate_run(laser_run(tmp_path), "laser", progress=lambda i, n: seen.append((i, n)))
    assert seen[-1] == (4, 4) and len(seen) == 4
    assert r["frames"] == 3 and r["frames_total"] == 4          # frame 0 has no truth
    assert r["obstacle_frames"] == 3 and r["obstacles"] == 1
    # the default grid needs two hits running: frames 1..3 see the person (hit in 0 and 1)
    assert r["detected_obstacle_frames"] == 3 and r["obstacles_detected"] == 1
    assert r["per_class"]["person"]["recall"] == 1.0
    assert r["false_positive_frames"] == 0       # the stray hit of frame 3 is seen only once
    assert r["timed_frames"] == 4 and r["ms_per_frame"] >= 0
    assert r["run"] == "lr" and r["pipeline"] == "laser"
    json.dumps(r)
    assert "person" in format_table(r)


class _FakePipeline:
    """Stands in for a pipeline: puts a point where the truth file of the frame says (read
    from a dict), to test the runner's wiring without any perception."""

    name = "fake"

    def __init__(self, requires, points_by_stamp):
        self.requires = requires
        self.points = points_by_stamp
        self.calls = []
        self.closed = False

    def missing(self, inputs):
        return [s for s in self.requires if not inputs.has(s)]

    def process(self, inputs):
        self.calls.append(inputs)
        return perception.Detections(points_xy=np.asarray(
            self.points.get(inputs.stamp_ns, np.zeros((0, 2))), np.float32).reshape(-1, 2))

    def close(self):
        self.closed = True


def test_evaluate_run_wiring_with_a_fake_pipeline(tmp_path, monkeypatch):
    from appliance.config import default_config, GridConfig
    import dataclasses
    cfg = dataclasses.replace(default_config(), grid=GridConfig(occupied_at=1.0))
    fake = _FakePipeline(("laser",), {100_000_000: [(9.2, 0.0), (12.0, 3.0)],
                                      200_000_000: [(9.2, 0.0)]})
    monkeypatch.setattr(perception, "make_pipeline", lambda name, config: fake)
    run = laser_run(tmp_path)
    (run / "laser/000003.csv").unlink()          # a dropped laser frame: no points from it
    r = evaluate_run(run, "anything", config=cfg)
    assert fake.closed and len(fake.calls) == 3  # frame 3 had no laser: not processed
    assert all(c.laser is not None and c.stereo is None for c in fake.calls)
    assert all(c.vehicle is not None for c in fake.calls)
    assert r["frames_missing_input"] == 1 and r["timed_frames"] == 3
    # frame 3 (its laser file gone) is named and not scored (issue #16: it used to be scored
    # as a miss, silently); one-frame grid: frame 1 detects and has one FP cell; frame 2 detects
    assert r["frames_missing"] == 1 and r["frames_missing_indices"] == [3]
    assert r["detected_obstacle_frames"] == 2 and r["obstacle_frames"] == 2
    assert r["false_positive_frames"] == 1 and r["fp_cells_per_frame"] == pytest.approx(1 / 2)


def test_evaluate_run_refuses_pipeline_without_its_sensor(tmp_path, monkeypatch):
    fake = _FakePipeline(("stereo",), {})
    monkeypatch.setattr(perception, "make_pipeline", lambda name, config: fake)
    run = tmp_path / "lo"
    write(run / "run.toml", '[run]\nname = "lo"\nscored_zone = {x_min_m = 2, x_max_m = 9}\n'
          + LASER)
    write(run / "frames.csv", "index\n0\n")
    with pytest.raises(ConfigError, match=r"pipeline 'stereo' needs stereo, run 'lo' has only "
                                          r"laser"):
        evaluate_run(run, "stereo")
    assert fake.closed


def test_evaluate_run_unknown_pipeline(tmp_path):
    with pytest.raises(ConfigError, match="unknown pipeline"):
        evaluate_run(laser_run(tmp_path), "no-such-pipeline")


def test_evaluate_contract_example_folder():
    """The contract's own example (tests/data): the laser sees the person's near face."""
    import dataclasses
    from appliance.config import GridConfig, default_config
    cfg = dataclasses.replace(default_config(), grid=GridConfig(occupied_at=1.0))
    r = evaluate_run(Path(__file__).parent / "data" / "contract-example", "laser", config=cfg)
    assert r["run"] == "stubble-day-01" and r["frames"] == 1 and r["frames_total"] == 2
    assert r["frames_missing_input"] == 1                     # frame 1 has no laser file
    assert r["obstacle_frames"] == 1 and r["detected_obstacle_frames"] == 1
    assert r["per_class"]["person"]["obstacles_detected"] == 1
    assert r["false_positive_frames"] == 0
    assert r["zone"]["x_min_m"] == 2.0 and r["zone"]["apex_x_m"] == 1.2
