"""tools/tilted_laser_probe.py (would a second, tilted laser see the low obstacles?): its reading
of a tilted scan on an analytic field, and its refusals."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hal.types import Mount  # noqa: E402
from tools.tilted_laser_probe import flag, scan_heights  # noqa: E402

Z, MEET = 0.7, 5.0


def _scan(boxes):
    """Ranges of a +-135 deg, 0.5 deg scan from a mount at (1.3, 0, Z) pitched to meet flat
    ground MEET m ahead, over flat ground with axis-aligned boxes (x0, x1, y0, y1, height)."""
    tilt = math.degrees(math.atan2(Z, MEET))
    m = Mount(1.3, 0.0, Z, 0.0, tilt, 0.0)
    ang = np.radians(np.arange(541) * 0.5 - 135.0)
    d = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1) @ m.rotation().T
    r = np.full(len(ang), np.nan)
    down = d[:, 2] < -1e-9
    r[down] = Z / -d[down, 2]                             # the ground
    for (x0, x1, y0, y1, h) in boxes:                     # the box's near face
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x0 - 1.3) / d[:, 0]
        y, zz = t * d[:, 1], Z + t * d[:, 2]
        hit = (d[:, 0] > 0) & (y >= y0) & (y <= y1) & (zz >= 0) & (zz <= h) & (
            ~np.isfinite(r) | (t < r))
        r[hit] = t[hit]
    return r, ang, m


def test_a_tilted_scan_reads_hit_heights_above_its_own_ground_and_flags_wide_objects():
    # the plane runs 0.3 m above the ground 2.14 m before the line: a dog-sized box (0.5 m
    # across, 0.45 m tall) and a stubble tuft (0.12 m across, 0.6 m tall) both stand there
    xd = 1.3 + MEET * (1 - 0.3 / Z)
    dog = (xd, xd + 0.6, -0.9, -0.4, 0.45)
    tuft = (xd, xd + 0.12, 0.5, 0.62, 0.6)
    r, ang, m = _scan([dog, tuft])
    pts, above, ok = scan_heights(r, ang, m, 0.0, 0.0, region=(0.0, 12.0, 3.0))
    on_dog = ok & (np.abs(pts[:, 0] - xd) < 0.01) & (pts[:, 1] < -0.3)
    on_tuft = ok & (np.abs(pts[:, 0] - xd) < 0.01) & (pts[:, 1] > 0.3)
    ground = ok & ~on_dog & ~on_tuft
    assert on_dog.sum() >= 8 and on_tuft.sum() >= 2
    np.testing.assert_allclose(above[on_dog], 0.3, atol=0.02)     # where the plane hit it
    assert np.all(np.abs(above[ground]) < 0.02)
    step = math.radians(0.5)
    fl = flag(r, above, ok, step, 0.2, 0.3)
    assert fl[on_dog].all() and not fl[on_tuft].any() and not fl[ground].any()
    assert flag(r, above, ok, step, 0.2, 0.1)[on_tuft].all()      # narrower runs: the tuft too
    # higher than the plane runs there: nothing
    assert not flag(r, above, ok, step, 0.35, 0.1).any()
    # outside the region: not judged
    assert not ok[pts[:, 0] > 12.0].any()


def test_refuses_acceptance_seeds_and_bad_lists():
    for args in (["stubble-thin", "1000"], ["stubble-thin", "1", "--meet", "x"],
                 ["stubble-thin", "1", "--meet", "0"]):
        p = subprocess.run([sys.executable, str(ROOT / "tools" / "tilted_laser_probe.py"), *args],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert p.returncode == 2 and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1


def test_a_short_drive_reports_every_combination():
    import json
    p = subprocess.run([sys.executable, str(ROOT / "tools" / "tilted_laser_probe.py"),
                        "stubble-thin", "1", "--minutes", "0.2", "--meet", "6", "--json"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads(p.stdout)
    assert s["drives"] == 1 and s["hours"] > 0 and len(s["meets"]) == 1
    rows = s["meets"][0]["rows"]
    assert len(rows) == 9 and all(r["false_cycles_per_h"] >= r["false_stop_zone_cycles_per_h"]
                                  for r in rows)
    assert s["meets"][0]["plane_on_ground_share"] > 0.5      # the plane meets the field
