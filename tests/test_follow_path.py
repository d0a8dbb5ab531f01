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
from appliance.zones import PathBend, same_bend, to_path_frame, zone_outline, zone_rects
from hal import GateState
from hal.errors import ConfigError
from hal.types import VehicleState

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


def test_a_straight_path_is_the_straight_zones_and_an_arc_is_follow_turn_s_arc():
    rng = np.random.default_rng(0)
    q = rng.uniform([-1, -3], [20, 3], (300, 2))
    pb = PathBend(arc_path(0.0, 12.0), F)
    assert np.allclose(pb.to_frame(q), q, atol=1e-9)
    assert np.allclose(pb.from_frame(q), q, atol=1e-9)
    # along a circle the path's frame is the front's circle of [zones] follow_turn (up to the
    # polyline's chords), away from the front's own corner
    for k in (0.4, -0.7):
        pb = PathBend(arc_path(k, 4.0, 401), F)
        q = rng.uniform([F + 0.3, -0.4], [F + 1.5, 0.4], (100, 2))
        assert np.allclose(pb.to_frame(q), to_path_frame(q, k, F), atol=0.01)
        assert np.allclose(pb.from_frame(pb.to_frame(q)), q, atol=0.01)      # chords again


def test_beside_two_legs_of_a_u_turn_a_point_is_taken_at_the_nearer():
    """Conservative: a point the path passes twice within the zones' reach is as near as the
    first pass, and as central as the nearest pass."""
    a = np.linspace(0.0, 3.0, 61)
    th = np.linspace(0.0, math.pi, 40)[1:-1]
    hairpin = np.concatenate([np.stack([a, 0 * a], 1),
                              np.stack([3.0 + 0.4 * np.sin(th), 0.4 - 0.4 * np.cos(th)], 1),
                              np.stack([a[::-1], 0 * a + 0.8], 1)])
    pb = PathBend(hairpin, 0.0, near_m=0.7)         # front_x 0: the front's curve is the path
    back = 3.0 + math.pi * 0.4 + 2.0                # the second pass's station at x = 1
    got = pb.to_frame(np.array([[1.0, 0.5], [1.0, 1.5], [1.0, -0.2]]))
    assert got[0] == pytest.approx([1.0, 0.3], abs=0.01)      # first pass, offset to the second
    assert got[1] == pytest.approx([back, -0.7], abs=0.01)    # beyond near_m of the first
    assert got[2] == pytest.approx([1.0, -0.2], abs=1e-9)     # only the first


def test_the_planned_path_is_checked_and_without_one_the_zones_are_straight():
    assert ZonesConfig().follow_path is False
    cfg = parse_config({"zones": {"follow_path": True, "path_max_offset_m": 0.3}}, "t")
    assert cfg.zones.follow_path and cfg.zones.path_max_offset_m == 0.3
    with pytest.raises(ConfigError, match="path_max_offset_m"):
        parse_config({"zones": {"path_max_offset_m": -1}}, "t")
    with pytest.raises(ValueError, match="two distinct points"):
        PathBend(np.zeros((3, 2)), F)
    core = DecisionCore(_gh(follow_path=True))
    for path, why in ((None, "no planned path"),
                      (np.array([[2.0, 0.0], [5.0, 0.0]]), "starts 2.00 m from the vehicle"),
                      (np.array([[math.nan, 0.0], [5.0, 0.0]]), "not a number"),
                      (np.array([[0.0, 0.0]]), "two distinct points"),
                      (np.array([[0.0, 0.0, 1.0]]), "")):
        v = VehicleState(0, 0, speed_mps=0.5, path_xy=path)
        assert core._bend(v) == 0.0
        assert why in core.path_refused and core.path_refused
    # the usual case, and off: nothing read
    assert isinstance(core._bend(VehicleState(0, 0, path_xy=u_turn())), PathBend)
    assert core.path_refused == ""
    assert DecisionCore(_gh())._bend(VehicleState(0, 0, path_xy=u_turn())) == 0.0


def _gh(**kw):
    return Config(gate=GateConfig(hold_off_s=0.3),
                  zones=ZonesConfig(front_x_m=F, half_width_m=HW, min_stop_m=2.0, **kw))


def _drive(core, pts, path, n=4):
    out = pic = None
    for k in range(n):
        v = VehicleState(k * DT, k, speed_mps=0.1, yaw_rate_radps=0.1, path_xy=path)
        pic = core.perceive({"rgbd": Detections(points_xy=pts)}, v, k * DT)
        out = core.decide(k * DT, [], pic)
    return out, pic


def _blob(xy):
    o = np.array([-0.05, 0.0, 0.05])
    return np.array([[xy[0] + a, xy[1] + b] for a in o for b in o])


def test_the_row_end_off_the_path_is_no_stop_and_the_crate_on_it_is():
    # the vehicle 40 degrees into its turn out of the aisle: the path bends left at once
    path = arc_path(1.0 / 0.8, 3.0)
    ahead = _blob((F + 0.7, 0.0))            # the row's end straight ahead, 0.7 m
    on_path = _blob(PathBend(path, F).from_frame(np.array([[F + 1.2, 0.0]]))[0])
    assert abs(on_path[4, 1]) > HW + 0.3     # far to the left: beside the straight zone
    out, _ = _drive(DecisionCore(_gh()), ahead, path)
    assert out.state is GateState.STOP
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), ahead, path)
    assert out.state is not GateState.STOP and pic.verdict.in_stop == 0
    assert pic.verdict.path is not None and same_bend(pic.verdict.bend, pic.verdict.path)
    out, pic = _drive(DecisionCore(_gh(follow_path=True)), on_path, path)
    assert out.state is GateState.STOP
    assert pic.verdict.nearest_m == pytest.approx(1.2, abs=0.1)    # along the path
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
