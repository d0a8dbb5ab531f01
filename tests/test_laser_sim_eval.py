"""The paper's laser baseline on the simulated field, through the real CLI: it finds the
obstacles, and it also calls stubble obstacles (the paper's finding) — visible in the score."""
import json

import pytest

from appliance.cli import main

KEYS = {"frames", "obstacle_frames", "detected_obstacle_frames", "recall", "obstacles",
        "obstacles_detected", "false_positive_frames", "fp_cells_per_frame", "per_class",
        "ms_per_frame"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("runs")
    out = {}
    for scene, n in (("stubble-empty", 60), ("stubble-day", 80)):
        path = base / scene
        assert main(["sim", scene, "--frames", str(n), "--out", str(path),
                     "--sensors", "laser"]) == 0
        out[scene] = path
    return out


def evaluate(path, capsys, *extra):
    capsys.readouterr()
    assert main(["eval", str(path), "--pipeline", "laser", "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_sim_cli_writes_a_run_with_preview(runs):
    p = runs["stubble-day"]
    assert (p / "run.toml").exists() and (p / "preview.png").stat().st_size > 1000
    assert len(list((p / "laser").glob("*.csv"))) == 80
    assert len(list((p / "truth").glob("*.json"))) == 80


def test_laser_false_positives_on_stubble_are_visible(runs, capsys):
    res = evaluate(runs["stubble-empty"], capsys)
    assert KEYS <= set(res)
    assert res["obstacle_frames"] == 0
    # nothing is there but stubble and ground: every occupied cell is a false positive
    assert res["false_positive_frames"] >= 5
    assert res["fp_cells_per_frame"] > 0.2


def test_laser_detects_the_obstacle_course(runs, capsys):
    res = evaluate(runs["stubble-day"], capsys)
    assert res["obstacle_frames"] > 100
    assert res["recall"] > 0.5
    assert res["obstacles_detected"] >= res["obstacles"] - 2
    assert set(res["per_class"]) >= {"person", "drum", "pole"}
    # and it stops for stubble too
    assert res["false_positive_frames"] > 10


def test_attitude_projection_removes_some_ground_hits(runs, capsys, tmp_path):
    cfg = tmp_path / "att.toml"
    cfg.write_text("[perception.laser]\nuse_attitude = true\nmin_height_m = 0.3\n")
    base = evaluate(runs["stubble-empty"], capsys)
    better = evaluate(runs["stubble-empty"], capsys, "--config", str(cfg))
    assert better["fp_cells_per_frame"] < base["fp_cells_per_frame"]


def test_eval_unknown_pipeline_is_a_clear_error(runs, capsys):
    capsys.readouterr()
    assert main(["eval", str(runs["stubble-day"]), "--pipeline", "sonar"]) == 2
    err = capsys.readouterr().err
    assert "unknown pipeline 'sonar'" in err and "laser" in err
