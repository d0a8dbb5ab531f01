"""The daemon closed-loop on the simulated field: the vehicle obeys the box."""
import dataclasses
import math

from appliance.config import default_config
from appliance.daemon import Daemon, sim_config
from drivers.sim.field import SimField
from hal import GateState


def sim_daemon(scene="stubble-day"):
    cfg = sim_config(default_config(), scene)
    d = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    d.start()
    return d


def test_box_stops_the_vehicle_before_the_person_on_its_path():
    d = sim_daemon()
    log = []
    d.loop.on_cycle.append(lambda r: log.append(r))
    try:
        d.run(max_cycles=150)          # 15 s: the course's first obstacles are 8-13 m ahead
        st = d.status()
    finally:
        d.shutdown()
    assert st["sim"]["collisions"] == 0
    stops = [r for r in log if r.output.state is GateState.STOP and "stop zone" in r.output.reason]
    assert stops, "the box never stopped for an obstacle"
    # the vehicle stood still while the box said STOP for an obstacle (it obeys the link)
    assert st["sim"]["stopped_s"] > 2.0
    # and it drove when clear
    assert st["sim"]["distance_m"] > 5.0


def test_unplugged_laser_stops_within_two_cycles_of_its_timeout_and_recovers():
    d = sim_daemon()
    log = []
    d.loop.on_cycle.append(lambda r: log.append(r))
    try:
        d.run(max_cycles=15)
        laser = d.devices["laser"]
        laser.unplugged = True
        t_unplug = len(log)
        d.run(max_cycles=10)
        first = next(i for i, r in enumerate(log[t_unplug:])
                     if r.output.state is GateState.STOP and "laser" in r.output.reason)
        assert first <= int(laser.timeout_s * 10) + 2
        assert d.status()["devices"]["laser"]["state"] == "no_data"
        laser.unplugged = False
        d.run(max_cycles=30)
        assert d.status()["devices"]["laser"]["state"] == "ok"
        assert all("laser" not in r.output.reason for r in log[-5:])
    finally:
        d.shutdown()


def _stopped_before_an_obstacle():
    """stubble-day 0 driven with a perfect box until it stops before the first obstacle on
    the path (the field, its vehicle)."""
    f = SimField("stubble-day", 0, sensors=("laser",))
    v = f.vehicle
    for _ in range(200):
        f.step(0.1, f.oracle_command())
        if v.speed == 0.0:
            break
    assert v.clearance_ahead() < 6.0
    return f, v


def _detoured(trace=None):
    """...then held at STOP until the driver has steered round it (5 s, then his manoeuvre:
    the box's STOP is not obeyed while he drives). ``trace`` gets (pose, speed, yaw rate)
    every 0.1 s step of the manoeuvre."""
    f, v = _stopped_before_an_obstacle()
    for _ in range(60):
        f.step(0.1, GateState.STOP)
        if v.detours:
            break
    assert v.detours == 1 and v.stats()["manoeuvre"] == "back"
    for _ in range(400):
        before = v.pose()
        f.step(0.1, GateState.STOP)
        if trace is not None:
            trace.append((before, v.pose(), v.speed, v.yaw_rate))
        if v.stats()["manoeuvre"] is None:
            break
    assert v.stats()["manoeuvre"] is None
    return f, v


def test_the_driver_backs_up_and_steers_round_and_the_box_odometry_sees_all_of_it():
    """The detour is driven, not a jump: he backs up (a negative speed), then steers out along
    an S, heading where he goes. Dead reckoning from the speed and yaw rate the box is given
    follows the true pose to a few centimetres, so what the box stopped for moves in its grid
    as it does in the world (before, the vehicle was put 3 m to the side with no motion at
    all, and the obstacle stayed in front of the box's grid)."""
    trace = []
    f, v = _detoured(trace)
    assert min(sp for _, _, sp, _ in trace) < -0.5              # it backed up
    assert max(abs(w) for _, _, _, w in trace) > 0.2             # and turned
    (x, y, yaw), _, _, _ = trace[0]
    worst = 0.0
    for (_, after, sp0, w), prev in zip(trace, [trace[0][2]] + [t[2] for t in trace[:-1]]):
        d = 0.5 * (prev + sp0) * 0.1
        yaw_mid = yaw + 0.5 * w * 0.1
        x, y, yaw = x + d * math.cos(yaw_mid), y + d * math.sin(yaw_mid), yaw + w * 0.1
        worst = max(worst, math.hypot(x - after[0], y - after[1]),
                    2.0 * abs(math.remainder(yaw - after[2], 2 * math.pi)))
    assert worst < 0.1, worst
    assert v.collisions == 0 and abs(v.offset_m) in (3.0, 6.0) and v.clearance_ahead() > 6.0


def test_the_driver_does_not_steer_out_where_the_way_out_is_blocked():
    """He looks before he goes: an obstacle where the S out to one side would pass makes him
    take another (never a collision of his, which the campaign would count against the box)."""
    f, v = _stopped_before_an_obstacle()
    here, ahead = v.offset_m, v.clearance_ahead()
    d = v.detour_offset_m
    assert v._way_out_free(here, here - 2 * d, ahead)        # the side he takes on this field
    # a drum where the vehicle would stand halfway along that S
    length, back = v._way_out(here, here - 2 * d, ahead)
    s0 = v.s
    v.s, v.offset_m = max(0.0, s0 - back) + 0.5 * length, here - d
    x, y, _ = v.pose()
    v.s, v.offset_m = s0, here
    drum = next(o for o in f.world.obstacles if o.shape == "cylinder")
    f.world.obstacles.append(dataclasses.replace(drum, id="blocker", x=x, y=y, vx_mps=0.0,
                                                 vy_mps=0.0))
    v._footprints.append(v._footprint_points(f.world.obstacles[-1]))
    assert not v._way_out_free(here, here - 2 * d, ahead)
    for _ in range(60):
        f.step(0.1, GateState.STOP)
        if v.detours:
            break
    assert v.detours == 1 and v._manoeuvre["o1"] != here - 2 * d
    for _ in range(400):
        f.step(0.1, GateState.STOP)
        if v.stats()["manoeuvre"] is None:
            break
    assert v.collisions == 0 and v.offset_m != here - 2 * d


def test_driver_takes_over_at_a_real_obstacle_and_overrides_a_false_stop():
    f, v = _detoured()
    assert v.detours == 1 and abs(v.offset_m) > 0 and v.clearance_ahead() > 6.0
    # a false stop in open field: the driver waits, then overrides and creeps on
    g = SimField("stubble-empty", 0, sensors=("laser",))
    w = g.vehicle
    for _ in range(120):
        g.step(0.1, GateState.STOP)
    assert w.overrides == 1 and w.detours == 0
    s0 = w.s
    for _ in range(30):
        g.step(0.1, GateState.STOP)
    assert w.s > s0 and g.vehicle.collisions == 0


def test_easing_back_after_a_detour_the_vehicle_heads_where_it_goes_and_the_gyro_sees_it():
    """Past the obstacle the driver steers back onto the path. The vehicle must head where it
    moves and its yaw rate must say so: it used to slide sideways with its heading held (0.3 m
    a metre), so to the box's odometry everything still ahead seemed to move sideways at 0.3x
    its speed (a still drum became a 0.9 m/s mover)."""
    f, v = _detoured()
    assert v.detours == 1 and abs(v.offset_m) > 0
    x0, y0, yaw0 = v.pose()
    gyro = yaw0                       # the heading the box would integrate from the yaw rate
    eased, worst_slip, worst_gyro = 0, 0.0, 0.0
    for _ in range(400):
        off = v.offset_m
        f.step(0.1, GateState.CLEAR)
        x1, y1, yaw1 = v.pose()
        gyro += v.yaw_rate * 0.1
        moved = math.hypot(x1 - x0, y1 - y0)
        if moved > 0.05:
            course = math.atan2(y1 - y0, x1 - x0)
            mid = math.atan2(math.sin(yaw0) + math.sin(yaw1), math.cos(yaw0) + math.cos(yaw1))
            worst_slip = max(worst_slip, abs(math.remainder(course - mid, 2 * math.pi)))
        worst_gyro = max(worst_gyro, abs(math.remainder(gyro - yaw1, 2 * math.pi)))
        eased += v.offset_m != off
        x0, y0, yaw0 = x1, y1, yaw1
        if v.offset_m == 0.0:
            break
    assert v.offset_m == 0.0 and v.heading_off == 0.0 and eased > 20
    assert worst_slip < math.radians(1.5), math.degrees(worst_slip)
    assert worst_gyro < math.radians(1.0), math.degrees(worst_gyro)


def test_in_a_greenhouse_lane_the_driver_clears_a_real_obstacle_and_the_drive_goes_on():
    """No room to steer round between bush rows: held at STOP before a real obstacle, the
    safety driver takes it out of the way (counted as a detour, named in ``cleared``); it is
    gone from the world (no collision, not seen, not in the corridor) and the vehicle drives
    on. Before this, every greenhouse drive stood at its first obstacle to the end."""
    f = SimField("greenhouse-coverage", 1, sensors=("rgbd",))
    v = f.vehicle
    for _ in range(1500):
        f.step(0.1, f.oracle_command())
        if v.speed == 0.0 and v.time_s > 1.0:
            break
    assert v.speed == 0.0 and v.clearance_ahead() < 6.0
    s_stop = v.s
    for _ in range(60):                        # held 6 s: cleared after 5
        f.step(0.1, GateState.STOP)
    assert v.detours == 1 and len(v.cleared) == 1 and v.offset_m == 0.0
    gone = next(o for o in f.world.obstacles if o.id == v.cleared[0])
    assert all(t["id"] != gone.id for t in f.truth())
    for _ in range(100):
        f.step(0.1, f.oracle_command())
    assert v.s > s_stop + 2.0 and v.collisions == 0
    assert v.stats()["cleared"] == [gone.id]
    # a stubble scene steers round instead and clears nothing
    g = SimField("stubble-day", 0, sensors=("laser",))
    assert g.scene.clear_after_stop is False and g.vehicle.stats()["cleared"] == []
