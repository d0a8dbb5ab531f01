"""[zones] follow_path: the stop and slow zones laid along the path the vehicle will drive.

The greenhouse's remaining false stops were the end of the next bush row straight ahead of a
sprayer coming out of a U-turn (docs/rgbd.md, docs/zones.md); the present curvature bends the
zones past the aisle, the route's mean curvature not enough. The planned path itself (an
autopilot's, the simulator's route) says what the vehicle will drive over."""
from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.config import Config, GateConfig, ZonesConfig, parse_config
from appliance.decision import DecisionCore
from appliance.evaluation import decision_record
from appliance.perception import Detections
from appliance.zones import PathBend, same_bend, zone_outline, zone_rects
from hal import GateState
from hal.errors import ConfigError
from hal.types import VehicleState
from tests.test_follow_turn import _blob, _gh          # the greenhouse sprayer's zones; a post

S = 10**9
DT = S // 10
F, HW = 1.1, 0.5                  # the greenhouse sprayer's front and half width


def arc_path(k, length=6.0, n=121):
    """The origin's path along a circle of curvature ``k`` (left positive), from the origin."""
    s = np.linspace(0.0, length, n)
    if abs(k) < 1e-12:
        return np.stack([s, np.zeros(n)], axis=1)
    r = 1.0 / k
    return np.stack([r * np.sin(k * s), r * (1 - np.cos(k * s))], axis=1)


def u_turn(gap=1.6, straight=1.0, step=0.05):
    """Out of an aisle: ``straight`` m ahead, a half circle to the left of diameter ``gap``,
    then back along the next aisle."""
    a = np.arange(0.0, straight, step)
    leg1 = np.stack([a, np.zeros_like(a)], axis=1)
    r = gap / 2
    th = np.arange(0.0, math.pi, step / r)
    turn = np.stack([straight + r * np.sin(th), r * (1 - np.cos(th))], axis=1)
    b = np.arange(0.0, 4.0, step)
    leg2 = np.stack([straight - b, np.full_like(b, gap)], axis=1)
    return np.concatenate([leg1, turn, leg2])


def test_a_straight_path_is_the_straight_zones():
    rng = np.random.default_rng(0)
    q = rng.uniform([-1, -3], [20, 3], (300, 2))
    pb = PathBend(arc_path(0.0, 12.0), F, HW, reach_m=25.0)
    assert np.array_equal(pb.to_frame(q), q) and np.array_equal(pb.from_frame(q), q)
    # nearly straight (a 1000 km radius): what lies ahead of the front is where it was, to
    # within the placing of the body (every 5 cm, interpolated)
    pb = PathBend(arc_path(1e-6, 12.0), F, HW, reach_m=12.0)
    assert not pb.straight
    ahead = (q[:, 0] > F + 0.1) & (q[:, 0] < 12.0)
    assert np.allclose(pb.to_frame(q)[ahead], q[ahead], atol=1e-3)
    beside = q[:, 0] <= F                          # beside or behind the body: its own
    assert np.array_equal(pb.to_frame(q)[beside], q[beside])


def test_in_a_turn_the_body_sweeps_what_is_beside_it_and_misses_what_is_straight_ahead():
    """The zones are what the body sweeps: in a tight left turn the inner side of the body
    meets a crate standing beside its front corner (the straight zones never hold it: behind
    the front), and a row's end straight ahead of the front, outside the turn, is never met.
    The front's own track would have missed the first (training seed 28's crate)."""
    path = arc_path(1.0 / 0.9, 4.0, 401)
    pb = PathBend(path, F, HW, reach_m=4.0)
    crate = np.array([[F - 0.2, HW + 0.15]])        # beside the front's left corner
    row_end = np.array([[F + 0.7, -0.1]])           # straight ahead, 0.7 m
    x, y = pb.to_frame(crate)[0]
    assert F < x < F + 1.0 and abs(y) <= HW         # met within the first metre
    x, y = pb.to_frame(row_end)[0]
    assert abs(y) > HW                               # never met
    # the body placed at that distance along the path does cover the crate
    s = pb.to_frame(crate)[0, 0] - F + 0.05
    i = int(np.searchsorted(pb.s, s))
    bx, by = pb._body(crate)
    assert 0.0 <= bx[0, i] <= F and abs(by[0, i]) <= HW
    # the tail swings out: a post just beside the rear corner on the outside of the turn is
    # met by a body that reaches 0.5 m behind its origin, not by one that ends there
    post = np.array([[-0.2, -(HW + 0.04)]])
    assert abs(pb.to_frame(post)[0, 1]) > HW
    x, y = PathBend(path, F, HW, reach_m=4.0, rear_m=0.5).to_frame(post)[0]
    assert F < x < F + 1.0 and abs(y) <= HW
    # a U-turn's second pass through the same place counts at the first
    u = u_turn(gap=1.6, straight=3.0)
    pb = PathBend(u, F, HW, reach_m=12.0)
    x, y = pb.to_frame(np.array([[F + 1.0, 0.0]]))[0]
    assert x == pytest.approx(F + 1.0, abs=0.01) and y == pytest.approx(0.0, abs=1e-6)


def test_the_planned_path_is_checked_and_without_one_the_zones_are_straight():
    assert ZonesConfig().follow_path is False
    cfg = parse_config({"zones": {"follow_path": True, "path_max_offset_m": 0.3}}, "t")
    assert cfg.zones.follow_path and cfg.zones.path_max_offset_m == 0.3
    with pytest.raises(ConfigError, match="path_max_offset_m"):
        parse_config({"zones": {"path_max_offset_m": -1}}, "t")
    with pytest.raises(ValueError, match="two distinct points"):
        PathBend(np.zeros((3, 2)), F, HW)
    core = DecisionCore(_gh(follow_path=True))
    for path, why in ((None, "no planned path"),
                      (np.array([[2.0, 0.0], [5.0, 0.0]]), "starts 2.00 m from the vehicle"),
                      (np.array([[math.nan, 0.0], [5.0, 0.0]]), "not numbers"),
                      (np.array([[0.0, 0.0], [2.0, math.inf], [4.0, 0.0]]), "not numbers"),
                      (np.array([[0.0, 0.0]]), "two distinct points"),
                      (np.zeros((0, 2)), "no points"),
                      (np.zeros((2, 3)), "not a list of (x, y) points"),
                      ("north", "planned path not used")):
        v = VehicleState(0, 0, speed_mps=0.5, path_xy=path)
        assert core._bend(v) == 0.0
        assert why in core.path_refused and core.path_refused
    # the usual case, and off: nothing read
    assert isinstance(core._bend(VehicleState(0, 0, path_xy=u_turn())), PathBend)
    assert core.path_refused == ""
    assert DecisionCore(_gh())._bend(VehicleState(0, 0, path_xy=u_turn())) == 0.0


def _drive(core, pts, path, n=4):
    out = pic = None
    for k in range(n):
        v = VehicleState(k * DT, k, speed_mps=0.1, yaw_rate_radps=0.1, path_xy=path)
        pic = core.perceive({"rgbd": Detections(points_xy=pts)}, v, k * DT)
        out = core.decide(k * DT, [], pic)
    return out, pic


def test_the_row_end_off_the_path_is_no_stop_and_the_crate_on_it_is():
    # the vehicle 40 degrees into its turn out of the aisle: the path bends left at once
    path = arc_path(1.0 / 0.8, 3.0)
    ahead = _blob((F + 0.7, 0.0))            # the row's end straight ahead, 0.7 m
    on_path = _blob(PathBend(path, F, HW).from_frame(np.array([[F + 1.2, 0.0]]))[0])
    assert abs(on_path[4, 1]) > HW + 0.3     # far to the left: beside the straight zone
    out, _ = _drive(DecisionCore(_gh()), ahead, path)
    assert out.state is GateState.STOP
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), ahead, path)
    assert out.state is not GateState.STOP and pic.verdict.in_stop == 0
    assert pic.verdict.path is not None and same_bend(pic.verdict.bend, pic.verdict.path)
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), on_path, path)
    assert out.state is GateState.STOP
    assert pic.verdict.nearest_m == pytest.approx(1.2, abs=0.15)   # along the path
    # the same with a path that goes straight on: the row's end is a STOP again
    out, _ = _drive(DecisionCore(_gh(follow_path=True)), ahead, arc_path(0.0, 3.0))
    assert out.state is GateState.STOP
    # and without the path this cycle (the autopilot stopped sending it): straight
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), ahead, None)
    assert out.state is GateState.STOP and pic.verdict.path is None


def test_the_eval_record_and_the_snapshot_carry_the_path():
    path = arc_path(1.0 / 0.8, 3.0)
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), _blob((F + 1.5, 2.0)), path)
    rec = decision_record(3, 3 * DT, out, pic, zone_rects(0.1, _gh().zones), "clear")
    assert len(rec["path_xy"]) == len(path) and rec["path_xy"][0] == [0.0, 0.0]
    outline = zone_outline(F, F + 2.0, HW, pic.verdict.bend, F)
    # the stop zone's outline follows the path: its far end is to the left, not ahead
    assert outline[:, 1].max() > 1.0 and outline[:, 0].max() < F + 2.0 - 0.3


def test_the_simulator_sends_its_route_ahead():
    from drivers.sim.scenes import build_scene
    from drivers.sim.vehicle import Vehicle
    sc = build_scene("greenhouse-coverage", seed=7)
    v = Vehicle(sc, seed=7)
    v.s = 5.0
    p = v.planned_path(reach_m=3.0, step_m=0.25)
    assert np.allclose(p[0], 0.0, atol=1e-9)             # from the origin
    assert np.hypot(*np.diff(p, axis=0).T).sum() == pytest.approx(3.0, abs=0.05)
    assert np.all(np.hypot(p[:, 0], p[:, 1]) <= 3.0 + 1e-6)


def test_a_box_set_to_follow_a_path_that_gets_none_stops_on_straight_zones_and_says_so():
    """The link sends no planned path (an autopilot that does not plan one, or a tractor):
    the zones stay straight, a post ahead is a STOP, and status says why."""
    from tests.test_decision import make_loop
    clock, loop, laser, link = make_loop(Config(gate=GateConfig(hold_off_s=0.3),
                                                zones=ZonesConfig(follow_path=True)))
    for _ in range(4):
        loop.cycle()
        clock.advance(DT)
    assert loop.status()["obstacles"]["zones_along"] == "no planned path"
    laser.put_obstacle(4.0, 0.0)
    states = []
    for _ in range(8):
        states.append(loop.cycle().output.state)
        clock.advance(DT)
    assert states[-1] is GateState.STOP and link.sent[-1].state is GateState.STOP
    clock, loop, laser, link = make_loop(Config())      # off: the key says so
    loop.cycle()
    assert loop.status()["obstacles"]["zones_along"] is None


def test_the_campaign_judges_contact_and_held_cells_in_the_vehicle_frame():
    """The campaign's truth in the zones' frame of a box that follows its path, and beside it
    what a collision's contact part and the box's cells are judged by: the footprint in the
    vehicle frame and the straight corridor, the same as for a box with straight zones."""
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    data = deep_merge(drive_config_data("greenhouse-coverage", 7),
                      {"zones": {"follow_path": True}})
    drv = Drive("greenhouse-coverage", 7, 0.01, config_data=data).build()
    try:
        v = drv.vehicle
        turns = np.flatnonzero(np.abs(np.diff(v._yaw)) > 0.02)
        v.s = float(v._s[turns[0]]) - 0.3            # entering the first U-turn
        bend = DecisionCore(parse_config(data, "t"))._bend(
            VehicleState(0, 0, speed_mps=0.7, path_xy=v.planned_path()))
        assert isinstance(bend, PathBend)
        bent, straight = drv.truth(2.0, bend), drv.truth(2.0, 0.0)
        assert [o["id"] for o in bent] == [o["id"] for o in straight] and bent
        for b, s_ in zip(bent, straight):
            assert np.array_equal(b["pts_vehicle"], s_["pts"])
            assert b["ahead_straight"] == s_["ahead"] == s_["ahead_straight"]
        assert any(not np.allclose(b["pts"], b["pts_vehicle"]) for b in bent)
    finally:
        drv.daemon.shutdown()


def test_the_campaign_judges_a_path_box_on_the_route_driven_not_on_its_own_path():
    """A box following an autopilot's legs ([sim] path = "mission") lays its zones where the
    vehicle does not drive in a turn; the campaign judges what was in the zones along the
    route the vehicle really drives: the same truth as for a box given the route itself."""
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    data = deep_merge(drive_config_data("greenhouse-coverage", 7),
                      {"zones": {"follow_path": True}, "sim": {"path": "mission"}})
    drv = Drive("greenhouse-coverage", 7, 0.01, config_data=data).build()
    try:
        v = drv.vehicle
        turns = np.flatnonzero(np.abs(np.diff(v._yaw)) > 0.02)
        v.s = float(v._s[turns[0]]) + 1.0             # in the first U-turn
        route = DecisionCore(parse_config(data, "t"))._bend(
            VehicleState(0, 0, speed_mps=0.7, path_xy=v.planned_path()))
        legs = PathBend(v.mission_path(), route.front_x_m, route.half_width_m,
                        reach_m=route.reach_m, rear_m=route.rear_m)
        assert not np.allclose(legs.o, route.o, atol=0.3)      # the legs cut the turn
        driven = drv._driven(legs)
        assert np.allclose(driven.o, route.o) and np.allclose(driven.yaw, route.yaw)
        by_legs, by_route = drv.truth(2.0, legs), drv.truth(2.0, route)
        assert by_route and [o["id"] for o in by_legs] == [o["id"] for o in by_route]
        for a, b in zip(by_legs, by_route):
            assert np.array_equal(a["pts"], b["pts"]) and a["deep"] == b["deep"]
    finally:
        drv.daemon.shutdown()
