"""The long-run tool's accounting (tools/longrun_stereo.py), on short closed-loop runs of the
daemon with hand-made pipelines whose answer we know: a blind box (the vehicle must hit the
person on its path, counted as a collision), a phantom obstacle on an empty field (a false
stop, then the safety driver's override), and a box that reports the simulator's truth (true
stops only). No sensor is rendered for these pipelines, so each run takes a few seconds."""
from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest

from appliance.perception import Detections, Pipeline, register_pipeline
import appliance.perception as perception
from drivers.sim.scenes import COVERAGE_LANES, build_scene
from tools.longrun_stereo import CSV_FIELDS, LongRun, plateau_verdict, refresh_summary


class BlindPipeline(Pipeline):
    """Sees nothing, ever."""

    name = "test-blind"

    def process(self, inputs):
        return Detections.empty()


class PhantomPipeline(Pipeline):
    """Nothing for the first 2 s, then a 1 m x 1 m 'obstacle' 0.5-1.5 m ahead of the front,
    fixed in the vehicle frame, forever (a patch, not a point: the grid moves last cycle's
    evidence with the vehicle, so only a patch is hit twice in a row while moving)."""

    name = "test-phantom"
    front_x_m = 2.2

    def __init__(self, options=None):
        super().__init__(options)
        self.calls = 0

    def process(self, inputs):
        self.calls += 1
        if self.calls <= 20:
            return Detections.empty()
        xx, yy = np.meshgrid(np.arange(0.55, 1.5, 0.1) + self.front_x_m,
                             np.arange(-0.45, 0.5, 0.1))
        return Detections(points_xy=np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float32))


class TruthPipeline(Pipeline):
    """Reports the footprints of the real obstacles within 25 m (the test hands it the sim)."""

    name = "test-truth"
    field = None

    def process(self, inputs):
        v = type(self).field.vehicle
        pts = [v.footprint_in_vehicle(k) for k in range(len(v.scene.world.obstacles))]
        pts = np.concatenate(pts) if pts else np.zeros((0, 2))
        near = (pts[:, 0] > 0) & (pts[:, 0] < 25) & (np.abs(pts[:, 1]) < 10)
        return Detections(points_xy=pts[near].astype(np.float32))


@pytest.fixture(autouse=True)
def _test_pipelines():
    names = {"test-blind": "BlindPipeline", "test-phantom": "PhantomPipeline",
             "test-truth": "TruthPipeline"}
    for n, cls in names.items():
        register_pipeline(n, f"{__name__}:{cls}")
    yield
    for n in names:
        perception._PIPELINES.pop(n, None)


def _run(tmp_path, pipeline, scene, seconds, plot=False, before=None):
    lr = LongRun(tmp_path / "out", scene=scene, seed=0, minutes=seconds / 60.0,
                 pipelines=(pipeline,), every=10, plot=plot, progress=False)
    lr.build()
    if before:
        before(lr)
    return lr, lr.run()


def test_blind_box_counts_the_collision_with_the_person_on_the_path(tmp_path):
    lr, s = _run(tmp_path, "test-blind", "stubble-day", 8.0, plot=True)
    # stubble-day seed 0: the person stands on the path ~13 m ahead; a box that sees nothing
    # lets the vehicle drive into it
    assert s["collisions"] >= 1
    assert any(c.endswith("/person") for c in s["collided_with"])
    hits = [e for e in s["events"] if e["event"] == "collision"]
    assert len(hits) == s["collisions"]
    assert hits[0]["reason"].startswith("box said CLEAR")
    assert hits[0]["seen_frames_10s"].startswith("0/") and hits[0]["last_seen_s_before"] is None
    # the box never stopped for anything after booting: no stop events of any kind
    assert s["stops_total"] == 0 and s["false_stop_s"] == 0.0
    # the files: CSV rows every 10 cycles, events, summary, a picture
    out = tmp_path / "out"
    with open(out / "longrun.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_FIELDS
    assert [int(r["cycles"]) for r in rows] == list(range(10, 81, 10))
    assert int(rows[-1]["collisions"]) == s["collisions"]
    assert json.loads((out / "summary.json").read_text())["collisions"] == s["collisions"]
    with open(out / "events.csv", newline="") as f:
        assert [r["event"] for r in csv.DictReader(f)] == ["collision"] * s["collisions"]
    img = cv2.imread(str(out / "longrun.png"))
    assert img is not None and img.shape[1] == 1500
    assert 'pipelines = ["test-blind"]' in (out / "config.toml").read_text()
    # no novelty model in this box: no model verdict; the RSS verdict is taken from the CSV
    assert s["model"]["samples"]["plateau"] is None
    again = refresh_summary(out)
    assert again["rss_mb"]["verdict"]["points"] == len(rows) == 8
    assert again["collisions"] == s["collisions"]


def test_phantom_on_an_empty_field_is_one_false_stop_then_an_override(tmp_path):
    lr, s = _run(tmp_path, "test-phantom", "stubble-empty", 15.0)
    assert s["stops"] == {"true": 0, "false": 1, "early": 0, "fault": 0}
    ev = [e for e in s["events"] if e["event"] == "stop"]
    assert len(ev) == 1 and ev[0]["kind"] == "false" and ev[0]["real_nearest_m"] is None
    assert "stop zone" in ev[0]["reason"]
    assert 2.0 <= ev[0]["t_s"] <= 2.5                 # the phantom appears after 2 s
    hours = 150 / 10 / 3600
    assert s["false_stops_per_hour"] == pytest.approx(1 / hours, rel=1e-3)
    # STOP for ~13 s with nothing real ahead; the safety driver overrode after 10 s held
    assert 12.0 <= s["false_stop_s"] <= 13.5
    assert s["overrides"] == 1 and s["collisions"] == 0


def test_a_box_that_sees_the_truth_makes_only_true_stops_and_never_collides(tmp_path):
    def hand_over(lr):
        TruthPipeline.field = lr.field
    lr, s = _run(tmp_path, "test-truth", "stubble-day", 14.0, before=hand_over)
    assert s["collisions"] == 0
    assert s["stops"]["false"] == 0 and s["stops"]["fault"] == 0
    assert s["stops"]["true"] >= 1
    first = next(e for e in s["events"] if e["event"] == "stop")
    assert first["obstacle"].endswith("/person")
    assert 0.0 <= first["real_nearest_m"] <= first["stop_zone_m"] + 0.5
    # held at STOP before a real obstacle: the safety driver steered round it
    assert s["detours"] >= 1
    # the forensics: this box saw the person in every frame it had in view
    o = next(o for o in lr.field.world.obstacles if o.cls == "person")
    seen = lr.seen_before(o, 14.0)
    assert seen["last_seen_s_before"] is not None
    n, total = map(int, seen["seen_frames_10s"].split("/"))
    assert total == 100 and n >= 50


def test_plateau_verdict():
    t = np.arange(400)
    rising_then_flat = np.minimum(t * 200, 30000).astype(float)
    v = plateau_verdict(rising_then_flat, bound=38400)
    assert v["plateau"] is True and v["max"] == 30000 and v["q4_max_vs_q2_max"] == 0.0
    assert v["points_to_95pct_of_q4_mean"] == 144      # 200 t >= 0.95 * 30000 from t = 143
    # a dip in the third quarter (cells excluded near obstacles for a while) is still a plateau
    dip = rising_then_flat.copy()
    dip[220:280] = 22000
    assert plateau_verdict(dip, bound=38400)["plateau"] is True
    assert plateau_verdict(t * 100.0)["plateau"] is False                   # still growing
    assert plateau_verdict(np.full(400, 50000.0), bound=38400)["plateau"] is False  # over bound
    assert plateau_verdict(np.ones(3), bound=10)["plateau"] is None        # too short to say


def test_coverage_scene_lanes_and_obstacles():
    sc = build_scene("stubble-coverage-classic", 0)
    length, spacing, lanes = COVERAGE_LANES
    ys = np.unique(np.round(sc.path[:, 1][np.abs(sc.path[:, 1] / spacing
                                                 - np.round(sc.path[:, 1] / spacing)) < 1e-9]))
    assert len(ys) == lanes
    seg = np.hypot(*np.diff(sc.path, axis=0).T).sum()
    assert seg > 20 * 60 * sc.cruise_mps                  # more than 20 min at cruise speed
    obs = sc.world.obstacles
    on_lane = [o for o in obs if abs(o.y / spacing - round(o.y / spacing)) * spacing <= 0.31]
    between = [o for o in obs if abs((o.y / spacing) % 1 - 0.5) * spacing <= 0.21]
    assert len(on_lane) + len(between) == len(obs)
    lanes_with = {round(o.y / spacing) for o in on_lane}
    assert 0 < len(lanes_with) < lanes                    # obstacles on some lanes, not all
    assert all(30.0 <= o.x <= length - 30.0 for o in obs)
    assert all(o.x >= 60.0 for o in on_lane if round(o.y / spacing) == 0)
    assert build_scene("stubble-coverage-classic", 0).world.obstacles[0].x == obs[0].x   # seeded
    assert math.isclose(sc.cruise_mps, build_scene("stubble-day", 0).cruise_mps)
