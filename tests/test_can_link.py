"""The CAN link between processes over a real python-can bus: udp_multicast on loopback inside
a network namespace this test creates (this machine's kernel has no SocketCAN). Peers: the
vehicle side (its own process, decoding with cantools from drivers/fieldguard.dbc and applying
the 300 ms / alive counter / CRC contract) and an independent J1939 stack (can-j1939) that
contests the box's address claim. The box side is the real appliance loop at 10 Hz."""
from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import time

import pytest

from tests.conftest import missing_tool

import can  # noqa: E402,F401
import cantools  # noqa: E402,F401
import msgpack  # noqa: E402,F401

from drivers.can_link import DEFAULT_DBC, CanJ1939VehicleLink  # noqa: E402
from drivers.j1939 import (AddressClaimer, ClaimState, J1939Id, J1939Name,  # noqa: E402
                           crc8_sae_j1850, make_id)
from hal import GateState, MonotonicClock  # noqa: E402
from hal.health import Health  # noqa: E402
from tools.linkrig import PY, ROOT, LoopRig, Peer, wait_for  # noqa: E402

GROUP = "239.74.163.2"
CLONE_NEWNET = 0x40000000
PEER_NAME = "0x0000000000000001"      # lower than the box's NAME: it wins the contest


# ---- pure J1939 logic ----------------------------------------------------------------------------
def test_crc_and_ids_and_claim_rules():
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert make_id(3, 0xFF50, 0x80) == 0x0CFF5080
    assert make_id(6, 60928, 0x80) == 0x18EEFF80
    box = AddressClaimer(J1939Name.parse("0xA00C810000E00001"), 0x80)
    box.start(0.0)
    winner = make_id(6, 60928, 0x80)
    out = box.on_frame(winner, (1).to_bytes(8, "little"), 0.1)      # lower NAME: we lose
    assert box.address == 0x81 and box.state == ClaimState.WAIT_VETO and out
    box.tick(0.2)
    assert not box.usable
    box.tick(0.4)
    assert box.usable
    loser = (0xFFFFFFFFFFFFFFFF).to_bytes(8, "little")
    out = box.on_frame(make_id(6, 60928, 0x81), loser, 0.5)          # higher NAME: we defend
    assert box.address == 0x81 and out[0].data == box.name.to_bytes()
    fixed = AddressClaimer(J1939Name.parse("0x200C810000E00001"), 0x80)   # not arbitrary
    fixed.start(0.0)
    out = fixed.on_frame(winner, (1).to_bytes(8, "little"), 0.1)
    assert fixed.state == ClaimState.CANNOT_CLAIM and out[0].can_id & 0xFF == 254


def test_error_frames_and_bus_off_are_faults():
    import can
    link = CanJ1939VehicleLink("can", MonotonicClock(), error_frames_per_s_fault=3)
    link._on_error_frame(can.Message(arbitration_id=0x40, is_error_frame=True), 1.0)
    assert link.health().state is Health.FAULT and "bus-off" in link.health().reason
    link.clear_fault()
    for i in range(3):
        link._on_error_frame(can.Message(arbitration_id=0x04, is_error_frame=True), 1.0 + i / 10)
    assert "error frames" in link.health().reason


def test_bus_off_is_held_over_the_next_speed_frame():
    """A bus-off used to be cleared by the next speed frame (<= 100 ms later), so the loop
    could miss it entirely: the soak's bus-offs never became a STOP. It is held fault_hold_s."""
    import can
    link = CanJ1939VehicleLink("can", MonotonicClock(), interface="virtual", channel="busoff")
    link.open()
    try:
        speed = link.speed_msg.encode({"WBSD_Speed": 1.0, "WBSD_Distance": 0,
                                       "WBSD_Direction": 1}, padding=True)
        jid = J1939Id.parse(make_id(3, 65096, 0xF0))
        link._on_speed(jid, speed)
        assert link.health().state is Health.OK
        link._on_error_frame(can.Message(arbitration_id=0x40, is_error_frame=True),
                             time.monotonic())
        link._on_speed(jid, speed)                    # the next speed frame: still FAULT
        assert link.health().state is Health.FAULT and "bus-off" in link.health().reason
        assert link.counters["speed_discarded"] == 1
        time.sleep(link.fault_hold_s + 0.05)
        link._on_speed(jid, speed)                    # after the hold: trusted again
        assert link.health().state is Health.OK
    finally:
        link.close()


# ---- between processes -----------------------------------------------------------------------------
def _ip(*args, check=True):
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def _setns(path: str) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(path, os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), "setns failed")
    finally:
        os.close(fd)


@pytest.fixture(scope="module")
def netns():
    if shutil.which("ip") is None:
        missing_tool("iproute2 not installed (tools/ci_system_deps.sh installs it)")
    name = f"fgcan{os.getpid()}"
    r = _ip("netns", "add", name, check=False)
    if r.returncode != 0:
        missing_tool(f"cannot create a network namespace here: {r.stderr.strip()}")
    try:
        for cmd in (["link", "set", "lo", "up"], ["link", "set", "lo", "multicast", "on"],
                    ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            _ip("netns", "exec", name, "ip", *cmd)
        home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        _setns(f"/var/run/netns/{name}")       # this thread (and its children) now live there
        try:
            yield name
        finally:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.setns(home, CLONE_NEWNET)
            os.close(home)
    finally:
        _ip("netns", "del", name, check=False)


@pytest.fixture(scope="module")
def canrig(netns):
    peer = Peer([PY, str(ROOT / "tests/peers/j1939_peer.py"), "udp_multicast", GROUP, "0x80",
                 PEER_NAME])
    # the emulator where the package is (the source tree, or the installed wheel: test_install)
    import drivers.emulators.can_vehicle as can_vehicle
    vehicle = Peer([PY, can_vehicle.__file__, "udp_multicast", GROUP,
                    DEFAULT_DBC])
    assert wait_for(lambda: peer.find(ev="ready") and vehicle.find(ev="ready"), 15), \
        peer.proc.stderr and "peers did not start"
    time.sleep(0.6)                            # the peer holds 0x80 before the box comes
    link = CanJ1939VehicleLink("link", MonotonicClock(), 0.3, interface="udp_multicast",
                               channel=GROUP, preferred_address=0x80)
    r = LoopRig(link).start()
    r.vehicle, r.peer = vehicle, peer
    yield r
    r.close()
    for p in (peer, vehicle):
        p.cmd("quit")
        p.stop()


def report(peer: Peer, ev=None):
    n = len(peer.events)
    peer.cmd("report")
    assert wait_for(lambda: len(peer.events) > n, 3)
    return peer.events[-1]


def test_contested_claim_then_status_frames_decode(canrig):
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 10), canrig.loop.gate.reason
    c = canrig.link.claimer
    assert c.address == 0x81 and c.lost >= 1 and c.state == ClaimState.CLAIMED
    time.sleep(1.0)
    rep = report(canrig.vehicle)
    # a handful of claims, not a storm (the peer once answered its own echo ~25 000 times a
    # second; the flood dropped frames on the way to the vehicle)
    assert len(rep["claims"]) < 50, f"{len(rep['claims'])} address claims on the bus"
    assert rep["status_ok"] > 5 and rep["bad_crc"] == 0 and rep["bad_counter"] == 0
    assert rep["sa"] == [0x81] and rep["sectors"] >= 12 * 5
    assert rep["last_status"]["FG_State"] == "CLEAR"
    assert rep["max_gap_ms"] < 300
    aiso = rep["aiso"]
    assert any(a[1] == 0 for a in aiso) and aiso[-1][1] == 1
    assert aiso[-1][2] == "ffffffffffff"                        # reserved bytes
    stop_n = [a[0] for a in aiso if a[1] == 0][-1]
    assert aiso[-1][0] == (stop_n + 1) % 256                     # transition counted
    p = report(canrig.peer)
    assert p["state"] == 2 and p["address"] == 0x80             # can-j1939 kept its address
    assert p["rx"].get(f"{0xFF50}:{0x81}", 0) > 5                # and sees the box's frames
    peers = canrig.link.peers()
    assert peers[0]["address"] == 0x81 and any(q.get("address") == 0x80 for q in peers[1:])


def test_obstacle_stop_reaches_the_vehicle(canrig):
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 10)
    canrig.laser.put_obstacle(4.0, 0.0)
    assert wait_for(lambda: canrig.state is GateState.STOP, 2)
    time.sleep(0.3)
    rep = report(canrig.vehicle)
    s = rep["last_status"]
    assert s["FG_State"] == "STOP" and s["FG_Zone"] == "StopZone"
    assert s["FG_ReasonCode"] == "ObstacleInStopZone"
    assert abs(s["FG_NearestDistance"] - 1.4) < 0.15 and abs(s["FG_NearestBearing"]) <= 2
    assert rep["aiso"][-1][1] == 0 and rep["vehicle_stop"]
    canrig.laser.clear()
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 5)


def test_silent_speed_peer_is_stop(canrig):
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 10)
    canrig.vehicle.cmd("silent")
    assert wait_for(lambda: canrig.link.health().state is Health.NO_DATA, 2)
    assert wait_for(lambda: canrig.state is GateState.STOP, 1)
    time.sleep(0.3)
    assert report(canrig.vehicle)["last_status"]["FG_State"] == "STOP"
    canrig.vehicle.cmd("talk")
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 5)


def test_bus_loss_is_stop_on_both_sides(canrig, netns):
    assert wait_for(lambda: canrig.state is GateState.CLEAR, 10)
    canrig.vehicle.cmd("reset")
    _ip("netns", "exec", netns, "ip", "link", "set", "lo", "down")
    try:
        assert wait_for(lambda: canrig.state is GateState.STOP, 2)
        assert wait_for(lambda: canrig.link.health().state is not Health.OK, 2)
        assert canrig.link.counters.get("tx_errors", 0) >= 1
        time.sleep(0.5)
        rep = report(canrig.vehicle)
        assert rep["vehicle_stop"] and rep["stops_by_timeout"] >= 1    # silence = STOP there
    finally:
        _ip("netns", "exec", netns, "ip", "link", "set", "lo", "up")
        _ip("netns", "exec", netns, "ip", "route", "add", "224.0.0.0/4", "dev", "lo",
            check=False)
