"""tools/why_false_stops.py on RGB-D (greenhouse) drives: the candidates at and near the stop
zone at each false stop, or at asked times (docs/rgbd.md "The U-turn's exit")."""
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parent.parent
TOOL = ROOT / "tools" / "why_false_stops.py"


def _run(*args):
    return subprocess.run([sys.executable, str(TOOL), *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def _cand(x, y, length=0.2, width=0.2, sources=("geometry",), contact=True):
    return SimpleNamespace(x_m=x, y_m=y, length_m=length, width_m=width, height_m=0.4,
                           points=100, confidence=1.0, sources=sources, ground_contact=contact)


def test_near_zone_keeps_what_meets_or_nears_the_stop_zone_nearest_first():
    sys.path.insert(0, str(ROOT / "tools"))
    sys.path.insert(0, str(ROOT))
    from why_false_stops import near_zone
    cands = [_cand(3.0, 0.0, sources=("geometry", "texture"), contact=False),  # 1.8 m ahead
             _cand(1.6, 0.3),                        # 0.4 m ahead of the front at 1.1 m
             _cand(3.7, 0.0),                        # its near edge 0.5 m beyond a 2.0 m zone
             _cand(1.6, 1.4),                        # beside: 0.05 m outside the 1.25 m half
             _cand(8.0, 0.0),                        # far beyond the margin
             _cand(1.6, -3.0)]                       # far to the side
    got = near_zone(cands, front_x_m=1.1, half_width_m=1.25, stop_len_m=2.0, margin_m=1.0)
    assert [(r["ahead_m"], r["in_stop_zone"]) for r in got] == [
        (0.4, True), (0.4, False), (1.8, True), (2.5, False)]
    inz = [r for r in got if r["ahead_m"] == 1.8][0]
    assert inz["sources"] == ["geometry", "texture"] and inz["ground_contact"] is False
    assert near_zone(cands, 1.1, 1.25, 2.0, margin_m=0.0) == [r for r in got
                                                             if r["in_stop_zone"]]


def test_an_rgbd_drive_writes_a_record_and_a_picture_at_each_asked_time(tmp_path):
    # 0.04 min: 24 cycles at 10 Hz, to t = 2.3 s, past both asked times (0.05 min ran 3 s)
    p = _run("greenhouse-coverage", "1", "--minutes", "0.04", "--at", "1.0,2.0",
             "--out", str(tmp_path))
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert set(res) == {"false_stops", "true_stops", "missed_stops", "collisions"}
    recs = [json.loads(x) for x in
            (tmp_path / "greenhouse-coverage-1.jsonl").read_text().splitlines()]
    asked = [r for r in recs if r["cause"] == "asked"]
    assert [r["t_s"] for r in asked] == [1.0, 2.0]
    assert len(recs) - len(asked) == res["false_stops"]
    for r in asked:
        assert r["state"] in ("CLEAR", "SLOW", "STOP")
        assert isinstance(r["candidates"], list) and r["vehicle"]["speed_mps"] >= 0
        assert len(r["before"]) == 5 and r["before"][-1]["t_s"] < r["t_s"]
    pics = sorted(x.name for x in tmp_path.glob("greenhouse-coverage-1-t*.png"))
    assert "greenhouse-coverage-1-t001.0.png" in pics and "greenhouse-coverage-1-t002.0.png" in pics
    assert (tmp_path / "greenhouse-coverage-1-events.json").exists()


def test_bad_at_is_one_clear_line(tmp_path):
    p = _run("greenhouse-coverage", "1", "--minutes", "0.05", "--at", "1.0,soon",
             "--out", str(tmp_path))
    assert p.returncode == 2 and "--at wants seconds" in p.stderr
    assert "Traceback" not in p.stderr
    p = _run("stubble-coverage", "1", "--minutes", "0.05", "--at", "1.0", "--out", str(tmp_path))
    assert p.returncode == 2 and "--at is for RGB-D drives" in p.stderr
    assert "Traceback" not in p.stderr


def test_a_stereo_drive_still_runs_and_writes_the_drive_s_result(tmp_path):
    """The stereo-novelty path (the tool's first): a 3-s drive, no false stop in it; the
    drive's result and events are written as the campaign writes them. (The pair at a tenth
    of 1280x1024: nothing checked here depends on the image's size; no false stop at 0.5
    either; 2 CPU-s, not 5.)"""
    p = _run("stubble-coverage", "1", "--minutes", "0.05", "--out", str(tmp_path),
             "--stereo-scale", "0.1")
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    written = json.loads((tmp_path / "stubble-coverage-1-result.json").read_text())
    assert res["false_stops"] == written["false_stops"] and written["kind"] == "stubble-coverage"
    lines = (tmp_path / "stubble-coverage-1.jsonl").read_text().splitlines()
    assert len(lines) == res["false_stops"]
    assert isinstance(json.loads((tmp_path / "stubble-coverage-1-events.json").read_text()), list)
