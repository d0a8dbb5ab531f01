"""The planned path from an autopilot's mission (drivers/mission_path.py,
drivers/mavlink_mission.py): the legs' geometry, the mission protocol's download (retries,
changes, what is refused), the simulator's mission path, and the decision's heading check.
The link against the scripted vehicle through MAVProxy is in tests/test_mavlink_link.py."""
from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from appliance.config import ConfigError, parse_config
from appliance.decision import path_heading_deg
from drivers.mavlink_mission import MissionReader
from drivers.mission_path import local_en, path_ahead


# ---- geometry ------------------------------------------------------------------------------------
def test_path_runs_from_the_origin_to_the_waypoint_then_along_the_legs():
    wp = [(10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
    p = path_ahead((0.0, 0.0, 0.0), wp, 0, reach_m=15.0, step_m=0.5)
    assert np.allclose(p[0], [0, 0])
    assert np.allclose(p[-1], [10.0, 5.0])                    # 10 m to the corner, 5 m left
    s = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    assert abs(s[-1] - 15.0) < 1e-9 and np.all(np.diff(s) <= 0.5 + 1e-9)
    # the same world seen from a vehicle heading north (yaw 90 deg) at (0, 0): the waypoint
    # 10 m east is on its right
    q = path_ahead((0.0, 0.0, math.pi / 2), wp, 0, reach_m=15.0, step_m=0.5)
    assert np.allclose(q[20], [0.0, -10.0]) and np.allclose(q[-1], [5.0, -10.0])
    # from the second waypoint on; and a path shorter than the reach ends at the last one
    r = path_ahead((10.0, 2.0, math.pi / 2), wp, 1, reach_m=50.0)
    assert np.allclose(r[0], [0, 0]) and np.allclose(r[-1], [8.0, 10.0])


def test_no_path_past_the_last_waypoint_or_from_bad_numbers():
    wp = [(10.0, 0.0)]
    assert path_ahead((0, 0, 0), wp, 1) is None
    assert path_ahead((0, 0, 0), wp, -1) is None
    assert path_ahead((math.nan, 0, 0), wp, 0) is None
    assert path_ahead((0, 0, 0), [(math.inf, 0.0)], 0) is None
    assert path_ahead((10.0, 0.0, 0.0), wp, 0) is None       # standing on it: no length


def test_local_frame_of_latitude_and_longitude():
    e, n = local_en(-27.0 + 1e-5, 153.0 + 1e-5, -27.0, 153.0)
    assert abs(n - 1.1132) < 1e-3                             # 1e-5 deg of latitude
    assert abs(e - 1.1132 * math.cos(math.radians(-27.0))) < 1e-3


def test_heading_of_a_path():
    assert path_heading_deg(np.array([[0, 0], [2, 0]], float)) == 0.0
    assert abs(path_heading_deg(np.array([[0, 0], [0.5, 0.5], [0.5, 3]], float)) - 57.8) < 0.1
    assert path_heading_deg(np.array([[0, 0], [0, 0]], float)) is None


# ---- the mission protocol, as the box's side runs it -----------------------------------------------
class Wire:
    """What the reader sends (name, args) and a vehicle that answers on the next service."""

    def __init__(self, items):
        self.items, self.sent = items, []

    def __call__(self, name, *args):
        self.sent.append((name, args))


def _msg(t, **kw):
    kw.setdefault("target_system", 42)
    kw.setdefault("target_component", 196)
    kw.setdefault("mission_type", 0)
    return t, NS(**kw)


def _answer(reader, wire, now):
    """The vehicle's answer to the last request."""
    name, args = wire.sent[-1]
    if name == "mission_request_list":
        reader.on_message(*_msg("MISSION_COUNT", count=len(wire.items)), now)
    elif name == "mission_request_int":
        seq = args[0]
        cmd, frame, x, y = wire.items[seq]
        reader.on_message(*_msg("MISSION_ITEM_INT", seq=seq, command=cmd, frame=frame,
                                x=x, y=y), now)


def _download(reader, wire, now=0.0):
    for _ in range(100):
        reader.service(now, wire)
        if reader.state != "downloading":
            return
        _answer(reader, wire, now)
    raise AssertionError("no end to the download")


LAT0, LON0 = -27.0, 153.0
ITEMS = [(16, 0, int(LAT0 * 1e7), int(LON0 * 1e7)),                     # home
         (16, 6, int((LAT0 + 1e-4) * 1e7), int(LON0 * 1e7)),            # 11.1 m north
         (178, 0, 0, 0),                                                 # DO_CHANGE_SPEED
         (16, 6, int((LAT0 + 1e-4) * 1e7), int((LON0 + 1e-4) * 1e7))]   # then 9.9 m east


def test_download_then_the_path_while_in_auto_and_only_then():
    r = MissionReader(42, 196)
    w = Wire(ITEMS)
    _download(r, w)
    assert r.state == "ready" and r.status()["waypoints"] == 3
    assert w.sent[0] == ("mission_request_list", (0,))
    assert [a[0] for n, a in w.sent if n == "mission_request_int"] == [0, 1, 2, 3]
    assert w.sent[-1] == ("mission_ack", (0, 0))
    r.on_message("MISSION_CURRENT", NS(seq=1, total=3), 0.0)
    # at home, heading north: the first leg is straight ahead, the next on the right
    p, why = r.path(10, 0.0, global_pos=(LAT0, LON0))
    assert why == "" and np.allclose(p[0], [0, 0], atol=1e-6)
    assert abs(p[-1][0] - 11.13) < 0.02 and abs(p[-1][1] + (15 - 11.13)) < 0.03
    # after the DO command: seq 2 has no position, so the waypoint the vehicle heads for is 3
    r.on_message("MISSION_CURRENT", NS(seq=2, total=3), 0.0)
    p, _ = r.path(10, math.pi / 2, global_pos=(LAT0 + 1e-4, LON0))     # heading east at wp 1
    assert np.allclose(p[-1], [9.90, 0.0], atol=0.02)
    assert r.path(4, 0.0, global_pos=(LAT0, LON0)) == (None, "vehicle not in its mission "
                                                             "mode (custom mode 4)")
    assert r.path(10, 0.0, global_pos=None)[1] == "no fresh GLOBAL_POSITION_INT"
    r.on_message("MISSION_CURRENT", NS(seq=4, total=3), 0.0)
    assert r.path(10, 0.0, global_pos=(LAT0, LON0))[1] == "no waypoint left in the mission"


def test_requests_are_retried_then_the_download_fails_and_starts_again_later():
    r = MissionReader(42, 196, retry_s=0.5, retries=3)
    w = Wire(ITEMS)
    for k in range(10):                   # the vehicle never answers
        r.service(k * 0.25, w)
    assert [n for n, _ in w.sent] == ["mission_request_list"] * 3
    assert r.state == "failed" and r.failure == "no MISSION_COUNT after 3 requests"
    assert r.path(10, 0.0, global_pos=(LAT0, LON0))[1].startswith("mission failed: no "
                                                                   "MISSION_COUNT")
    r.service(3.0, w)
    assert r.state == "failed"            # a back-off before the next try
    _download(r, w, now=8.0)
    assert r.state == "ready" and r.status()["downloads"] == 2


def test_a_lost_item_is_asked_for_again():
    r = MissionReader(42, 196, retry_s=0.5)
    w = Wire(ITEMS)
    r.service(0.0, w)
    _answer(r, w, 0.0)
    r.service(0.0, w)                     # asks for item 0; the answer is lost
    r.service(0.2, w)
    assert w.sent[-1] == ("mission_request_int", (0, 0)) and len(w.sent) == 2
    r.service(0.6, w)                     # again after retry_s
    assert w.sent[-1] == ("mission_request_int", (0, 0)) and len(w.sent) == 3
    _download(r, w, 0.6)
    assert r.state == "ready"


def test_other_clients_traffic_is_not_taken_for_the_box():
    r = MissionReader(42, 196)
    w = Wire(ITEMS)
    r.service(0.0, w)
    # the vehicle answers a ground station (sysid 255) that asked at the same time
    r.on_message(*_msg("MISSION_COUNT", count=99, target_system=255), 0.0)
    r.on_message(*_msg("MISSION_COUNT", count=99, mission_type=1), 0.0)   # a fence list
    assert r.status()["items"] is None
    _answer(r, w, 0.0)
    assert r.status()["items"] == 4


def test_a_changed_mission_is_read_again_and_not_used_meanwhile():
    r = MissionReader(42, 196)
    w = Wire(ITEMS)
    r.on_message("MISSION_CURRENT", NS(seq=1, total=3), 0.0)
    _download(r, w)
    r.on_message("MISSION_CURRENT", NS(seq=1, total=3), 0.1)
    r.service(0.1, w)
    assert r.state == "ready"             # the same total: nothing to do
    r.on_message("MISSION_CURRENT", NS(seq=1, total=2), 0.2)   # someone uploaded another
    r.service(0.2, w)
    assert r.state == "downloading"
    assert r.path(10, 0.0, global_pos=(LAT0, LON0))[1] == "mission downloading"
    _download(r, w, 0.2)
    # the vehicle acknowledging someone else's upload also makes it read again
    r.on_message(*_msg("MISSION_ACK", type=0, target_system=255), 0.3)
    r.service(0.3, w)
    assert r.state == "downloading"
    _download(r, w, 0.3)
    # a periodic re-read keeps using the mission it has
    r.on_message("MISSION_CURRENT", NS(seq=1, total=2), 0.3)
    r.service(40.0, w)
    assert r.state == "downloading" and r.path(10, 0.0, global_pos=(LAT0, LON0))[1] == ""


@pytest.mark.parametrize("items, why", [
    ([(16, 6, 910000000, 0)], "item 0 has latitude/longitude out of range"),
    ([(16, 6, int(LAT0 * 1e7), int(LON0 * 1e7)), (16, 1, 10000, 0)],
     "the mission mixes global and local frames"),
    ([(16, 4, 1, 1)], "item 0 is in MAV_FRAME 4, which the box does not read"),
])
def test_missions_the_box_cannot_read_are_refused_with_the_reason(items, why):
    r = MissionReader(42, 196)
    _download(r, Wire(items))
    assert r.state == "failed" and r.failure == why


def test_too_long_a_mission_is_refused():
    r = MissionReader(42, 196, max_items=10)
    w = Wire(ITEMS * 5)
    _download(r, w)
    assert r.failure == "the mission has 20 items (more than 10)"


def test_local_ned_missions():
    r = MissionReader(42, 196)
    # MISSION_ITEM_INT local: metres x 1e4; x north, y east
    _download(r, Wire([(16, 1, 0, 0), (16, 1, 100000, 0), (16, 1, 100000, 50000)]))
    r.on_message("MISSION_CURRENT", NS(seq=1, total=2), 0.0)
    p, why = r.path(10, 0.0, local_pos=(0.0, 0.0))
    assert why == "" and np.allclose(p[-1], [10.0, -5.0])
    assert r.path(10, 0.0, global_pos=(LAT0, LON0))[1] == "no fresh LOCAL_POSITION_NED"


# ---- the simulator's mission path, and the config -------------------------------------------------
def test_simulated_mission_path_follows_the_lanes_ends():
    from drivers.sim.field import SimField
    f = SimField("greenhouse-coverage", seed=3, sensors=(), path="mission")
    v = f.vehicle
    xy, s = v.mission_waypoints()
    lanes = v.scene.lanes
    assert len(xy) == 2 * len(lanes) and np.isclose(s[1], lanes[0][1])
    p = f.vehicle_state(0, 1).path_xy
    assert np.allclose(p[0], [0, 0]) and np.allclose(p[:, 1], 0.0, atol=1e-6)  # along lane 0
    # in the turn the autopilot heads for the next lane's far end: the path heads off the
    # vehicle's heading (the decision does not use it then: path_max_heading_deg)
    heads = []
    while v.s < s[2] + 1.0:
        f.step(0.1, None)
        if v.s > s[1]:
            heads.append(path_heading_deg(f.vehicle_state(0, 1).path_xy))
    assert max(abs(h) for h in heads) > 80 and abs(heads[-1]) < 20
    g = SimField("greenhouse-coverage", seed=3, sensors=(), path="none")
    assert g.vehicle_state(0, 1).path_xy is None
    with pytest.raises(ValueError, match="unknown path source 'legs'"):
        SimField("greenhouse-coverage", seed=3, sensors=(), path="legs")


def test_sim_path_config_is_checked():
    cfg = parse_config({"sim": {"path": "mission", "mission_wp_radius_m": 1.5}}, "<t>")
    assert cfg.sim.path == "mission" and cfg.sim.mission_wp_radius_m == 1.5
    with pytest.raises(ConfigError, match="sim.path"):
        parse_config({"sim": {"path": "legs"}}, "<t>")
    with pytest.raises(ConfigError, match="path_max_heading_deg"):
        parse_config({"zones": {"path_max_heading_deg": -1}}, "<t>")


def test_decision_refuses_a_path_heading_off_the_vehicle():
    from appliance.decision import DecisionCore
    from hal.types import VehicleState
    cfg = parse_config({"zones": {"follow_path": True}}, "<t>")
    core = DecisionCore(cfg)
    side = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 5.0]])          # straight to the left
    bend = core._bend(VehicleState(0, 1, 1.0, 0.0, 0.0, 0.0, 0.0, path_xy=side))
    assert bend == 0.0 and core.path_refused == ("planned path not used: it heads +90 deg off "
                                                 "the vehicle's heading")
    ahead = np.array([[0.0, 0.0], [1.0, 0.3], [5.0, 1.0]])         # 17 deg: used
    bend = core._bend(VehicleState(0, 1, 1.0, 0.0, 0.0, 0.0, 0.0, path_xy=ahead))
    assert bend != 0.0 and core.path_refused == ""


def test_status_text_says_what_the_zones_lie_along():
    from appliance.cli import format_status
    o = {"occupied_cells": 0, "stop_zone_m": 2.0, "in_stop_zone": False, "in_slow_zone": False,
         "nearest_m": None, "zones_along": "planned path not used: it heads +90 deg off the "
                                           "vehicle's heading"}
    text = format_status({"obstacles": o})
    assert "zones   along planned path not used: it heads +90 deg" in text
    assert "zones   along" not in format_status({"obstacles": dict(o, zones_along=None)})


def test_the_link_hands_no_path_on_an_aged_position():
    """The MAVLink link lays the mission's path only on a position younger than its timeout:
    an aged GLOBAL_POSITION_INT (the autopilot stopped sending it) is no path, with the
    reason, while the same mission and mode with a fresh one give the path."""
    import time
    from drivers.mavlink_link import MavlinkVehicleLink
    from hal import MonotonicClock
    link = MavlinkVehicleLink("link", MonotonicClock(), 0.5, sysid=42, mission_path=True)
    _download(link.mission, Wire(ITEMS))
    link.mission.on_message("MISSION_CURRENT", NS(seq=1, total=3), 0.0)
    link._vehicle_mode = 10
    now = time.monotonic()
    link._gpos = (now - 0.1, LAT0, LON0)
    p = link._planned_path(now, 0.0)
    assert p is not None and link.path_refused == "" and link.counters["paths_sent"] == 1
    link._gpos = (now - 0.6, LAT0, LON0)               # older than the link's 0.5 s timeout
    assert link._planned_path(now, 0.0) is None
    assert link.path_refused == "no fresh GLOBAL_POSITION_INT"
    assert [x for x in link.peers() if x["role"] == "self"][0]["mission"]["path"] == \
        "no fresh GLOBAL_POSITION_INT"
    off = MavlinkVehicleLink("link", MonotonicClock(), 0.5, sysid=42)   # mission_path off
    assert off._planned_path(now, 0.0) is None and off.mission is None
