"""[zones] follow_turn: the stop and slow zones bent along the arc the vehicle drives.

The greenhouse's headland false stops on training seeds were bush-row ends straight ahead of a
vehicle in a 1 m U-turn: in the straight stop zone, nowhere near the arc it drives."""
from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.config import Config, GateConfig, GridConfig, ZonesConfig, parse_config
from appliance.decision import DecisionCore, assess_tracks
from hal.errors import ConfigError
from appliance.evaluation import _StopTally
from appliance.perception import Detections
from appliance.tracking import TrackView
from appliance.zones import (from_path_frame, heading_to_path_frame, to_path_frame, zone_outline,
                             zone_rects)
from hal import GateState
from hal.types import VehicleState

S = 10**9
DT = S // 10
F, HW, R = 1.1, 0.5, 1.0          # the greenhouse sprayer's front and half width; a 1 m U-turn


def on_front_circle(s_m, k=1.0 / R, f=F, lateral=0.0):
    """The vehicle-frame point ``s_m`` along the front centre's circle (left turn for k > 0),
    ``lateral`` to the left of it."""
    sgn = 1.0 if k > 0 else -1.0
    r0 = 1.0 / abs(k)
    rf = math.hypot(f, r0) - lateral
    a = math.atan2(f, r0) + s_m / math.hypot(f, r0)
    return np.array([rf * math.sin(a), sgn * (r0 - rf * math.cos(a))])


def test_to_path_frame_unrolls_the_front_s_circle_and_is_the_identity_when_straight():
    pts = np.array([[3.0, 0.2], [F, 0.0], [7.5, -1.0]])
    assert np.array_equal(to_path_frame(pts, 0.0, F), pts)
    assert np.allclose(to_path_frame(pts, 1e-5, F), pts, atol=1e-4)   # a 100 km radius
    for k in (1.0, -1.0, 0.4):
        for s in (0.0, 0.5, 2.0, 4.0):
            for lat in (0.0, 0.3, -0.3):
                got = to_path_frame(on_front_circle(s, k, lateral=lat), k, F)[0]
                assert got == pytest.approx([F + s, lat if k > 0 else -lat], abs=1e-9)
    # the mirror image of a left turn is the right turn
    p = np.array([[2.0, 0.7], [1.5, -0.2]])
    mirrored = to_path_frame(p * [1, -1], -1.0, F) * [1, -1]
    assert np.allclose(mirrored, to_path_frame(p, 1.0, F))
    # behind the vehicle: before the front on its circle, in no zone
    assert to_path_frame(np.array([[-1.0, 0.0]]), 1.0, F)[0, 0] < F
    # and back
    q = np.array([[F, 0.0], [2.0, 0.4], [3.5, -0.5]])
    for k in (1.0, -0.7, 0.0):
        assert np.allclose(to_path_frame(from_path_frame(q, k, F), k, F), q)
    out = zone_outline(F, F + 2.0, HW, 1.0, F)
    assert np.allclose(to_path_frame(out, 1.0, F)[:, 1] ** 2, HW ** 2)
    # a thing's heading follows the path's tangent
    assert heading_to_path_frame(on_front_circle(1.0)[None], 0.0, 1.0)[0] < -0.5


def _gh(**kw):
    return Config(gate=GateConfig(hold_off_s=0.3),
                  zones=ZonesConfig(front_x_m=F, half_width_m=HW, min_stop_m=2.0, **kw))


def _turn(core, pts, n=4, speed=0.1, yaw_rate=0.1, t0=0):
    """``n`` cycles of a vehicle creeping round a 1 m turn (1 cm a cycle) seeing ``pts``."""
    out = pic = None
    for k in range(t0, t0 + n):
        v = VehicleState(k * DT, k, speed_mps=speed, yaw_rate_radps=yaw_rate)
        pic = core.perceive({"rgbd": Detections(points_xy=pts)}, v, k * DT)
        out = core.decide(k * DT, [], pic)
    return out, pic


def _blob(xy):
    o = np.array([-0.05, 0.0, 0.05])
    return np.array([[xy[0] + a, xy[1] + b] for a in o for b in o])


def test_in_a_tight_turn_the_bush_end_straight_ahead_is_no_stop_and_the_thing_on_the_arc_is():
    ahead = _blob((F + 1.1, 0.0))            # 1.1 m straight ahead: where the U-turn does not go
    on_arc = _blob(on_front_circle(1.2))     # 1.2 m along the arc, 1.1 m to the left
    assert abs(on_arc[4, 1]) > HW + 0.3
    straight, bent = _gh(), _gh(follow_turn=True)
    out, _ = _turn(DecisionCore(straight), ahead)
    assert out.state is GateState.STOP
    out, pic = _turn(DecisionCore(bent), ahead)
    assert out.state is not GateState.STOP and pic.verdict.in_stop == 0
    assert pic.verdict.curvature_1pm == pytest.approx(1.0)
    out, _ = _turn(DecisionCore(straight), on_arc)
    assert out.state is not GateState.STOP
    out, pic = _turn(DecisionCore(bent), on_arc)
    assert out.state is GateState.STOP
    # distances are along the arc
    assert pic.verdict.nearest_m == pytest.approx(1.2, abs=0.1)


def test_the_turn_is_kept_while_the_vehicle_stands_and_a_broken_yaw_rate_is_straight():
    core = DecisionCore(_gh(follow_turn=True))
    ahead = _blob((F + 1.1, 0.0))
    _turn(core, np.zeros((0, 2)))
    # stopped mid-turn: no yaw rate, no speed; the steering has not moved
    out, pic = _turn(core, ahead, speed=0.0, yaw_rate=0.0, t0=4)
    assert pic.verdict.curvature_1pm == pytest.approx(1.0)
    assert out.state is not GateState.STOP
    # a yaw rate that is not a number (the links quarantine one before it gets here): the
    # straight zones
    assert core._curvature(VehicleState(0, 0, speed_mps=0.5, yaw_rate_radps=math.nan)) == 0.0
    out, pic = _turn(core, ahead, yaw_rate=0.0, t0=8)       # driving straight again
    assert pic.verdict.curvature_1pm == 0.0 and out.state is GateState.STOP
    # a curvature beyond the vehicle's is clamped
    _, pic = _turn(DecisionCore(_gh(follow_turn=True)), ahead, speed=0.2, yaw_rate=5.0)
    assert pic.verdict.curvature_1pm == pytest.approx(2.0)


def test_off_by_default_and_checked():
    assert ZonesConfig().follow_turn is False
    cfg = parse_config({"zones": {"follow_turn": True, "max_curvature_1pm": 1.5}}, "t")
    assert cfg.zones.follow_turn and cfg.zones.max_curvature_1pm == 1.5
    with pytest.raises(ConfigError, match="max_curvature_1pm"):
        parse_config({"zones": {"max_curvature_1pm": -1}}, "t")
    # off: the yaw rate changes nothing
    _, pic = _turn(DecisionCore(_gh()), _blob((F + 1.1, 0.0)))
    assert pic.verdict.curvature_1pm == 0.0


def test_tracks_are_judged_in_the_bent_zones_too():
    cfg = Config(zones=ZonesConfig(front_x_m=F, half_width_m=HW, min_stop_m=2.0,
                                   follow_turn=True), grid=GridConfig())
    p = on_front_circle(1.0)
    t = TrackView(id=3, x_m=float(p[0]), y_m=float(p[1]), length_m=0.3, width_m=0.3,
                  height_m=0.5, vx_mps=0.0, vy_mps=0.0, confidence=0.9, sources=("geometry",),
                  confirmed=True, coasting=False, hits=5, age_s=1.0)
    assert assess_tracks([t], np.zeros((0, 2)), 0.1, cfg).in_stop == 0
    v = assess_tracks([t], np.zeros((0, 2)), 0.1, cfg, curvature_1pm=1.0)
    assert v.in_stop == 1 and v.nearest_m == pytest.approx(1.0 - 0.15, abs=0.05)


def test_eval_judges_the_truth_in_the_zones_the_box_bent():
    """fieldguard eval: a real obstacle on the arc is in the bent stop zone (its STOP is not
    a false stop); one straight ahead out of the turn is not (no missed stop)."""
    z = ZonesConfig(front_x_m=F, half_width_m=HW, min_stop_m=2.0)
    stop_rect, slow_rect = zone_rects(0.1, z)
    p = on_front_circle(1.0)
    on_arc = {"x_m": float(p[0]), "y_m": float(p[1]), "length_m": 0.3, "width_m": 0.3}
    ahead = {"x_m": F + 1.1, "y_m": 0.0, "length_m": 0.3, "width_m": 0.3}
    t = _StopTally(0.3)
    t.add(1, 1 * DT, "STOP", "obstacle", [on_arc], stop_rect, slow_rect, None, 1.0)
    t.add(2, 10 * S, "CLEAR", "clear", [ahead], stop_rect, slow_rect, None, 1.0)
    r = t.result()
    assert r["false_stop_frames"] == 0 and r["missed_stop_frames"] == 0
    t = _StopTally(0.3)                   # the same frames with straight zones
    t.add(1, 1 * DT, "STOP", "obstacle", [on_arc], stop_rect, slow_rect, None, 0.0)
    t.add(2, 10 * S, "CLEAR", "clear", [ahead], stop_rect, slow_rect, None, 0.0)
    r = t.result()
    assert r["false_stop_frames"] == 1 and r["missed_stop_frames"] == 1


def test_the_snapshot_and_the_console_draw_the_zones_bent():
    from appliance.snapshot import STATE_BGR, draw_zones
    z = ZonesConfig(front_x_m=F, half_width_m=HW, min_stop_m=2.0)
    ppm, size = 50, 400

    def px(x, y):                         # 50 px a metre, the vehicle's origin at the bottom
        return int(round(size / 2 - y * ppm)), int(round(size - 20 - x * ppm))

    def stop_drawn(kappa):
        img = np.zeros((size, size, 3), np.uint8)
        draw_zones(img, px, z, 2.0, kappa)
        return np.all(img == STATE_BGR[GateState.STOP], axis=2)

    straight, bent = stop_drawn(0.0), stop_drawn(1.0)
    # the stop zone's far edge: straight ahead when straight, on the arc to the left when bent
    far = on_front_circle(2.0)
    assert straight[px(F + 2.0, 0.0)[::-1]] and not bent[px(F + 2.0, 0.0)[::-1]]
    near_far = [bent[py, pxx] for pxx, py in (px(far[0] + dx, far[1] + dy)
                                              for dx in (-0.02, 0, 0.02)
                                              for dy in (-0.02, 0, 0.02))]
    assert any(near_far)


def test_a_non_finite_yaw_rate_or_speed_never_wipes_the_grid():
    """Defence in depth (the links quarantine such values first): moving the grid by NaN
    would empty it, a CLEAR with an obstacle ahead."""
    for bad in (dict(yaw_rate_radps=math.nan), dict(speed_mps=math.nan)):
        core = DecisionCore(_gh())
        out, pic = _turn(core, _blob((F + 1.0, 0.0)), n=3, speed=0.0, yaw_rate=0.0)
        assert pic.verdict.in_stop > 0
        v = VehicleState(3 * DT, 3, **{"speed_mps": 0.5, "yaw_rate_radps": 0.5, **bad})
        pic = core.perceive({"rgbd": Detections(points_xy=_blob((F + 1.0, 0.0)))}, v, 3 * DT)
        assert len(pic.cells_xy) and pic.verdict.in_stop > 0     # wiped, one hit is too few
