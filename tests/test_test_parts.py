"""tools/test_parts.sh: the suite's two parts at once, and its exit status.

The first version of it (2026-12-06) exited 1 after every run, both parts passing: its EXIT
trap killed the already-reaped background pytest, and under `set -e` that failing `kill`
became the script's status. CI refused the landing; these run the script itself on tiny
suites that pass and fail.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "tools" / "test_parts.sh"

PASSING = "def test_ok():\n    assert 1 + 1 == 2\n"
FAILING = "def test_broken():\n    assert 1 + 1 == 3\n"
# written by the background part: the scheduling policy it ran under
POLICY = ("import os\n"
          "def test_policy():\n"
          "    open(os.environ['POLICY_OUT'], 'w').write(str(os.sched_getscheduler(0)))\n")


def _suite(tmp_path, name, body):
    d = tmp_path / name
    d.mkdir()
    (d / "pytest.ini").write_text("[pytest]\n")
    (d / f"test_{name}.py").write_text(body)
    # -c: this folder's own ini (not the project's addopts, conftest or phases)
    return f"{d / f'test_{name}.py'} -c {d / 'pytest.ini'} -p no:cacheprovider -q"


def _run(low, fg, env=None):
    # the tiny suites need no plugin: without autoloading them (hypothesis's alone takes ~2 s of
    # CPU to import) each of these ten pytest sessions starts in ~0.7 s instead of ~3.5 s
    return subprocess.run(["bash", str(SCRIPT), low, fg], cwd=ROOT, capture_output=True,
                          text=True, timeout=120,
                          env={**os.environ, "FIELDGUARD_PYTHON": sys.executable,
                               "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1", **(env or {})})


def test_both_parts_pass_exit_zero_and_both_outputs_printed(tmp_path):
    out = tmp_path / "policy"
    r = _run(_suite(tmp_path, "bg", PASSING + POLICY), _suite(tmp_path, "fg", PASSING),
             env={"POLICY_OUT": str(out)})
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 passed" in r.stdout          # the background part's output, printed at the end
    assert "1 passed" in r.stdout          # the foreground part's
    assert r.stdout.index("1 passed") < r.stdout.index("2 passed")
    if subprocess.run(["chrt", "--idle", "0", "true"], capture_output=True).returncode == 0:
        assert int(out.read_text()) == os.SCHED_IDLE
    else:
        pytest.skip("no chrt --idle here: the nice 19 fallback was used (exit status checked)")


def test_a_failing_foreground_part_fails_the_run(tmp_path):
    r = _run(_suite(tmp_path, "bg", PASSING), _suite(tmp_path, "fg", FAILING))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "1 failed" in r.stdout and "1 passed" in r.stdout


def test_a_failing_background_part_fails_the_run(tmp_path):
    r = _run(_suite(tmp_path, "bg", FAILING), _suite(tmp_path, "fg", PASSING))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "test: the low-priority part exit 1" in r.stderr


def test_wrong_arguments_say_how_to_call_it():
    r = subprocess.run(["bash", str(SCRIPT), "only-one"], cwd=ROOT, capture_output=True,
                       text=True, timeout=30)
    assert r.returncode == 2 and "usage: test_parts.sh" in r.stderr


def test_the_wall_clock_lock_makes_a_second_taker_wait_and_never_hang(tmp_path, monkeypatch):
    """tests/conftest.py hold_wallclock_lock: the soak and the fake GigE pair through the
    daemon never overlap. Held by one open file (the soak's process holds its copy), a second
    taker waits; after its bound it goes on without it; once released it is taken at once.
    On a lock of its own (the environment names it, so the child process below takes the same
    one): the suite's soak holds the checkout's lock for ~100 s, and this test, run while it
    did, waited 5 s for it and failed."""
    import time
    from tests.conftest import hold_wallclock_lock, wallclock_lock_path
    monkeypatch.setenv("FIELDGUARD_WALLCLOCK_LOCK", str(tmp_path / "wallclock.lock"))
    assert wallclock_lock_path() == tmp_path / "wallclock.lock"
    first, waited = hold_wallclock_lock(max_wait_s=5.0)
    assert first is not None and waited < 5.0
    try:
        # another process (as the soak is to the wall-clock part): not within 1 s, then on
        code = (f"import sys; sys.path.insert(0, {str(ROOT)!r}); "
                "from tests.conftest import hold_wallclock_lock as h; "
                "f, w = h(max_wait_s=1.0); print(f is None, w >= 1.0)")
        t = time.monotonic()
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=30).stdout.split()
        assert out == ["True", "True"] and time.monotonic() - t < 20
    finally:
        first.close()
    again, waited = hold_wallclock_lock(max_wait_s=5.0)
    assert again is not None and waited < 1.0
    again.close()
