"""Property-based tests (hypothesis) of the safety gate, the fusion grid and the tracker, over
arbitrary sequences of faults, zone verdicts, clock steps (backwards, huge jumps) and vehicle
motion. The properties are the box's promises:

- gate: never CLEAR or SLOW while a fault is active or there is no picture; tightening takes
  effect in the same cycle; loosening to a level only after every cycle of at least
  ``hold_off_s`` (watched throughout: no clock step back, no gap longer than the hold-off)
  wanted that level or better; every STOP names its cause; the rolling counter counts.
- fusion: evidence finite, >= 0 and bounded by the geometric series 1 / (1 - decay); nothing
  kept from the future (a clock step back starts the grid again); a point fixed in the world
  moves in the grid as the vehicle's motion says.
- tracking: no NaN, no track born or seen after the present cycle, never more tracks than
  ``max_tracks``.

Examples are bounded (the file runs in well under a minute); hypothesis' database replays any
failure it found first.
"""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from appliance.config import GateConfig, GridConfig
from appliance.fusion import GridFusion
from appliance.gate import SafetyGate
from appliance.zones import ZoneVerdict
from hal.types import GateState, VehicleState

RANK = {GateState.STOP: 0, GateState.SLOW: 1, GateState.CLEAR: 2}
S = 10**9
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# one cycle's clock step: mostly the 10 Hz period with jitter, sometimes nothing, a step back,
# a stall, or a huge jump either way
clock_step = st.one_of(
    st.integers(90_000_000, 110_000_000),
    st.integers(90_000_000, 110_000_000),
    st.integers(90_000_000, 110_000_000),
    st.just(0),
    st.integers(-3600 * S, -1),
    st.integers(200_000_000, 5 * S),
    st.integers(3600 * S, 48 * 3600 * S),
)
faults = st.one_of(st.just([]), st.just([]), st.lists(
    st.sampled_from(["laser: stale (0.40 s old)", "link: send failed", "loop lagging",
                     "stereo: FAULT cable out", "pipeline rgbd raised ValueError"]),
    min_size=1, max_size=3))


@st.composite
def verdicts(draw):
    kind = draw(st.sampled_from(["none", "clear", "clear", "slow", "stop", "stop-named"]))
    if kind == "none":
        return None
    near = draw(st.floats(0.0, 40.0))
    return ZoneVerdict(stop_len_m=3.0, slow_len_m=8.0,
                       in_stop=draw(st.integers(1, 50)) if kind.startswith("stop") else 0,
                       in_slow=draw(st.integers(1, 50)) if kind == "slow" else 0,
                       nearest_m=None if kind == "clear" else near, sectors=(),
                       stop_reason="track 3 (person) in the stop zone" if kind == "stop-named"
                       else None)


def wanted_rank(fs, v) -> int:
    if fs or v is None or v.in_stop:
        return 0
    return 1 if v.in_slow else 2


def watched_for(hist, level: int, hold_off_s: float) -> float:
    """How long (s) the cycles up to now have without a break wanted ``level`` or better,
    counting only what was watched (a step back or a gap over the hold-off is a break)."""
    t_end = hist[-1][0]
    start = t_end
    for k in range(len(hist) - 1, -1, -1):
        t, w = hist[k]
        if w < level:
            break
        start = t
        if k and not 0 <= t - hist[k - 1][0] <= hold_off_s * S + 1:
            break
    return (t_end - start) / S


@FAST
@given(hold_off=st.sampled_from([0.0, 0.3, 1.0, 2.5]),
       steps=st.lists(st.tuples(clock_step, faults, verdicts()), min_size=1, max_size=60))
def test_gate_promises(hold_off, steps):
    gate = SafetyGate(GateConfig(hold_off_s=hold_off))
    t = 100 * 3600 * S
    hist = []
    prev = 0                                    # boots in STOP
    for i, (dt, fs, v) in enumerate(steps):
        t = max(0, t + dt)
        out = gate.decide(t, fs, v)
        r, w = RANK[out.state], wanted_rank(fs, v)
        hist.append((t, w))
        # never looser than this cycle wants: fault / no picture / stop zone -> STOP at once
        assert r <= w, (out, fs, v)
        if fs:
            assert out.state is GateState.STOP and fs[0] in out.reason
        elif v is None:
            assert out.state is GateState.STOP and "no obstacle picture" in out.reason
        elif v.in_stop and v.stop_reason:
            assert out.state is GateState.STOP and v.stop_reason in out.reason
        # loosening only after the hold-off, watched, without a break
        if r > prev:
            held = watched_for(hist, r, hold_off)
            assert held + 1e-9 >= hold_off, (f"{list(RANK)[prev]} -> {out.state.value} after "
                                             f"{held:.3f} s of {hold_off} s: {hist[-8:]}")
        # every STOP names its cause
        if out.state is GateState.STOP:
            assert out.reason.strip()
            assert gate.cause in ("boot", "fault", "no-picture", "obstacle")
            assert gate.history[-1].reason.strip()
        assert out.seq == (i + 1) & 0xFFFF
        assert out.speed_limit_mps is None or out.state is GateState.SLOW
        prev = r


def test_gate_regression_jump_after_one_calm_cycle():
    """Found by test_gate_promises: STOP, one calm cycle, then the clock jumps an hour: the
    hold-off was counted as held (3600 s 'clear') and the gate let go after 0.1 s watched."""
    gate = SafetyGate(GateConfig(hold_off_s=1.0))
    clear = ZoneVerdict(3.0, 8.0, 0, 0, None, ())
    t = 1000 * S
    assert gate.decide(t, ["laser: stale"], clear).state is GateState.STOP
    assert gate.decide(t + S // 10, [], clear).state is GateState.STOP
    assert gate.decide(t + 3600 * S, [], clear).state is GateState.STOP
    # watched for a whole hold-off after the jump: released
    out = None
    for k in range(1, 12):
        out = gate.decide(t + 3600 * S + k * S // 10, [], clear)
    assert out.state is GateState.CLEAR


def test_gate_regression_stop_to_clear_skips_the_slow_hold_off():
    """Found by test_gate_promises: after a STOP, 0.9 s of something in the slow zone and then
    one clear cycle released straight to CLEAR: the slow zone had not been clear for the
    hold-off. Now it goes to SLOW, and to CLEAR after a clear hold-off."""
    gate = SafetyGate(GateConfig(hold_off_s=1.0))
    slow = ZoneVerdict(3.0, 8.0, 0, 4, 5.0, ())
    clear = ZoneVerdict(3.0, 8.0, 0, 0, None, ())
    t = 1000 * S
    gate.decide(t, ["x"], clear)
    for k in range(1, 11):
        gate.decide(t + k * S // 10, [], slow)
    out = gate.decide(t + 11 * S // 10, [], clear)
    assert out.state is GateState.SLOW
    for k in range(12, 21):
        assert gate.decide(t + k * S // 10, [], clear).state is GateState.SLOW
    assert gate.decide(t + 21 * S // 10, [], clear).state is GateState.CLEAR


# ---- fusion ------------------------------------------------------------------------------
GRID = GridConfig(cell_m=0.2, x_min_m=-2.0, x_max_m=20.0, y_min_m=-8.0, y_max_m=8.0)
odd = st.sampled_from([math.nan, math.inf, -math.inf])
points = st.lists(st.tuples(st.one_of(st.floats(-5, 25), odd), st.one_of(st.floats(-10, 10), odd)),
                  max_size=30)
vehicles = st.one_of(st.none(), st.builds(
    lambda v, w: VehicleState(stamp_ns=0, seq=0, speed_mps=v, yaw_rate_radps=w),
    st.floats(-5, 15), st.floats(-1.5, 1.5)))


@FAST
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")
@given(steps=st.lists(st.tuples(clock_step, points, vehicles), min_size=1, max_size=25),
       decay=st.sampled_from([0.0, 0.5, 0.9]))
def test_fusion_promises(steps, decay):
    g = GridFusion(GridConfig(**{**GRID.__dict__, "decay": decay}))
    bound = 1.0 / (1.0 - decay) + 1e-4
    t = 100 * 3600 * S
    for dt, pts, veh in steps:
        t = max(0, t + dt)
        occ = g.update(np.array(pts, np.float64).reshape(-1, 2), veh, t)
        ev = g.evidence
        assert np.isfinite(ev).all() and ev.min() >= 0 and ev.max() <= bound
        if dt < 0:                    # nothing kept from the future: only this cycle's hits
            assert ev.max() <= 1.0 + 1e-6
        assert np.isfinite(occ).all()
        if len(occ):
            assert (occ[:, 0] >= GRID.x_min_m).all() and (occ[:, 0] <= GRID.x_max_m).all()
            assert (occ[:, 1] >= GRID.y_min_m).all() and (occ[:, 1] <= GRID.y_max_m).all()


@FAST
@given(x=st.floats(1.0, 15.0), y=st.floats(-5.0, 5.0), v=st.floats(0.0, 6.0),
       w=st.floats(-0.5, 0.5))
def test_fusion_ego_motion_moves_a_world_point_as_the_vehicle_moves(x, y, v, w):
    g = GridFusion(GridConfig(**{**GRID.__dict__, "decay": 1.0, "occupied_at": 0.5}))
    t0 = 10 * S
    g.update(np.array([[x, y]]), None, t0)
    dt = 0.1
    g.update(np.zeros((0, 2)), VehicleState(stamp_ns=0, seq=0, speed_mps=v, yaw_rate_radps=w),
             t0 + int(dt * S))
    occ = g.occupied()
    assert len(occ) >= 1
    # where the point is now, in the vehicle frame (the grid's own motion model)
    dth, dx = w * dt, v * dt
    px, py = x - dx * math.cos(dth / 2), y - dx * math.sin(dth / 2)
    ex = math.cos(-dth) * px - math.sin(-dth) * py
    ey = math.sin(-dth) * px + math.cos(-dth) * py
    d = np.hypot(occ[:, 0] - ex, occ[:, 1] - ey).min()
    assert d <= 1.5 * GRID.cell_m * math.sqrt(2), (occ, ex, ey)


def test_fusion_regression_step_back_keeps_no_future_evidence():
    """Found by test_fusion_promises: a clock step back kept the evidence from 'later' cycles
    (the tracker already dropped its tracks then)."""
    g = GridFusion(GRID)
    for k in range(3):
        g.update(np.array([[5.0, 0.0]]), None, 10 * S + k * S // 10)
    assert g.evidence.max() > 1.0
    g.update(np.zeros((0, 2)), None, 5 * S)
    assert g.evidence.max() == 0.0


def test_fusion_non_finite_vehicle_motion_keeps_the_grid_finite():
    g = GridFusion(GRID)
    g.update(np.array([[5.0, 0.0]]), None, 10 * S)
    g.update(np.zeros((0, 2)), VehicleState(stamp_ns=0, seq=0, speed_mps=float("nan")),
             10 * S + S // 10)
    assert np.isfinite(g.evidence).all()


# ---- tracking ----------------------------------------------------------------------------
def _tracker():
    from appliance.config import TrackingConfig
    from appliance.tracking import Tracker
    return Tracker(TrackingConfig(enabled=True, max_tracks=12), GRID)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(steps=st.lists(st.tuples(clock_step, points, vehicles), min_size=1, max_size=20))
def test_tracking_promises(steps):
    from appliance.perception.base import Detections
    tr = _tracker()
    t = 100 * 3600 * S
    for dt, pts, veh in steps:
        t = max(0, t + dt)
        det = {"laser": Detections(points_xy=np.array(pts, np.float64).reshape(-1, 2))}
        views = tr.update(det, veh, t)
        assert len(tr.tracks) <= 12
        for tv in views:
            vals = (tv.x_m, tv.y_m, tv.vx_mps, tv.vy_mps, tv.confidence, tv.length_m,
                    tv.width_m, tv.height_m)
            assert all(math.isfinite(a) for a in vals), tv
            assert 0.0 <= tv.confidence <= 1.0
            assert tv.age_s >= 0                     # not born after this cycle
        for trk in tr.tracks:
            assert trk.born_ns <= t and trk.last_hit_ns <= t


def test_tracking_regression_points_all_off_the_grid():
    """Found by test_tracking_promises: a pipeline whose points all fall off the grid (one at
    x_max exactly) made the clustering raise ValueError on an empty labelling."""
    from appliance.perception.base import Detections
    tr = _tracker()
    det = {"laser": Detections(points_xy=np.array([[GRID.x_max_m, 0.0], [-50.0, 3.0]]))}
    assert tr.update(det, None, 10 * S) == []


# ---- the loop: stale sources and failed sends ------------------------------------------------
@st.composite
def loop_steps(draw):
    return (draw(st.one_of(st.just(100_000_000), st.just(100_000_000), st.integers(1, 400_000_000),
                           st.integers(3600 * S, 2 * 3600 * S))),
            draw(st.sampled_from(["ok", "ok", "ok", "silent", "aged", "raise"])),
            draw(st.sampled_from([False, False, False, True])),        # the send fails
            draw(st.sampled_from([False, False, False, True])),        # the link goes silent
            draw(st.one_of(st.none(), st.none(), st.floats(3.0, 25.0))))  # an obstacle ahead


CALM = (100_000_000, "ok", False, False, None)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(steps=st.lists(loop_steps(), min_size=1, max_size=40))
# at least these reach CLEAR and SLOW, so the checks on them run whatever hypothesis draws
@example(steps=[CALM] * 6 + [(100_000_000, "silent", False, False, None)] * 4 + [CALM] * 6)
@example(steps=[CALM] * 6 + [(100_000_000, "ok", False, False, 8.0)] * 4
         + [(100_000_000, "ok", True, False, None)] * 2 + [CALM] * 6)
def test_loop_never_clear_while_a_source_is_stale_or_a_send_failed(steps):
    """The whole loop (laser pipeline, grid, zones, gate, links) over arbitrary cable-outs,
    aged data, driver exceptions, refused sends, a silent vehicle link and clock jumps: no
    CLEAR or SLOW goes out in a cycle whose laser or link data is older than its timeout, whose
    laser driver just raised, or after a send that did not go out."""
    from appliance.config import Config, GateConfig
    from appliance.loop import ApplianceLoop
    from appliance.perception import make_pipeline
    from hal import ManualClock
    from tests.fakes import HandLaser, HandLink
    clock = ManualClock(10**9)
    cfg = Config(gate=GateConfig(hold_off_s=0.3), grid=GridConfig(occupied_at=1.0))
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    loop = ApplianceLoop(cfg, clock, {"laser": laser, "link": link},
                         [make_pipeline("laser", cfg)])
    laser_stamp = link_stamp = None
    prev_sent = None
    for dt, mode, fail, silent, obstacle in steps:
        clock.advance(dt)
        now = clock.now_ns()
        laser.silent = mode == "silent"
        laser.age_s = 0.4 if mode == "aged" else 0.0
        laser.raise_on_service = RuntimeError("driver bug") if mode == "raise" else None
        laser.clear()
        if obstacle is not None:
            laser.put_obstacle(obstacle, 0.0)
        link.fail, link.silent = fail, silent
        out = loop.cycle().output
        if mode in ("ok", "aged"):
            laser_stamp = now - int(laser.age_s * 1e9)
        if not silent:
            link_stamp = now
        fresh = (laser_stamp is not None and now - laser_stamp <= laser.timeout_s * 1e9
                 and link_stamp is not None and now - link_stamp <= link.timeout_s * 1e9)
        if out.state is not GateState.STOP:
            assert fresh, (out, mode, silent)
            assert mode != "raise", out
            assert prev_sent is True, out                  # the last message went out
        else:
            assert out.reason.strip()
        prev_sent = not fail


def test_fusion_regression_a_lone_cell_survives_a_turn():
    """Found by test_fusion_ego_motion...: a single hit 14 m ahead vanished from the grid when
    the vehicle turned (0.875 m/s, 0.5 rad/s): the nearest-neighbour warp skipped its cell."""
    g = GridFusion(GridConfig(**{**GRID.__dict__, "decay": 1.0, "occupied_at": 0.5}))
    g.update(np.array([[14.0, 0.0]]), None, 10 * S)
    g.update(np.zeros((0, 2)), VehicleState(stamp_ns=0, seq=0, speed_mps=0.875,
                                            yaw_rate_radps=0.5), 10 * S + S // 10)
    assert len(g.occupied()) == 1
