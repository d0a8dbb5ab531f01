"""fieldguard campaign-compare: two real (tiny) campaigns of the same drives under two laser
configurations, compared drive by drive; the first difference judged against the simulator's
truth; the sign test's arithmetic; bad folders are one clear error."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.campaign_compare import (CompareError, _first_text, compare, first_difference,
                                        sign_test)
from appliance.cli import main

ROOT = Path(__file__).resolve().parents[1]

# the paper's laser stops at the first return in the stop zone, a stubble tuft's top included;
# today's default waits for a second cycle (a SLOW "unconfirmed" first): on training seeds 1
# and 2 of the coverage field the two boxes part at a tuft 21.8-23.5 s into the drive (24-s
# drives: 27 s until 2026-12-07, every check the same, 35 CPU-s of the suite instead of 41).
# Seed 1 alone since 2026-12-08 (the suite over its 10 minutes; ~18 CPU-s less): one pair of
# drives shows the first difference and its judgement; the sign test's arithmetic and the
# pairing of many drives are checked below without driving
PAPER = ('[perception]\npipelines = ["laser"]\n[perception.laser]\nmin_width_m = 0.0\n'
         '[grid]\nstop_recur_now = ["laser"]\n')
DEFAULT = '[perception]\npipelines = ["laser"]\n'


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    """The two campaigns run side by side, each the `fieldguard campaign` command in its own
    process (one core each; in turn they took 16 s of the suite)."""
    base = tmp_path_factory.mktemp("compare")
    out, procs = {}, {}
    for name, text in (("paper", PAPER), ("default", DEFAULT)):
        cfg = base / f"{name}.toml"
        cfg.write_text(text)
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", "appliance.cli", "campaign", "--scene", "stubble-coverage",
             "--seeds", "1", "--minutes", "0.4", "--out", str(base / name), "--workers", "1",
             "--config", str(cfg), "--stereo-scale", "0.25", "--no-report"],
            cwd=str(ROOT), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out[name] = base / name
    for name, p in procs.items():
        so, se = p.communicate(timeout=300)
        assert p.returncode == 0, (name, so[-2000:], se[-3000:])
    return out


def test_two_laser_configurations_part_at_a_tuft(two):
    c = compare(two["paper"], two["default"])
    assert [(d["kind"], d["seed"]) for d in c["drives"]] == [("stubble-coverage", 1)]
    assert not c["acceptance_seeds"] and c["only_in_a"] == c["only_in_b"] == []
    for d in c["drives"]:
        f = d["first_difference"]
        assert f is not None, d
        # the paper's laser (A) stops for the tuft, today's (B) slows: A is the cautious one,
        # and nothing real is within the zones (the coverage field's obstacles are far off)
        assert f["a"]["state"] == "STOP" and f["b"]["state"] == "SLOW", f
        assert f["cautious"] == "a" and f["judgement"] == "phantom", f
        assert 20.0 < f["t_s"] < 27.0
        assert d["a"]["false_stops"] >= 1
    p = c["paired"]["first_difference"]
    assert p["b_better"] == 1 and p["b_worse"] == 0 and p["sign_test_p"] == 1.0
    # totals come from the summaries, drive by drive
    tot = c["totals"]
    for side, name in (("a", "paper"), ("b", "default")):
        s = json.loads((two[name] / "summary.json").read_text())
        assert tot[side]["false_stops"] == s["false_stops"]
        assert tot[side]["collisions"] == s["collisions"]
    # a campaign against itself never parts
    same = compare(two["paper"], two["paper"])
    assert all(d["first_difference"] is None for d in same["drives"])
    assert same["paired"]["false_stops"]["same"] == 1


def test_many_drives_pair_by_kind_and_seed_in_order(two, tmp_path):
    """The one driven pair copied as three seeds (5, 3, 4, listed out of order) in both
    campaigns: three drives paired in order, three first differences B better, the sign test
    over them; no drive is driven again."""
    import shutil
    dirs = {}
    for name in ("paper", "default"):
        d = dirs[name] = tmp_path / name
        shutil.copytree(two[name], d)
        s = json.loads((d / "summary.json").read_text())
        (one,) = s["per_drive"]
        s["per_drive"] = []
        for seed in (5, 3, 4):
            shutil.copytree(d / "drives" / f"stubble-coverage-{one['seed']}",
                            d / "drives" / f"stubble-coverage-{seed}")
            s["per_drive"].append(dict(one, seed=seed))
        (d / "summary.json").write_text(json.dumps(s))
    c = compare(dirs["paper"], dirs["default"])
    assert [(d["kind"], d["seed"]) for d in c["drives"]] == [("stubble-coverage", k)
                                                              for k in (3, 4, 5)]
    p = c["paired"]["first_difference"]
    assert p["b_better"] == 3 and p["b_worse"] == 0 and p["sign_test_p"] == 0.25
    assert c["paired"]["false_stops"]["b_fewer"] == 3


def test_the_cli_prints_the_table_and_json(two, capsys):
    assert main(["campaign-compare", str(two["paper"]), str(two["default"])]) == 0
    text = capsys.readouterr().out
    assert "stubble-coverage-1" in text and "first differences: B better in 1, worse in 0, early" in text
    assert main(["campaign-compare", str(two["paper"]), str(two["default"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["paired"]["first_difference"]["b_better"] == 1


def test_the_picture(two, tmp_path, capsys):
    import cv2
    import numpy as np
    png = tmp_path / "cmp.png"
    assert main(["campaign-compare", str(two["paper"]), str(two["default"]),
                 "--png", str(png)]) == 0
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] == 1000
    # the drive's first difference was B better: a green mark, no red one
    green = (img[:, :, 1] > 140) & (img[:, :, 0] < 40) & (img[:, :, 2] < 40)
    red = (img[:, :, 2] > 200) & (img[:, :, 0] < 40) & (img[:, :, 1] < 40)
    assert green.sum() > 40 and red.sum() == 0
    assert main(["campaign-compare", str(two["paper"]), str(two["default"]),
                 "--png", str(tmp_path / "no" / "such" / "dir" / "x.png")]) == 2
    assert "cannot write the picture" in capsys.readouterr().err


def _rows(states, near=None, zone=3.8):
    return [{"t_s": f"{i / 10:.1f}", "x_m": f"{i * 0.25:.2f}", "y_m": "0.00",
             "speed_mps": "2.50", "state": s, "reason": s.lower(), "stop_zone_m": f"{zone}",
             "real_nearest_m": "" if near is None else f"{near}", "real_obstacle": ""}
            for i, s in enumerate(states)]


def test_first_difference_judges_caution_against_the_truth():
    a = _rows(["CLEAR", "CLEAR", "CLEAR"], near=25.0)
    b = _rows(["CLEAR", "SLOW", "CLEAR"], near=25.0)
    f = first_difference(a, b, reach_extra_m=3.0)
    assert f["t_s"] == pytest.approx(0.1) and f["cautious"] == "b" and f["judgement"] == "phantom"
    near = first_difference(_rows(["CLEAR", "STOP"], near=4.0),
                            _rows(["CLEAR", "CLEAR"], near=4.0), reach_extra_m=3.0)
    assert near["cautious"] == "a" and near["judgement"] == "right"
    early = first_difference(_rows(["CLEAR", "SLOW"], near=9.0),
                             _rows(["CLEAR", "CLEAR"], near=9.0), reach_extra_m=3.0)
    assert early["cautious"] == "a" and early["judgement"] == "early"   # zones reach 6.8 m
    nothing = first_difference(_rows(["STOP", "STOP"]), _rows(["STOP", "CLEAR"]), 3.0)
    assert nothing["judgement"] == "phantom" and nothing["real_nearest_m"] is None
    assert first_difference(a, a, 3.0) is None
    moved = _rows(["CLEAR", "CLEAR"])
    moved2 = [dict(r) for r in moved]
    moved2[1]["x_m"] = "9.99"
    assert first_difference(moved, moved2, 3.0)["cautious"] is None
    # nothing ahead in the path, but a walker about to walk into the vehicle: caution is right
    walk_a, walk_b = _rows(["CLEAR", "STOP"]), _rows(["CLEAR", "CLEAR"])
    for r in walk_a + walk_b:
        r["real_meets"] = "w2/person"
    walker = first_difference(walk_a, walk_b, 3.0)
    assert walker["judgement"] == "right" and walker["real_meets"] == "w2/person"
    assert "walking in to meet the vehicle: w2/person" in _first_text(walker)


def test_sign_test_is_the_exact_binomial():
    assert sign_test(0, 0) == 1.0
    assert sign_test(5, 5) == 1.0
    assert sign_test(6, 0) == pytest.approx(2 / 64)
    assert sign_test(1, 9) == pytest.approx(2 * (1 + 10) / 1024)
    assert sign_test(9, 1) == sign_test(1, 9)
    assert 0.0 < sign_test(20, 2) < 0.001 and not math.isnan(sign_test(3, 4))


def test_bad_folders_are_one_clear_error(tmp_path, capsys, two):
    assert main(["campaign-compare", str(tmp_path / "nope"), str(two["paper"])]) == 2
    assert "not a folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["campaign-compare", str(tmp_path / "empty"), str(two["paper"])]) == 2
    assert "no summary.json" in capsys.readouterr().err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "summary.json").write_text("{not json")
    assert main(["campaign-compare", str(tmp_path / "bad"), str(two["paper"])]) == 2
    assert "unreadable" in capsys.readouterr().err
    other = json.loads((two["paper"] / "summary.json").read_text())
    other["minutes_per_drive"] = 9.0
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "summary.json").write_text(json.dumps(other))
    with pytest.raises(CompareError, match="not the same drives"):
        compare(tmp_path / "other", two["paper"])
    other["minutes_per_drive"] = json.loads(
        (two["paper"] / "summary.json").read_text())["minutes_per_drive"]
    (tmp_path / "other" / "summary.json").write_text(json.dumps(other))
    with pytest.raises(CompareError, match="cycles.csv: missing"):
        compare(tmp_path / "other", two["paper"])
    for d in other["per_drive"]:
        d["seed"] += 1000
    (tmp_path / "other" / "summary.json").write_text(json.dumps(other))
    with pytest.raises(CompareError, match="no drive .* in common"):
        compare(tmp_path / "other", two["paper"])
