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


def wallclock_lock_path() -> Path:
    """The lock two wall-clock workloads of one checkout take so that they never overlap: the
    soak (its own fake GigE pair, a daemon and its emulators at nice -10, in a session of its
    own: tests/test_soak.py) and the fake GigE pair through the daemon (tests/test_hw_aravis.py),
    whose pair drops frames when the host is busy. Per checkout and user, in the temp dir.
    FIELDGUARD_WALLCLOCK_LOCK names another file: the lock's own test takes a private one (on
    the real one it waited for the soak whenever the two ran at once: a failure seen in the
    forty-third session when the simulated part ran on two workers)."""
    import hashlib
    import os
    import tempfile
    if os.environ.get("FIELDGUARD_WALLCLOCK_LOCK"):
        return Path(os.environ["FIELDGUARD_WALLCLOCK_LOCK"])
    tag = hashlib.sha1(str(ROOT).encode()).hexdigest()[:12]
    return Path(tempfile.gettempdir()) / f"fieldguard-wallclock-{os.getuid()}-{tag}.lock"


def hold_wallclock_lock(max_wait_s: float = 240.0):
    """Take the lock of :func:`wallclock_lock_path` (exclusive), waiting at most ``max_wait_s``
    for whoever holds it; the open file that holds it (close it to release), and the seconds
    waited. After ``max_wait_s`` the caller goes on without it (None), never hangs."""
    import fcntl
    import time
    f = open(wallclock_lock_path(), "a+")
    t0 = time.monotonic()
    while True:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return f, time.monotonic() - t0
        except BlockingIOError:
            if time.monotonic() - t0 >= max_wait_s:
                f.close()
                return None, time.monotonic() - t0
            time.sleep(0.5)


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


# -- the simulated-time modules: the soak beside them, and both cores for them ---------------
# These modules run in simulated time (lock-step daemons, pace 0; CLI tools; an install into
# a directory; no wall-clock figure asserted, no status socket, no Ray), so sharing the
# machine changes nothing they check. Every other module (links, devices, the console,
# services, Ray, the benchmarks: wall-clock deadlines) runs one test at a time at normal CPU
# priority; a new module is one of those until it is listed here. Listed slowest first
# (`--durations=0`, 2026-12-06): the order in which they are handed out. The last four joined
# on 2026-12-08 (lock-step daemons at pace 0, a CLI tool's refusals, pure functions, the import
# graph): the wall-clock part had become the longer of the two (275 s against 256 s in a
# fresh clone), and they were ~10 s of it.
#  - `./tools/test.sh` with no arguments (the whole suite, what CI runs) runs them as
#    `--phase simulated` on pytest-xdist's workers (one per core and one for the soak's test,
#    which waits; a module stays on one worker: its fixtures are computed once) at SCHED_IDLE,
#    the soak a test among them (it takes the normal policy back), and beside them the rest
#    as `--phase wall-clock`, one test at a time (docs/reliability.md).
#  - A plain `pytest` (no phase) runs them first too, in one process, with the soak in the
#    background: tools/soak.py's ~95 s of wall clock, in which the box's own processes use
#    half a core at nice -10, overlap theirs; the soak test then collects the result.
SIMULATED = ("test_campaign_shadow.py", "test_laser_false_stops.py", "test_cue.py",
             "test_campaign_compare.py", "test_campaign_models.py", "test_laser_ground_probe.py",
             "test_fuzz_short.py",
             "test_eval_out.py", "test_rgbd_sim.py", "test_low_obstacles.py", "test_deploy.py",
             "test_canopy.py", "test_why_false_stops.py", "test_sim_scenes.py", "test_sim_loop.py",
             "test_rgbd.py", "test_tilted_laser_probe.py", "test_why_missed.py",
             "test_longrun.py", "test_laser_sim_eval.py", "test_rgbd_colour_check.py",
             "test_sim_render.py", "test_sim.py", "test_stereo.py", "test_properties.py",
             "test_boot_safe.py", "test_decision.py", "test_test_parts.py",
             "test_low_cell_probe.py", "test_recall_cue.py", "test_slow_recur.py",
             "test_boot_learnt.py", "test_look.py", "test_match_correlation.py",
             "test_colour_lut_builds.py", "test_incidents.py", "test_boot_with_model.py",
             "test_hold_blind.py", "test_layers.py")
SOAK_MODULE = "test_soak.py"
SOAK_TEST = (f"tests/{SOAK_MODULE}::"
             "test_short_soak_no_false_clear_stop_within_two_cycles_no_fd_growth")
PHASES = ("simulated", "wall-clock")


def pytest_addoption(parser):
    parser.addoption("--phase", choices=PHASES, default=None,
                     help="only the simulated-time modules (tests/conftest.py SIMULATED, and "
                          "the soak), or only the others; tools/test.sh runs both")


def pytest_ignore_collect(collection_path, config):
    phase = config.getoption("--phase", None)
    name = collection_path.name
    if phase is None or not (name.startswith("test_") and name.endswith(".py")):
        return None
    simulated = name in SIMULATED or name == SOAK_MODULE
    return True if simulated != (phase == "simulated") else None


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
    import os
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # on xdist's workers (each collects the same list; the controller hands out modules in
        # its order): the soak first, run by its test on one worker, then the slowest first
        rank = {n: k for k, n in enumerate((SOAK_MODULE, *SIMULATED))}
        items.sort(key=lambda i: rank.get(Path(str(i.fspath)).name, len(rank)))
        return
    soak = [i for i in items if i.nodeid == SOAK_TEST]
    beside = [i for i in items if Path(str(i.fspath)).name in SIMULATED]
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
