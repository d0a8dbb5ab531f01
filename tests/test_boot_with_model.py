"""tools/boot_with_model.py: each drive from an empty state, then again with the model it saved
(the installed box's boot after the periodic save)."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import boot_with_model as bwm  # noqa: E402


def _run(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "boot_with_model.py"), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_seed_lists():
    assert bwm.seeds_of("79-81,90") == [79, 80, 81, 90]
    assert bwm.seeds_of("5") == [5]


def test_refusals_are_messages(tmp_path):
    p = _run("--scene", "stubble-coverage", "--seeds", "x-3", "--out", str(tmp_path))
    assert p.returncode == 2 and "--seeds wants" in p.stderr and "Traceback" not in p.stderr
    cfg = tmp_path / "laser.toml"
    cfg.write_text('[perception]\npipelines = ["laser"]\n')
    p = _run("--scene", "stubble-coverage", "--seeds", "1", "--config", str(cfg),
             "--out", str(tmp_path))
    assert p.returncode == 2 and "must run stereo-novelty" in p.stderr
    p = _run("--scene", "nosuch", "--seeds", "1", "--out", str(tmp_path))
    assert p.returncode == 2 and "unknown scene 'nosuch'" in p.stderr
    assert "Traceback" not in p.stderr
