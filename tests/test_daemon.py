"""The daemon end to end on replays: the fail-safe property over whole runs, status, CLI."""
import dataclasses
import json
import threading
import time

import numpy as np
import pytest

from appliance.cli import main
from appliance.config import GateConfig, default_config
from appliance.daemon import Daemon, replay_config
from drivers.runfolder import RunWriter
from hal import GateState, LaserScan, VehicleState
from tests.fakes import geometry

DROPPED = set(range(20, 26))          # a loose connector: 6 frames (0.6 s) with no scan
OBSTACLE = set(range(30, 36))         # a person 4 m ahead


def write_laser_run(path, n=60):
    geo = geometry()
    with RunWriter(path, "laser-faults", laser=geo) as w:
        for i in range(n):
            r = np.full(geo.beams, np.nan, np.float32)
            if i in OBSTACLE:
                r[265:276] = 4.0 - geo.mount.x_m
            scan = None if i in DROPPED else LaserScan(i * 10**8, i, r, geo)
            w.write_frame(i, i * 10**8, vehicle=VehicleState(i * 10**8, i, speed_mps=1.0),
                          laser=scan, truth=[])
    return path


def run_replay(path, hold_off=0.3, cycles=None):
    cfg = dataclasses.replace(default_config(), gate=GateConfig(hold_off_s=hold_off))
    d = Daemon(replay_config(cfg, str(path)), mode="replay", replay_path=str(path), pace=0.0,
               serve_status=False)
    d.start()
    log = []
    d.loop.on_cycle.append(lambda r: log.append(r))
    d.run(max_cycles=cycles or 70)
    d.shutdown()
    return d, log


def test_no_clear_while_a_required_source_is_stale(tmp_path):
    path = write_laser_run(tmp_path / "run")
    d, log = run_replay(path)
    timeout = d.devices["laser"].timeout_s
    start = log[0].stamp_ns
    seen_clear = False
    for r in log:
        t = (r.stamp_ns - start) / 1e9
        # computed from the run itself, not from the gate: the newest scan that exists and is due
        due = [k for k in range(60) if k * 0.1 <= t + 1e-9 and k not in DROPPED]
        stale = not due or (t - due[-1] * 0.1) > timeout + 1e-9
        if stale:
            assert r.output.state is not GateState.CLEAR, (t, r.output.reason)
        seen_clear |= r.output.state is GateState.CLEAR
    assert seen_clear, "the replay never cleared: the property would hold vacuously"
    by_t = {round((r.stamp_ns - start) / 1e8): r.output for r in log}
    # the dropout is seen: STOP naming the laser within two cycles of the timeout
    first = min(k for k, o in by_t.items() if k >= 20 and o.state is GateState.STOP)
    assert first <= 19 + int(timeout * 10) + 2
    assert "laser" in by_t[first].reason
    # the obstacle at 4 m is a STOP with its distance
    assert any(by_t[k].state is GateState.STOP and "stop zone" in by_t[k].reason
               for k in OBSTACLE)
    # after the run ends the data goes stale: STOP
    assert log[-1].output.state is GateState.STOP
    # the link was told STOP last, on shutdown
    assert d.devices["link"].sent[-1].state is GateState.STOP


def test_replay_is_deterministic(tmp_path):
    path = write_laser_run(tmp_path / "run")
    _, a = run_replay(path)
    _, b = run_replay(path)
    assert [(r.output.state, r.output.reason) for r in a] == \
           [(r.output.state, r.output.reason) for r in b]


def test_status_cli_against_running_daemon(tmp_path, capsys):
    path = write_laser_run(tmp_path / "run", n=600)
    sock = str(tmp_path / "status.sock")
    cfg = replay_config(default_config(), str(path))
    d = Daemon(cfg, mode="replay", replay_path=str(path), pace=1.0, status_socket=sock)
    d.start()
    th = threading.Thread(target=d.run, kwargs={"max_cycles": 600}, daemon=True)
    th.start()
    try:
        time.sleep(0.8)
        rc = main(["status", "--json", "--socket", sock])
        doc = json.loads(capsys.readouterr().out)
        assert doc["mode"] == "replay"
        assert doc["devices"]["laser"]["state"] in ("ok", "no_data")
        assert doc["cycles"] > 0 and "p99" in doc["timing_ms"]["cycle"]
        assert rc in (0, 1)
        rc = main(["status", "--socket", sock])
        text = capsys.readouterr().out
        assert "state" in text and "laser" in text and "loop" in text
    finally:
        d.request_stop()
        th.join(5)
        d.shutdown()
    assert main(["status", "--socket", sock]) == 2
    assert "no fieldguard daemon" in capsys.readouterr().err


def test_run_without_devices_is_a_clear_error(tmp_path, capsys):
    cfg = tmp_path / "empty.toml"
    cfg.write_text("[loop]\nrate_hz = 10\n")
    assert main(["run", "--config", str(cfg)]) == 2
    assert "no [devices]" in capsys.readouterr().err


def test_bad_run_folder_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "run").mkdir()
    assert main(["run", "--replay", str(tmp_path / "run"), "--fast"]) == 2
    assert "run.toml" in capsys.readouterr().err


@pytest.mark.parametrize("table, period", [
    ({"rgbd": {"type": "freenect", "timeout_s": 0.06}}, "1 / max_fps"),
    ({"rgbd": {"type": "freenect", "max_fps": 5.0, "timeout_s": 0.13}}, "1 / max_fps"),
    ({"trigger": {"type": "serial", "timeout_s": 0.04}}, "status_period_s"),
    ({"stereo": {"type": "aravis", "left": "a", "right": "b", "calibration": "c.json",
                 "rate_hz": 5.0}}, "1 / rate_hz"),
    ({"laser": {"type": "sick-lms1xx", "timeout_s": 0.03}}, "25 Hz"),
    ({"trigger": {"type": "serial", "night_below": 60.0}}, None)])
def test_hardware_settings_that_cannot_work_stop_start_up(table, period):
    """A timeout not longer than the device's period (it would never be fresh: a STOP that
    never clears, for a typo) or day/night thresholds without a gap: ConfigError at start."""
    from appliance.config import parse_config
    from appliance.daemon import Daemon
    from hal.errors import ConfigError
    cfg = parse_config({"devices": {**table, "link": {"type": "log"}}}, "hw.toml")
    d = Daemon(cfg, mode="hardware", serve_status=False)
    pattern = (r"night_below\] must be lower than day_above" if period is None else
               r"timeout_s .* must be longer than .*" + period.replace("(", r"\("))
    with pytest.raises(ConfigError, match=pattern):
        d.start()
    d.shutdown()
