"""tools/canopy_probe.py: the clusters the field's canopy drops, labelled by truth (a probe for a
shape rule, docs/front-end.md "The field's canopy, and the boot")."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import canopy_probe as cp  # noqa: E402


def test_clusters_shapes_and_labels():
    # a dog's back 4 m ahead (0.3 m wide, 0.8 m long) and a tuft top 1 m to its side
    rng = np.random.default_rng(0)
    back = np.column_stack([rng.uniform(4.0, 4.8, 200), rng.uniform(-0.15, 0.15, 200)])
    tuft = np.column_stack([rng.uniform(5.0, 5.05, 12), rng.uniform(1.0, 1.05, 12)])
    xy = np.concatenate([back, tuft])
    lab = cp.clusters(xy)
    assert len(np.unique(lab)) == 2 and len(np.unique(lab[:200])) == 1
    s = cp.shape(back, np.full(200, 0.6))
    assert s["points"] == 200 and 0.35 <= s["width_m"] <= 0.41 and 0.85 <= s["length_m"] <= 0.91
    assert s["h_span_m"] == 0.0 and s["h_max_m"] == 0.6
    dog = {"cls": "dog-head-on",
           "pts_vehicle": np.array([[3.95, -0.17], [4.85, -0.17], [4.85, 0.17], [3.95, 0.17]])}
    assert cp.label(back, [dog], 0.3) == ("obstacle", "dog-head-on")
    assert cp.label(tuft, [dog], 0.3) == ("field", "")
    assert cp.clusters(np.zeros((0, 2))).shape == (0,)


def test_summary_counts_what_each_rule_keeps(tmp_path):
    f = tmp_path / "a-canopy.jsonl"
    rows = [{"label": "obstacle", "cls": "dog-head-on", "points": 80, "width_m": 0.3,
             "length_m": 0.8, "h_max_m": 0.6, "h_span_m": 0.1, "x_m": 4.0},
            {"label": "field", "cls": "", "points": 12, "width_m": 0.12, "length_m": 0.1,
             "h_max_m": 0.6, "h_span_m": 0.02, "x_m": 5.0}]
    f.write_text("".join(json.dumps(r) + "\n" for r in rows))
    p = subprocess.run([sys.executable, str(ROOT / "tools" / "canopy_probe.py"), "--summary",
                        str(f)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert "obstacle: 1 clusters {'dog-head-on': 1}" in lines and "field: 1 clusters" in lines
    row = next(ln.split() for ln in lines if ln.split()[:2] == ["0.25", "30"])
    assert row[2:] == ["1/1", "0/1"]           # the dog kept, the tuft dropped
    # no drive named: a usage message, not a traceback
    p = subprocess.run([sys.executable, str(ROOT / "tools" / "canopy_probe.py")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "KIND SEED" in p.stderr
