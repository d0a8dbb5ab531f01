"""The chaos soak, a minute and a half of it: tools/soak.py runs the daemon with the SICK laser
emulator (TCP), the strobe controller emulator (socat pty), a MAVLink vehicle behind MAVProxy and
the CAN vehicle side (udp_multicast in a network namespace) while a seeded schedule injects a fault
every ~6 s; the box is judged from what the vehicles heard on the wire. Longer runs and the
figures: docs/reliability.md."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from tests.conftest import missing_tool

ROOT = Path(__file__).resolve().parents[1]


# 84 s with 15 s of warm-up leaves ~68 s for judging RSS and fds (a process needs 60 s: the
# median fd count of its first 30 s against its last 30 s) and ~12 faults (>= 5 asked); the
# hour-long soak is the tool's (docs/reliability.md). Was 105 s / 20 s (~85 s judged): the
# suite's 10 minutes were breached (stop 30's CI: 671 s). Tried 2026-12-08 and NOT kept: 60 s
# / 12 s with a 40-s window (--judge-window 40): in the whole suite it read fd growth +1 from
# a GigE reconnect's ~10 s of 2-8 extra fds inside the last 20-s half (back to 31 by the end):
# in a window that short a reconnect's transient moves the median
JUDGE_WINDOW_S = 60
SOAK_ARGS = ("--minutes", "1.4", "--seed", "3", "--interval", "6", "--warmup", "15",
             "--judge-window", str(JUDGE_WINDOW_S))


def soak_missing() -> str | None:
    """Why the soak cannot run on this machine, or None."""
    if os.geteuid() != 0:
        return "the soak needs root (a network namespace and a tmpfs)"
    for tool in ("ip", "socat"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed (tools/hw_system_deps.sh installs it)"
    if shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) is None and \
            shutil.which("mavproxy.py") is None:
        return "MAVProxy not installed (pip install --no-deps MAVProxy)"
    return None


def start_soak(out: Path) -> subprocess.Popen:
    """tools/soak.py with SOAK_ARGS into ``out`` (its JSON summary to out/stdout.json, its
    messages to out/stderr.txt: files, so a long run never blocks on a full pipe). Its own
    process group: tests/conftest.py ends it (SIGTERM: the soak's cleanup runs) if pytest
    ends first."""
    out.mkdir(parents=True, exist_ok=True)
    # the soak holds the checkout's wall-clock lock while it runs (the fake GigE pair through
    # the daemon waits for it: tests/conftest.py wallclock_lock_path): taken here, handed to
    # the soak's process, which keeps it to its end
    from tests.conftest import hold_wallclock_lock
    lock, _ = hold_wallclock_lock()
    try:
        with open(out / "stdout.json", "w") as so, open(out / "stderr.txt", "w") as se:
            return subprocess.Popen([sys.executable, str(ROOT / "tools/soak.py"), *SOAK_ARGS,
                                     "--out", str(out), "--json"], stdout=so, stderr=se,
                                    cwd=str(ROOT), start_new_session=True,
                                    pass_fds=() if lock is None else (lock.fileno(),))
    finally:
        if lock is not None:
            lock.close()                # the soak's copy of the descriptor keeps the lock


def stop_soak(proc: subprocess.Popen) -> None:
    """End a soak still running: SIGTERM to its process group (its cleanup of the namespace
    and the emulators runs), SIGKILL if it has not ended 30 s later."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(30)
    except ProcessLookupError:
        pass
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_short_soak_no_false_clear_stop_within_two_cycles_no_fd_growth(tmp_path, background_soak):
    """Run alone, the soak is started here. In a plain `pytest` of the whole suite
    tests/conftest.py starts it at the beginning, while the modules that run in simulated time
    (no wall clock in what they assert) go first, and this test collects it: the soak's ~95 s
    overlap theirs. In `./tools/test.sh`'s first phase (pytest-xdist) this test runs first on
    one worker and starts it here, the other workers running those modules. The soak and its
    children run at nice -10, as the box would have its computer to itself."""
    why = soak_missing()
    if why:
        missing_tool(why)
    bg = background_soak
    out = bg[1] if bg else tmp_path / "soak"
    proc = bg[0] if bg else start_soak(out)
    try:
        rc = proc.wait(timeout=420)
    except subprocess.TimeoutExpired:
        stop_soak(proc)
        raise AssertionError("the soak ran past 420 s: " + (out / "stderr.txt").read_text()[-3000:])
    assert rc == 0, f"{out}: " + (out / "stderr.txt").read_text()[-3000:]
    s = json.loads((out / "stdout.json").read_text())
    full = json.loads((out / "summary.json").read_text())
    brief = json.dumps({k: v for k, v in s.items() if k not in ("by_kind", "status_cli")})
    detail = brief + json.dumps([f for f in full["faults"]
                                 if f.get("false_clears") or (f.get("stop_cycles_mav") or 0) > 2])
    # 20 are scheduled; each waits for the previous one's recovery (hold-off, reconnects), so a
    # machine shared with other work fits fewer (5 under a load of 50 on 2 cores)
    assert s["faults_injected"] >= 5, brief
    assert not s["tool_errors"], s["tool_errors"]
    assert s["false_clears"] == 0, detail
    assert not s["faults_without_stop"], s["faults_without_stop"]
    assert not s["runs_on_failures"], s["runs_on_failures"]     # clock steps change nothing
    assert s["stops_measured"] >= 4, brief
    assert s["max_stop_latency_cycles"] <= 2, detail
    assert s["max_stop_latency_cycles_can"] <= 2, detail
    assert s["recoveries"] == s["faults_injected"], full["faults"]
    assert s["fd_growth"] <= 0, brief
    assert s["judge_window_s"] == JUDGE_WINDOW_S, brief
    assert s["rss_judged_over_s"] >= JUDGE_WINDOW_S, brief  # the fd judgement above had its window
    # the daemon's own memory account was sampled (glibc): the soak can tell a leak from an
    # allocator keeping freed pages
    from appliance.memory import malloc_stats
    if malloc_stats() is not None:                       # glibc here, and in the daemon
        assert full["malloc_in_use_slope_mb_per_h"] is not None, brief
        assert full["py_blocks_slope_per_h"] is not None, brief
    for png in ("rss_fds.png", "timeline.png", "latency.png", "memory.png"):
        assert (out / png).stat().st_size > 1000
    # the window is what decides which process is judged: the same run judged again
    # (--analyse, on a copy of its events: it rewrites the summary and the plots) with a window
    # longer than the box ran after its warm-up judges none; one too short to have two halves
    # is refused, in words
    again_dir = tmp_path / "judged-again"
    again_dir.mkdir()
    shutil.copy(out / "events.json", again_dir / "events.json")
    tool = [sys.executable, str(ROOT / "tools/soak.py"), "--analyse", "--out", str(again_dir),
            *SOAK_ARGS]
    again = subprocess.run([*tool, "--judge-window", "120"], capture_output=True, text=True,
                           cwd=str(ROOT), timeout=120)
    assert again.returncode == 0, again.stderr[-2000:]
    judged_again = json.loads(again.stdout)
    assert judged_again["judge_window_s"] == 120 and judged_again["rss_judged_over_s"] == 0
    bad = subprocess.run([*tool, "--judge-window", "5"], capture_output=True, text=True,
                         cwd=str(ROOT), timeout=120)
    assert bad.returncode == 2 and "--judge-window must be at least 10 s" in bad.stderr
    assert "Traceback" not in bad.stderr
    if bg:                                   # kept when an assertion above failed, to look at
        shutil.rmtree(out, ignore_errors=True)


def test_stop_latency_counts_a_can_frame_in_the_cycle_that_sent_it():
    """The soak counts a STOP's latency in the box's cycles, one OBSTACLE_DISTANCE a cycle on
    the wire. A cycle's HEARTBEAT arrives just before its OBSTACLE_DISTANCE and its CAN frame just
    before or just after it; the hour at 34114a2 put CAN frames that came 0-8 ms after their
    cycle's OBSTACLE_DISTANCE a cycle later than the HEARTBEAT of the same cycle (3 cycles
    against 2 at the same millisecond)."""
    from tools.soak import wire_cycles
    od = [10.0 + 0.1 * i for i in range(10)]          # cycles' OBSTACLE_DISTANCE at 10.0 ... 10.9
    td = 10.05                                        # the fault became detectable
    assert wire_cycles(od, td, 10.099) == 1           # HEARTBEAT of the next cycle, before its OD
    assert wire_cycles(od, td, 10.102) == 1           # CAN frame of that cycle, 2 ms after its OD
    assert wire_cycles(od, td, 10.199) == 2           # the cycle after
    assert wire_cycles(od, td, 10.204) == 2
    assert wire_cycles(od, td, 10.299) == 3
    assert wire_cycles(od, td, 10.06) == 1            # within the cycle it became detectable in


def test_the_modules_run_beside_the_soak_exist():
    """tests/conftest.py runs these (simulated time only) while the soak runs, on every core:
    a renamed one would silently run alone after them, and the suite would grow by its time."""
    from tests.conftest import SIMULATED, SOAK_MODULE, SOAK_TEST
    missing = [m for m in (*SIMULATED, SOAK_MODULE) if not (ROOT / "tests" / m).is_file()]
    assert not missing, missing
    assert len(set(SIMULATED)) == len(SIMULATED)
    assert SOAK_TEST.startswith(f"tests/{SOAK_MODULE}::")
    path, name = SOAK_TEST.split("::")
    assert f"def {name}(" in (ROOT / path).read_text()
