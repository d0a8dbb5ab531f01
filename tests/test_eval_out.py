"""`fieldguard eval RUN --out FILE`: the box's decision per frame as docs/run-format.md "The
box's decisions" defines, read back by a scorer that uses nothing of the project (json only),
and the summary's false_stop_frames / missed_stop_frames."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

RUN_TOML = """[run]
name = "out-test"
rate_hz = 10
scored_zone = { x_min_m = 2.0, x_max_m = 20.0 }

[laser]
angle_min_deg = -10.0
angle_step_deg = 5.0
beams = 5
range_max_m = 50.0
mount = { x_m = 1.3, y_m = 0.0, z_m = 0.7, roll_deg = 0.0, pitch_deg = 0.0, yaw_deg = 0.0 }
"""
CONFIG = """[grid]
occupied_at = 1.0
stop_recur_now = ["laser"]
[gate]
hold_off_s = 1.0
"""
PERSON = {"id": "p1", "class": "person", "x_m": 4.0, "y_m": 0.0, "z_m": 0.0,
          "length_m": 0.4, "width_m": 0.5, "height_m": 1.8, "yaw_deg": 0.0}
N = 70
# CONFIG: single-frame decisions, a laser cell a STOP on its first occupied frame (the frames
# counted below); the default waits a frame more (stop_recur_now = [], min_width_m 0.05: the
# 5-degree beams here are 22 cm across at 2.55 m and are kept)


def make_run(root: Path) -> Path:
    """70 frames at standstill (stop zone 2.6-4.6 m). 0-4: no truth file (not scored);
    0-14: nothing; 15-29: a person at 4 m, seen by the laser; 30-49: the person gone, a stray
    return left where they stood (no truth); frame 45 has no laser file; 50-59: nothing;
    60-64: the person back at 4 m but not seen; 65-69: nothing, no truth."""
    run = root / "run"
    (run / "laser").mkdir(parents=True)
    (run / "truth").mkdir()
    (run / "run.toml").write_text(RUN_TOML)
    rows = ["index,stamp_ns,speed_mps"] + [f"{i},{i * 100_000_000},0.0" for i in range(N)]
    (run / "frames.csv").write_text("\n".join(rows) + "\n")
    for i in range(N):
        hit = 15 <= i < 50
        if i != 45:
            (run / f"laser/{i:06d}.csv").write_text("\n\n2.55\n\n\n" if hit else "\n\n\n\n\n")
        if 5 <= i < 65:
            obs = [PERSON] if (15 <= i < 30 or 60 <= i < 65) else []
            (run / f"truth/{i:06d}.json").write_text(json.dumps({"obstacles": obs}))
    (root / "box.toml").write_text(CONFIG)
    return run


def independent_score(lines: list[dict], run: Path, hold_off_s: float) -> tuple[int, int]:
    """A scorer of its own: the decisions file and the truth files, json only. Footprints and
    zones are axis-aligned here (yaw 0 in this run)."""
    false_stop = missed = 0
    last_real = None
    for d in lines:
        tf = run / "truth" / f"{d['index']:06d}.json"
        if not tf.exists():
            continue
        z = d["stop_zone"]
        real = False
        for o in json.loads(tf.read_text())["obstacles"]:
            x0, x1 = o["x_m"] - o["length_m"] / 2, o["x_m"] + o["length_m"] / 2
            y0, y1 = o["y_m"] - o["width_m"] / 2, o["y_m"] + o["width_m"] / 2
            if x1 >= z["x_min_m"] and x0 <= z["x_max_m"] and y1 >= -z["half_width_m"] \
                    and y0 <= z["half_width_m"]:
                real = True
        if real:
            last_real = d["stamp_ns"]
        recent = last_real is not None and d["stamp_ns"] - last_real <= hold_off_s * 1e9
        if real and d["state"] != "STOP":
            missed += 1
        if d["state"] == "STOP" and d["cause"] == "obstacle" and not real and not recent:
            false_stop += 1
    return false_stop, missed


def eval_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "appliance.cli", "eval", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_out_file_every_frame_in_order_readable_with_json_only(tmp_path):
    run = make_run(tmp_path)
    out = tmp_path / "decisions.jsonl"
    p = eval_cli(str(run), "--pipeline", "laser", "--config", str(tmp_path / "box.toml"),
                 "--out", str(out), "--json")
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout)
    raw = out.read_bytes().decode("utf-8")
    assert raw.endswith("\n")
    lines = [json.loads(s) for s in raw.split("\n")[:-1]]
    assert [d["index"] for d in lines] == list(range(N))           # every frame, in order
    assert [d["stamp_ns"] for d in lines] == [i * 100_000_000 for i in range(N)]
    for d in lines:
        assert {"index", "stamp_ns", "cells", "state", "reason", "stop_zone", "slow_zone",
                "objects"} <= set(d)
        assert d["state"] in ("STOP", "SLOW", "CLEAR") and isinstance(d["reason"], str)
        assert d["stop_zone"] == {"x_min_m": 2.6, "x_max_m": 4.6, "half_width_m": 1.25}
        assert d["slow_zone"] == {"x_min_m": 4.6, "x_max_m": 9.6, "half_width_m": 1.25}
        assert all(len(c) == 2 and all(isinstance(v, float) for v in c) for c in d["cells"])
        assert d["objects"] == []                 # cells hold no objects; nothing here moves
    st = [d["state"] for d in lines]
    # boot: STOP held for hold_off (frames 0-9), then CLEAR
    assert st[:10] == ["STOP"] * 10 and {d["cause"] for d in lines[:10]} == {"boot"}
    assert st[10:15] == ["CLEAR"] * 5
    assert st[15:60] == ["STOP"] * 45             # the person, the stray return, the hold-off
    assert lines[45]["cause"] == "fault" and "laser" in lines[45]["reason"]
    assert lines[20]["cells"] == [[3.85, 0.05]] and "stop zone" in lines[20]["reason"]
    assert st[60:] == ["CLEAR"] * 10
    # frames 40-59 (past the hold-off after the person left) are STOP for an obstacle with
    # nothing real in the stop zone, except 45 (a fault); 60-64 miss the person
    assert summary["false_stop_frames"] == 19
    assert summary["false_stop_frame_indices"] == [i for i in range(40, 60) if i != 45]
    assert summary["missed_stop_frames"] == 5 and summary["missed_stop_frame_indices"] == [
        60, 61, 62, 63, 64]
    assert independent_score(lines, run, 1.0) == (19, 5)
    assert summary["decision"] == "cells+movers" and summary["frames_total"] == N


def test_out_with_tracks_lists_objects(tmp_path):
    run = make_run(tmp_path)
    cfg = tmp_path / "tracks.toml"
    cfg.write_text(CONFIG + "[tracking]\nenabled = true\nweights = { laser = 3.0 }\n")
    out = tmp_path / "d.jsonl"
    p = eval_cli(str(run), "--pipeline", "laser", "--config", str(cfg), "--out", str(out),
                 "--json")
    assert p.returncode == 0, p.stderr
    lines = [json.loads(s) for s in out.read_text().splitlines()]
    assert len(lines) == N
    held = [d for d in lines if d["objects"]]
    assert held and all(d["state"] == "STOP" for d in held)
    o = held[0]["objects"][0]
    assert {"id", "x_m", "y_m", "length_m", "width_m", "height_m", "vx_mps", "vy_mps",
            "confidence", "sources"} <= set(o)
    assert o["sources"] == ["laser"] and abs(o["x_m"] - 3.85) < 0.1 and 0 < o["confidence"] <= 1
    summary = json.loads(p.stdout)
    assert summary["decision"] == "tracks"
    assert independent_score(lines, run, 1.0) == (summary["false_stop_frames"],
                                                  summary["missed_stop_frames"])


def test_out_with_workers_for_one_run_writes_the_decisions(tmp_path):
    """`eval RUN --workers 1 --out F` (a script that always passes --workers) said "give one
    RUN with --out" although it gave one run; many runs with --out still say so."""
    run = make_run(tmp_path)
    out = tmp_path / "d.jsonl"
    p = eval_cli(str(run), "--pipeline", "laser", "--config", str(tmp_path / "box.toml"),
                 "--workers", "1", "--out", str(out), "--json")
    assert p.returncode == 0, p.stderr
    assert len(out.read_text().splitlines()) == N
    assert json.loads(p.stdout)["false_stop_frames"] == 19
    p = eval_cli(str(run), str(run), "--pipeline", "laser", "--workers", "1", "--out", str(out))
    assert p.returncode == 2 and "give one RUN with --out" in p.stderr
    assert "Traceback" not in p.stderr


def test_out_into_a_missing_folder_is_a_clear_error(tmp_path):
    run = make_run(tmp_path)
    p = eval_cli(str(run), "--pipeline", "laser", "--out", str(tmp_path / "no" / "d.jsonl"))
    assert p.returncode == 2 and "fieldguard: error:" in p.stderr and "does not exist" in p.stderr
    assert "Traceback" not in p.stderr


def test_eval_without_pipeline_runs_the_default_perception_for_the_run(tmp_path):
    from appliance.evaluation import default_pipelines
    from drivers.runfolder import RunReader
    run = make_run(tmp_path)
    info = RunReader(run).info
    assert default_pipelines(info) == ["laser"]
    p = eval_cli(str(run), "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["pipeline"] == "laser"


def test_default_pipelines_follow_the_sensors_and_the_config(tmp_path):
    from appliance.config import parse_config
    from appliance.evaluation import default_pipelines

    class Info:
        name = "x"
        sensors = ("stereo", "laser")

    assert default_pipelines(Info) == ["stereo-novelty", "laser"]
    cfg = parse_config({"perception": {"pipelines": ["stereo", "rgbd"]}})
    assert default_pipelines(Info, cfg, configured=True) == ["stereo"]
    # a config that leaves the pipelines at the built-in default (laser) gets the run's
    assert default_pipelines(Info, parse_config({"tracking": {"enabled": True}}),
                             configured=True) == ["stereo-novelty", "laser"]
    Info.sensors = ("rgbd",)
    assert default_pipelines(Info) == ["rgbd"]
    Info.sensors = ()
    with pytest.raises(Exception, match="no sensor"):
        default_pipelines(Info)


def test_the_table_names_false_and_missed_stops(tmp_path):
    run = make_run(tmp_path)
    p = eval_cli(str(run), "--pipeline", "laser", "--config", str(tmp_path / "box.toml"))
    assert p.returncode == 0, p.stderr
    assert "decision cells+movers: false-stop frames 19  missed-stop frames 5" in p.stdout


def test_stereo_novelty_eval_is_reproducible(tmp_path):
    """The novelty model learns in a background thread; offline, eval waits for each update,
    so two evaluations of the same run write the same decisions whatever the host's load
    (before, a re-run could differ by a frame or two: the score depended on thread timing)."""
    from appliance.evaluation import evaluate_run
    from drivers.sim.record import write_sim_run
    run = write_sim_run("stubble-day", 16, tmp_path / "run", seed=3, sensors=("stereo",),
                        stereo_scale=0.25)
    outs = []
    for k in range(2):
        out = tmp_path / f"decisions-{k}.jsonl"
        res = evaluate_run(run, "stereo-novelty", out=out)
        outs.append((out.read_text(), res["false_positive_frames"], res["fp_cells"]))
    assert outs[0][0].count("\n") == 16
    assert outs[0] == outs[1]
