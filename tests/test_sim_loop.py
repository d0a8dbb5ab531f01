"""The daemon closed-loop on the simulated field: the vehicle obeys the box."""
import dataclasses

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


def test_driver_takes_over_at_a_real_obstacle_and_overrides_a_false_stop():
    f = SimField("stubble-day", 0, sensors=("laser",))
    v = f.vehicle
    # drive with a perfect box until it stops before the first obstacle on the path
    for _ in range(200):
        f.step(0.1, f.oracle_command())
        if v.speed == 0.0:
            break
    assert v.clearance_ahead() < 6.0
    for _ in range(60):                        # held at STOP 6 s: the driver steers round
        f.step(0.1, GateState.STOP)
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
