import threading

import numpy as np
import pytest

from appliance.config import Config, GateConfig, GridConfig, LoopConfig
from appliance.loop import ApplianceLoop
from appliance.perception import Pipeline, make_pipeline
from appliance.perception.base import Detections
from hal import GateState, ManualClock
from tests.fakes import HandLaser, HandLink

P = 100_000_000  # 100 ms


def make(hold_off=0.3, **loop_kw):
    clock = ManualClock(10**9)
    cfg = Config(gate=GateConfig(hold_off_s=hold_off), loop=LoopConfig(**loop_kw),
                 grid=GridConfig(occupied_at=1.0))
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    loop = ApplianceLoop(cfg, clock, {"laser": laser, "link": link}, [make_pipeline("laser", cfg)])
    return clock, loop, laser, link


def step(clock, loop, n=1):
    out = None
    for _ in range(n):
        out = loop.cycle()
        clock.advance(P)
    return out


def test_boot_stop_then_clear_after_hold_off():
    clock, loop, laser, link = make(hold_off=0.3)
    states = [step(clock, loop).output.state for _ in range(6)]
    assert states[0] is GateState.STOP
    assert states[:3] == [GateState.STOP] * 3 and states[3] is GateState.CLEAR
    assert len(link.sent) == 6 and link.sent[-1].state is GateState.CLEAR


def test_obstacle_in_stop_zone_stops():
    clock, loop, laser, link = make()
    step(clock, loop, 6)
    laser.put_obstacle(4.0, 0.0)
    # the default stop_recur: the first cycle that sees it is a SLOW ("unconfirmed"), the
    # next that sees it again a STOP (the laser waits for a second look like the cameras;
    # docs/proving-ground.md "Tuft tops")
    r = step(clock, loop)
    assert r.output.state is GateState.SLOW and "unconfirmed" in r.output.reason
    r = step(clock, loop)
    assert r.output.state is GateState.STOP
    assert "stop zone" in r.output.reason
    laser.clear()
    laser.put_obstacle(8.0, 0.2)          # beyond the 2 m stop zone, inside the slow zone
    step(clock, loop, 5)
    assert step(clock, loop).output.state is GateState.SLOW


@pytest.mark.parametrize("fault", ["silent", "aged", "exception", "link_silent"])
def test_stale_or_broken_source_stops_within_two_cycles(fault):
    clock, loop, laser, link = make()
    step(clock, loop, 6)
    assert loop.gate.state is GateState.CLEAR
    if fault == "silent":           # cable out: no more data
        laser.silent = True
    elif fault == "aged":           # data arrives but is older than the timeout
        laser.age_s = 0.5
    elif fault == "exception":
        laser.raise_on_service = OSError("EIO reading /dev/ttyUSB0")
    else:
        link.silent = True
    states = []
    for _ in range(2 + int(laser.timeout_s * 10)):
        states.append(step(clock, loop).output)
    # within two cycles of the data going past its timeout (or at once, for a fault)
    first = next(i for i, o in enumerate(states) if o.state is GateState.STOP)
    limit = 1 if fault in ("aged", "exception") else int(laser.timeout_s * 10) + 2
    assert first < limit
    reason = states[first].reason
    assert ("laser" in reason) or ("link" in reason)
    if fault == "exception":
        assert "EIO" in reason


def test_fault_that_came_and_went_between_two_cycles_stops():
    """A wire error is held 0.3 s, but a starved loop can be later than that: the fault comes
    and goes between two cycles (the soak's laser garbage burst that was never stopped). The
    loop sees the device's fault count rise and stops in that cycle, naming the fault."""
    clock, loop, laser, link = make()
    step(clock, loop, 6)
    assert loop.gate.state is GateState.CLEAR
    laser._fault("bad data on the wire: 64 byte(s) outside any telegram")
    laser.service(clock.now_ns())             # the next good scan clears it before the cycle
    assert laser.health().ok
    r = step(clock, loop)
    assert r.output.state is GateState.STOP
    assert "64 byte(s) outside any telegram" in r.output.reason
    assert "came and went" in r.output.reason
    # seen once: the next cycle has no fault, and the gate releases after its hold-off
    r2 = step(clock, loop)
    assert not any("came and went" in f for f in r2.faults)
    step(clock, loop, 4)
    assert loop.gate.state is GateState.CLEAR
    # a fault that is still on is named as before
    laser.raise_on_service = OSError("EIO reading /dev/ttyUSB0")
    r3 = step(clock, loop)
    assert r3.output.state is GateState.STOP and "came and went" not in r3.output.reason


def test_failed_send_is_a_fault():
    clock, loop, laser, link = make(hold_off=0.0)
    step(clock, loop, 3)
    assert loop.gate.state is GateState.CLEAR
    link.fail = True
    step(clock, loop)                   # this one did not go out
    r = step(clock, loop)
    assert r.output.state is GateState.STOP and "did not go out" in r.output.reason
    link.fail = False
    step(clock, loop)
    assert step(clock, loop).output.state is GateState.CLEAR


class SlowPipeline(Pipeline):
    name = "slow"
    requires = ("laser",)

    def __init__(self, clock, ms):
        super().__init__(None)
        self.clock, self.ms, self.calls = clock, ms, 0

    def process(self, inputs):
        self.calls += 1
        self.clock.advance(int(self.ms * 1e6))
        return Detections()


def test_optional_stage_skipped_when_over_budget_and_lag_is_fault():
    clock = ManualClock(0)
    cfg = Config(loop=LoopConfig(budget_perception_ms=50, lag_cycles_fault=3),
                 gate=GateConfig(hold_off_s=0.0))
    cfg = cfg.__class__(**{**cfg.__dict__,
                           "perception": cfg.perception.__class__(pipelines=("laser",),
                                                                  optional=("laser",))})
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    slow = SlowPipeline(clock, 40)
    slow.name = "laser"                 # registered as the optional one
    loop = ApplianceLoop(cfg, clock, {"laser": laser, "link": link}, [slow])
    stop = threading.Event()
    loop.run(stop, max_cycles=5)
    # once the estimate (40 ms) is known it still fits in 50 ms: it runs every cycle
    assert slow.calls == 5 and not loop.skipped
    slow.ms = 70                        # now it takes longer than its budget...
    loop.run(stop, max_cycles=3)
    assert loop.skipped.get("laser", 0) >= 1     # ...so it is skipped once its estimate is known
    # a mandatory pipeline that overruns the whole period makes the loop lag -> STOP
    clock2 = ManualClock(0)
    laser2, link2 = HandLaser("laser", clock2), HandLink("link", clock2)
    loop2 = ApplianceLoop(Config(gate=GateConfig(hold_off_s=0.0),
                                 loop=LoopConfig(lag_cycles_fault=3)),
                          clock2, {"laser": laser2, "link": link2}, [SlowPipeline(clock2, 150)])
    loop2.run(stop, max_cycles=6)
    assert loop2.overruns >= 3
    assert link2.sent[-1].state is GateState.STOP and "lagging" in link2.sent[-1].reason


class Exploding(Pipeline):
    name = "boom"
    requires = ("laser",)

    def process(self, inputs):
        raise ValueError("NaN in disparity")


def test_pipeline_exception_is_stop_not_crash():
    clock = ManualClock(0)
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    loop = ApplianceLoop(Config(gate=GateConfig(hold_off_s=0.0)), clock,
                         {"laser": laser, "link": link}, [Exploding()])
    for _ in range(3):
        r = loop.cycle()
        clock.advance(P)
    assert r.output.state is GateState.STOP and "NaN in disparity" in r.output.reason


class Malformed(Pipeline):
    """A pipeline whose detections are malformed while ``broken`` is set."""
    name = "malformed"
    requires = ("laser",)
    broken = None

    def process(self, inputs):
        pts = np.zeros((4, 2), np.float32) + 30.0            # far outside the zones
        if self.broken == "xyz":
            pts = np.zeros((4, 3), np.float32) + 30.0
        elif self.broken == "nan":
            pts[1, 0] = np.nan
        return Detections(pts)


def two_pipelines(bad):
    clock = ManualClock(0)
    cfg = Config(gate=GateConfig(hold_off_s=0.0), grid=GridConfig(occupied_at=1.0))
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    return clock, ApplianceLoop(cfg, clock, {"laser": laser, "link": link},
                                [make_pipeline("laser", cfg), bad]), link


@pytest.mark.parametrize("broken,says", [("xyz", "points_xy of shape (4, 3), expected (N, 2)"),
                                         ("nan", "1 of 4 points not finite")])
def test_malformed_detections_are_a_pipeline_fault_then_clear(broken, says):
    bad = Malformed()
    bad.broken = broken
    clock, loop, link = two_pipelines(bad)
    outs = [step(clock, loop) for _ in range(3)]
    assert all(r.output.state is GateState.STOP for r in outs)
    assert outs[-1].output.reason.startswith("pipeline malformed failed: ValueError: "
                                             "malformed detections: " + says)
    assert "malformed" not in outs[-1].detections          # never fused
    bad.broken = None
    outs = [step(clock, loop) for _ in range(2)]
    assert outs[-1].output.state is GateState.CLEAR, outs[-1].output.reason


def test_fusion_failure_is_stop_not_crash_and_recovers():
    """A bug inside fusion (injected: the grid update raises) is a fault for that cycle, the
    vehicle is told STOP, and the loop goes on."""
    bad = Malformed()
    clock, loop, link = two_pipelines(bad)
    real, calls = loop.core.grid.update, []

    def broken_update(*a, **k):
        calls.append(1)
        if len(calls) <= 3:
            raise IndexError("index 4096 is out of bounds")
        return real(*a, **k)

    loop.core.grid.update = broken_update
    outs = [step(clock, loop) for _ in range(3)]
    assert all(r.output.state is GateState.STOP for r in outs)
    assert outs[-1].output.reason.startswith("fusion failed: IndexError: index 4096")
    assert outs[-1].verdict is None and len(outs[-1].cells_xy) == 0
    assert len(link.sent) == 3 and link.sent[-1].state is GateState.STOP   # told, every cycle
    assert loop.status()["obstacles"]["in_stop_zone"] is None
    outs = [step(clock, loop) for _ in range(2)]      # fusion works again: the loop is alive
    assert outs[-1].output.state is GateState.CLEAR, outs[-1].output.reason


def test_no_link_is_stop():
    clock = ManualClock(0)
    laser = HandLaser("laser", clock)
    loop = ApplianceLoop(Config(gate=GateConfig(hold_off_s=0.0)), clock, {"laser": laser},
                         [make_pipeline("laser")])
    assert loop.cycle().output.state is GateState.STOP


def test_status_document():
    clock, loop, laser, link = make()
    step(clock, loop, 4)
    st = loop.status()
    assert st["state"] in ("STOP", "CLEAR")
    assert st["devices"]["laser"]["state"] == "ok"
    assert st["timing_ms"]["cycle"]["p99"] is not None
    assert st["last_stops"][0]["reason"].startswith("booting")
    assert np.isfinite(st["timing_ms"]["perception"]["p50"])
