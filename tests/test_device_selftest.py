"""`fieldguard selftest` on a streaming device: one look at the newest sample is not enough (a
single lost frame leaves it stale for a period: the GigE pair's flaky selftest, the forty-third
session), so a merely stale device is given a grace for a fresh sample; a fault, a silent device
and a lock-step one are answered at once or after the grace, as before."""
from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from hal.clock import MonotonicClock
from hal.devices import Device
from hal.health import Health


class Stream(Device):
    """A threaded device: one sample at start, then silent until ``resume`` is set, then a
    sample every 20 ms (a stream that lost frames and goes on)."""

    def __init__(self, timeout_s=0.1):
        super().__init__("cam", MonotonicClock(), timeout_s=timeout_s)
        self.resume = threading.Event()
        self._first = True

    def _acquire_once(self):
        if self._first or self.resume.is_set():
            self._first = False
            self._publish(SimpleNamespace(stamp_ns=self.clock.now_ns()))
        self._stop_evt.wait(0.02)


def _stale(dev):
    dev.open()
    dev.start_acquisition()
    deadline = time.monotonic() + 10
    while dev.health().state is not Health.NO_DATA:
        assert time.monotonic() < deadline, dev.health()
        time.sleep(0.01)


def test_a_stale_stream_that_resumes_passes():
    dev = Stream()
    try:
        _stale(dev)
        threading.Timer(0.2, dev.resume.set).start()
        t0 = time.monotonic()
        h = dev.selftest_health(grace_s=30.0)
        assert h.state is Health.OK, h
        assert time.monotonic() - t0 < 30.0
        assert dev.selftest() == (True, "streaming")
    finally:
        dev.resume.set()
        dev.close()


def test_a_silent_stream_fails_after_the_grace():
    dev = Stream()
    try:
        _stale(dev)
        t0 = time.monotonic()
        h = dev.selftest_health(grace_s=0.3)
        assert time.monotonic() - t0 >= 0.3
        assert not h.ok and h.reason.startswith("stale: newest data"), h
        dev.SELFTEST_GRACE_S = 0.2
        ok, msg = dev.selftest()
        assert not ok and "stale" in msg
    finally:
        dev.close()


def test_a_fault_and_a_lockstep_device_are_answered_at_once():
    dev = Stream()
    try:
        _stale(dev)
        dev._fault("control connection lost")
        t0 = time.monotonic()
        h = dev.selftest_health(grace_s=30.0)
        assert h.state is Health.FAULT and time.monotonic() - t0 < 5.0
    finally:
        dev.close()
    # no thread of its own (simulation, replay: the loop publishes): waiting would change nothing
    lock = Stream()
    lock.open()
    try:
        lock._publish(SimpleNamespace(stamp_ns=lock.clock.now_ns() - 10**9))
        t0 = time.monotonic()
        h = lock.selftest_health(grace_s=30.0)
        assert h.state is Health.NO_DATA and time.monotonic() - t0 < 5.0
    finally:
        lock.close()
