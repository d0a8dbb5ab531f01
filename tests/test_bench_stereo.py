"""tools/bench_stereo.py, the speed figure of issue #14 ("perception + tracking ... at least 3x
faster than full-frame SGBM at the resolution it matches at"): a tiny run prints the box's
decision after perception and the ratio of the two against full-frame SGBM in the same run."""
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--scale", "0.5", "--learn", "2", "--frames", "1", "--reps", "2"]


def _bench(*extra):
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_stereo.py"), *TINY, *extra],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    return r.stdout


def test_prints_perception_plus_decision_against_full_frame():
    out = _bench()
    dec = re.search(r"decision \(cells\+movers: fusion, tracking, zones\) CPU\s+p50\s+([\d.]+)",
                    out)
    assert dec, out
    both = re.search(r"stereo-novelty \+ decision\s+CPU\s+p50\s+([\d.]+)", out)
    alone = re.search(r"stereo-novelty \(sgbm\) whole\s+CPU\s+p50\s+([\d.]+)", out)
    assert both and alone, out
    # the sum per frame: its median is at least the pipeline's alone
    assert float(both.group(1)) >= float(alone.group(1))
    ratio = re.search(r"perception \+ decision vs full-frame at the same matching resolution "
                      r"\(CPU p50\): ([\d.]+)x", out)
    assert ratio and float(ratio.group(1)) > 0, out


def test_no_decision_times_the_pipeline_alone():
    out = _bench("--no-decision")
    assert "whole    CPU" in out and "decision (" not in out and "perception + decision" not in out
