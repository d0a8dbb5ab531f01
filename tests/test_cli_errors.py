"""No traceback ever reaches a user: every mistake a user can make on the command line is one
`fieldguard: error: ...` line naming what and what to do, exit 2; anything unexpected is
`fieldguard: error: internal error: ...` with the traceback in a log file, exit 2. And
`config check` refuses what `run` refuses (issue #16)."""
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def fg(*args, timeout=120, cwd=None):
    r = subprocess.run([sys.executable, "-m", "appliance.cli", *map(str, args)],
                       capture_output=True, text=True, timeout=timeout, cwd=cwd or ROOT)
    return r.returncode, r.stdout, r.stderr


def fg_in(capsys, *args):
    """`fg` in this process, for a message and exit code that do not depend on being a process
    of its own (no daemon, no signal, no socket to another process): `main` returns what the
    process would exit with; an argparse error is its SystemExit code. (tests/conftest.py puts
    back the root logger `main` points at the captured stderr.)"""
    from appliance.cli import main
    capsys.readouterr()                            # only this call's output
    try:
        rc = main([*map(str, args)])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_user_error(rc, out, err, *needles):
    assert "Traceback" not in out + err, err
    assert rc == 2, (rc, out, err)
    line = err.strip().splitlines()[-1]
    assert line.startswith("fieldguard: error: "), err
    assert "internal error" not in line, line
    for n in needles:
        assert n in line, (n, line)


# ---- run and sim --------------------------------------------------------------------------
def test_run_sim_unknown_scene(capsys):
    assert_user_error(*fg_in(capsys, "run", "--sim", "nosuchscene", "--duration", "0.1"),
                      "unknown scene 'nosuchscene'", "stubble-day")


def test_run_sim_misspelt_scene_says_did_you_mean(capsys):
    assert_user_error(*fg_in(capsys, "run", "--sim", "stuble-day", "--duration", "0.1"),
                      "did you mean 'stubble-day'?")


def test_sim_unknown_scene(tmp_path, capsys):
    assert_user_error(*fg_in(capsys, "sim", "nosuchscene", "--out", tmp_path / "r"),
                      "unknown scene 'nosuchscene'")
    assert not (tmp_path / "r").exists()


def test_sim_zero_frames(tmp_path, capsys):
    assert_user_error(*fg_in(capsys, "sim", "stubble-day", "--frames", "0",
                             "--out", tmp_path / "r"), "--frames must be at least 1")


def test_sim_unknown_sensor(tmp_path, capsys):
    assert_user_error(*fg_in(capsys, "sim", "stubble-day", "--frames", "1", "--sensors", "lidar",
                          "--out", tmp_path / "r"), "'lidar'", "stereo, laser, rgbd")


def test_sim_unwritable_out(capsys):
    assert_user_error(*fg_in(capsys, "sim", "stubble-day", "--frames", "1", "--sensors", "laser",
                          "--out", "/proc/x"), "cannot write the run folder /proc/x",
                      "--out")


# ---- no daemon answering ------------------------------------------------------------------
def test_no_daemon_is_a_user_error(tmp_path, capsys):
    for cmd in (("status",), ("snapshot", "-o", tmp_path / "x.png"),
                ("record", "--seconds", "1", "--out", tmp_path / "rec")):
        assert_user_error(*fg_in(capsys, *cmd, "--socket", tmp_path / "none.sock"),
                          "no fieldguard daemon is answering", "--socket")


# ---- config check runs every check run runs -----------------------------------------------
def test_config_check_catches_a_misspelt_scene(tmp_path, capsys):
    f = tmp_path / "c.toml"
    f.write_text('[sim]\nscene = "stuble-day"\n')
    assert_user_error(*fg_in(capsys, "config", "check", "--sim", f), "[sim.scene]",
                      "did you mean 'stubble-day'?")
    assert_user_error(*fg_in(capsys, "run", "--sim", "--config", f, "--duration", "0.1"),
                      "[sim.scene]", "did you mean 'stubble-day'?")


def test_empty_config_check_and_run_agree(tmp_path, capsys):
    """An empty file is the built-in defaults: no devices. `run --config` refuses it, so
    `config check` (what the unit runs before `run --config`) refuses it too; with --sim both
    accept it."""
    f = tmp_path / "empty.toml"
    f.write_text("")
    assert_user_error(*fg_in(capsys, "config", "check", f), "no [devices] configured", "--sim")
    assert_user_error(*fg_in(capsys, "run", "--config", f, "--duration", "0.1"),
                      "no [devices] configured")
    rc, out, err = fg_in(capsys, "config", "check", "--sim", f)
    assert rc == 0 and "OK" in out, err
    # a real daemon (signal handlers, a status socket): a process of its own
    rc, out, err = fg("run", "--sim", "--config", f, "--duration", "0.3", "--fast",
                      "--socket", tmp_path / "s.sock")
    assert rc == 0 and "Traceback" not in err, err


def test_bad_mavlink_connection_is_refused_by_check_and_run(tmp_path, capsys):
    f = tmp_path / "c.toml"
    f.write_text('[devices.laser]\ntype = "sim"\n\n[devices.link]\ntype = "mavlink"\n'
                 'connection = "udp-out:127.0.0.1"\n')
    for cmd in (("config", "check", f), ("run", "--config", f, "--duration", "0.1")):
        assert_user_error(*fg_in(capsys, *cmd), "[devices.link.connection]", "udp-out:127.0.0.1",
                          "udpout:HOST:PORT")


@pytest.mark.parametrize("conn, ok", [("udpout:127.0.0.1:14550", True),
                                      ("tcp:10.0.0.2:5760", True), ("/dev/ttyACM0", True),
                                      ("udpout:127.0.0.1", False), ("udpout:host:0", False),
                                      ("serial0", False), ("udp-in:0.0.0.0:14550", False)])
def test_mavlink_connection_syntax(conn, ok):
    from appliance.config import parse_config
    from hal.errors import ConfigError
    data = {"devices": {"laser": {"type": "sim"},
                        "link": {"type": "mavlink", "connection": conn}}}
    if ok:
        parse_config(data, "t.toml")
    else:
        with pytest.raises(ConfigError, match=r"\[devices\.link\.connection\]"):
            parse_config(data, "t.toml")


@pytest.mark.parametrize("conn", ["udpout:127.0.0.1:14550", "/dev/ttyACM0"])
@pytest.mark.parametrize("opts, key", [({"sysid": 0}, "sysid"), ({"sysid": 256}, "sysid"),
                                       ({"target_system": 300}, "target_system"),
                                       ({"stream_hz": 0.0}, "stream_hz"),
                                       ({"heartbeat_hz": -1.0}, "heartbeat_hz"),
                                       ({"min_distance_cm": 500, "max_distance_cm": 400},
                                        "max_distance_cm"),
                                       ({"max_distance_cm": 70000}, "max_distance_cm")])
def test_mavlink_numbers_are_checked_for_serial_links_too(conn, opts, key):
    """sysid = 0 with a serial connection passed the config and reached the link's constructor
    as a ValueError (tests/fuzz/fuzz_config.py; corpus regress-sysid-0-serial-path): every
    number is now checked whatever the connection, and named."""
    from appliance.config import parse_config
    from hal.errors import ConfigError
    data = {"devices": {"laser": {"type": "sim"},
                        "link": {"type": "mavlink", "connection": conn, **opts}}}
    with pytest.raises(ConfigError, match=rf"\[devices\.link\.{key}\]"):
        parse_config(data, "t.toml")


# ---- the guard: an exception nobody meant -------------------------------------------------
def test_unexpected_exception_is_one_line_and_the_traceback_goes_to_a_log(monkeypatch, capsys,
                                                                         tmp_path):
    from appliance import cli

    def boom(a):
        raise KeyError("a bug")

    monkeypatch.setattr(cli, "cmd_config_check", boom)
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path))
    rc = cli.main(["config", "check", "x.toml"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert re.fullmatch(r"fieldguard: error: internal error: KeyError: 'a bug' \(please report; "
                        r"details in (\S+)\)", line), line
    logged = Path(line.rsplit(" ", 1)[-1].rstrip(")")).read_text()
    assert "Traceback" in logged and "boom" in logged and "KeyError: 'a bug'" in logged


# ---- a running daemon: a second one, snapshot -o DIR ---------------------------------------
# Last in the module: a module fixture lives until the module ends, and this real daemon
# (a process of its own, in real time) costs ~0.4 CPU-s a second while it runs.
# The commands against it stay processes of their own: a socket between two processes.
@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    from appliance.status import read_status
    d = tmp_path_factory.mktemp("d")
    sock = d / "status.sock"
    log = open(d / "daemon.log", "w")
    p = subprocess.Popen([sys.executable, "-m", "appliance.cli", "run", "--sim",
                          "--socket", str(sock)], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300          # a loaded host starts slowly
        while time.monotonic() < deadline:
            if sock.is_socket():
                # what `fieldguard status --json` reads, asked from this process (a `status`
                # process per poll cost ~0.5 CPU-s); no answer yet is its rc 2
                try:
                    st = read_status(str(sock))
                except (ConnectionError, OSError, ValueError):
                    st = None
                if st is not None and st.get("cycles") != 0:
                    break
            assert p.poll() is None, (d / "daemon.log").read_text()
            time.sleep(0.3)
        else:
            pytest.fail("daemon did not come up: " + (d / "daemon.log").read_text())
        yield sock
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=120)
        log.close()


def test_second_daemon_on_the_same_socket_says_so(daemon):
    assert_user_error(*fg("run", "--sim", "--socket", daemon, "--duration", "1"),
                      f"another fieldguard daemon is answering on {daemon}", "--socket")
    # and the first one still answers: the refused daemon did not remove its socket
    rc, out, err = fg("status", "--socket", daemon)
    assert rc in (0, 1) and "state" in out, err


def test_snapshot_into_a_folder(daemon, tmp_path):
    rc, out, err = fg("snapshot", "-o", tmp_path, "--socket", daemon)
    assert rc == 0 and "Traceback" not in err, err
    pngs = list(tmp_path.glob("fieldguard-snapshot-*.png"))
    assert len(pngs) == 1 and pngs[0].read_bytes()[:4] == b"\x89PNG"


def test_snapshot_unwritable(daemon):
    assert_user_error(*fg("snapshot", "-o", "/proc/nope/x.png", "--socket", daemon),
                      "cannot write /proc/nope/x.png")
