import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def missing_tool(reason: str):
    """A test needs something the project's own scripts install. Locally it is skipped with the
    reason; in CI (CI=true) it FAILS, so a missing install step can never hide behind a skip."""
    import os

    import pytest
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"{reason} — CI must install it (tools/ci_system_deps.sh)")
    pytest.skip(reason)


import logging as _logging  # noqa: E402

import pytest as _pytest  # noqa: E402


@_pytest.fixture(autouse=True)
def _restore_root_logging():
    """A test that runs the CLI in-process (or setup_logging) points the root logger at the
    stderr pytest captured for that test; once that test ends the file is closed, and every
    later warning from a thread (a link's acquisition thread in a module fixture) printed
    "--- Logging error --- ValueError: I/O operation on closed file". Put the root logger back."""
    root = _logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


# -- the soak beside the simulated-time tests ---------------------------------------------------
# The suite's soak (tests/test_soak.py) is ~95 s of wall clock in which the box's own processes
# use half a core. In a whole run it starts at the beginning and these modules go first: they
# run in simulated time (lock-step daemons, pace 0; CLI tools; no wall-clock figure asserted),
# so sharing the machine with the soak changes nothing they check, and the soak runs at
# nice -10 (tools/soak.py). The soak test then collects the result. Every other module (links,
# devices, the console, services: wall-clock deadlines) runs after it, alone as before.
SOAK_TEST = "tests/test_soak.py::test_short_soak_no_false_clear_stop_within_two_cycles_no_fd_growth"
SOAK_BESIDE = ("test_low_obstacles.py", "test_rgbd_sim.py", "test_eval_out.py",
               "test_sim_scenes.py", "test_rgbd.py", "test_laser_ground_probe.py",
               "test_laser_false_stops.py", "test_laser_sim_eval.py", "test_rgbd_colour_check.py",
               "test_longrun.py", "test_campaign_compare.py", "test_cue.py", "test_stereo.py")
_background_soak: list = []


@_pytest.fixture()
def background_soak():
    """(process, folder) of the soak started at the beginning of this run, or None (it stays
    listed: pytest_unconfigure ends it if pytest ends while it runs). A fixture: this file is
    imported by pytest as `conftest` and by the tests as `tests.conftest`, two modules."""
    return _background_soak[0] if _background_soak else None


def pytest_collection_modifyitems(session, config, items):
    if config.option.collectonly:
        return
    soak = [i for i in items if i.nodeid == SOAK_TEST]
    beside = [i for i in items if Path(str(i.fspath)).name in SOAK_BESIDE]
    if not soak or not beside:
        return
    from tests.test_soak import soak_missing, start_soak
    if soak_missing():
        return                               # the test says why (a skip, or a failure in CI)
    import tempfile
    items[:] = beside + soak + [i for i in items if i not in beside and i not in soak]
    out = Path(tempfile.mkdtemp(prefix="fieldguard-soak-"))
    _background_soak.append((start_soak(out), out))


def pytest_unconfigure(config):
    """A soak still running when pytest ends (interrupted, or its test deselected by -x):
    ended so that its cleanup (namespace, emulators) runs."""
    if _background_soak:
        from tests.test_soak import stop_soak
        while _background_soak:
            stop_soak(_background_soak.pop()[0])
