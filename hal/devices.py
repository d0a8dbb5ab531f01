"""Device interfaces. The base class does the shared work (newest-sample slot, freshness,
health, fault counting, an acquisition thread, idempotent close); a driver overrides only
``_open``, ``_close`` and either ``_acquire_once`` (threaded) or ``service`` (lock-step).

Modelled on python-can's BusABC (shared work in the base, backends override a few hooks) and
Nav2's collision-monitor ``Source`` (freshness checked in the base, a stale source blocks).
"""
from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from typing import Any, Generic, TypeVar

from .clock import Clock
from .errors import ConfigError, DeviceError
from .health import Health, HealthReport
from .types import (DepthFrame, GateOutput, LaserScan, StereoCalibration, StereoFrame,
                    VehicleState)

T = TypeVar("T")
log = logging.getLogger("fieldguard.hal")


class Device(ABC, Generic[T]):
    """A source of stamped samples with a freshness timeout.

    Drivers call :meth:`_publish` with each new sample (only the newest is kept: a slot, never a
    queue) and :meth:`_fault` when something goes wrong. The loop calls :meth:`latest` and
    :meth:`health`; neither ever blocks on the device.
    """

    kind = "device"

    def __init__(self, name: str, clock: Clock, timeout_s: float = 0.25):
        if timeout_s <= 0:
            raise ValueError("timeout_s must be > 0")
        self.name = name
        self.clock = clock
        self.timeout_s = float(timeout_s)
        self._lock = threading.Lock()
        self._sample: T | None = None
        self._received_ns: int | None = None
        self._samples = 0
        self._faults = 0
        self._fault_reason: str | None = None
        self._last_fault = ""
        self._opened = False
        self._closed = False
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self.counters: dict[str, int] = {}

    # ---- life cycle -------------------------------------------------------------------------
    def open(self) -> None:
        """Open the device. Raises DeviceInitializationError on failure."""
        if self._opened:
            return
        self._open()
        self._opened = True
        self._closed = False

    def close(self) -> None:
        """Close the device. Safe to call twice, and on a device that never opened."""
        if self._closed:
            return
        self._closed = True
        self._stop_evt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            # every _acquire_once returns within ~0.1 s once _stop_evt is set; only a starved
            # machine takes longer, and closing the connection under a running thread is what
            # printed "I/O operation on closed file" from a link thread after its test ended
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.warning("%s: acquisition thread still running 2 s after close(); waiting",
                            self.name)
                self._thread.join(timeout=10.0)
        try:
            if self._opened:
                self._close()
        except Exception as exc:  # closing must never raise into the supervisor
            log.warning("%s: error while closing: %s", self.name, exc)
        self._opened = False

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()

    def _open(self) -> None:  # override
        pass

    def _close(self) -> None:  # override
        pass

    # ---- threaded acquisition ---------------------------------------------------------------
    def start_acquisition(self) -> None:
        """Run :meth:`_acquire_once` repeatedly in a daemon thread until close()."""
        if self._thread is not None:
            return
        self._stop_evt.clear()
        self._thread = threading.Thread(target=self._acquire_loop, name=f"acq-{self.name}",
                                        daemon=True)
        self._thread.start()

    def _acquire_loop(self) -> None:
        while not self._stop_evt.is_set():
            try:
                self._acquire_once()
            except DeviceError as exc:
                self._fault(str(exc))
                self._stop_evt.wait(0.05)
            except Exception as exc:  # a driver bug marks the device unhealthy, never more
                self._fault(f"driver error: {type(exc).__name__}: {exc}")
                self._stop_evt.wait(0.05)

    def _acquire_once(self) -> None:
        """Block for at most a short while, publish what arrived. Override for threaded drivers."""
        self._stop_evt.wait(0.1)

    def service(self, now_ns: int) -> None:
        """Called by the loop once per cycle before it reads the device. Lock-step drivers
        (simulation, replay) publish here; it must return quickly. Default: nothing."""

    # ---- publishing (driver side) -------------------------------------------------------------
    def _publish(self, sample: T) -> None:
        with self._lock:
            self._sample = sample
            self._received_ns = self.clock.now_ns()
            self._samples += 1
            self._fault_reason = None

    def _fault(self, reason: str) -> None:
        with self._lock:
            self._faults += 1
            if self._fault_reason != reason:
                log.warning("%s: %s", self.name, reason)
            self._fault_reason = reason
            self._last_fault = reason

    def clear_fault(self) -> None:
        with self._lock:
            self._fault_reason = None

    def _count(self, counter: str, n: int = 1) -> None:
        with self._lock:
            self.counters[counter] = self.counters.get(counter, 0) + n

    # ---- reading (loop side) -----------------------------------------------------------------
    def _stamp_of(self, sample: T) -> int:
        return getattr(sample, "stamp_ns", None) or 0

    def latest(self, now_ns: int | None = None) -> T | None:
        """The newest sample if it is fresh (capture stamp younger than timeout_s), else None."""
        now = self.clock.now_ns() if now_ns is None else now_ns
        with self._lock:
            s = self._sample
            if s is None or self._fault_reason is not None:
                return None
            if now - self._stamp_of(s) > self.timeout_s * 1e9:
                return None
            return s

    def newest(self) -> T | None:
        """The newest sample whatever its age (for pictures and status, never for decisions)."""
        with self._lock:
            return self._sample

    def health(self, now_ns: int | None = None) -> HealthReport:
        now = self.clock.now_ns() if now_ns is None else now_ns
        with self._lock:
            s, fault = self._sample, self._fault_reason
            age = None if s is None else (now - self._stamp_of(s)) / 1e9
            common = dict(name=self.name, kind=self.kind, age_s=age, samples=self._samples,
                          faults=self._faults, counters=dict(self.counters),
                          last_fault=self._last_fault)
        if self._closed:
            return HealthReport(state=Health.CLOSED, reason="closed", **common)
        if fault is not None:
            return HealthReport(state=Health.FAULT, reason=fault, **common)
        if s is None:
            return HealthReport(state=Health.STARTING, reason="no data yet", **common)
        if age is not None and age > self.timeout_s:
            return HealthReport(state=Health.NO_DATA,
                                reason=f"stale: newest data {age:.2f} s old "
                                       f"(timeout {self.timeout_s:.2f} s)", **common)
        if age is not None and age < -self.timeout_s:
            return HealthReport(state=Health.FAULT,
                                reason=f"data stamped {-age:.2f} s in the future", **common)
        return HealthReport(state=Health.OK, **common)

    #: how long a self-test waits for a fresh sample when the newest one is stale at first look
    SELFTEST_GRACE_S = 1.0

    def selftest_health(self, grace_s: float | None = None) -> HealthReport:
        """Health for a self-test: one look is not enough for a streaming device. A single lost
        frame leaves the newest sample stale for up to a period (a GigE camera losing packets
        does that several times a minute), and a self-test that fails for it sends the
        technician after a cable that is fine. So when the newest sample is merely stale
        (NO_DATA) and the device's own thread delivers samples, wait up to ``grace_s`` for a
        fresh one. A FAULT, a device never heard from, a closed one, or one that stays silent
        through the grace fails as before (the loop's own STOP on a stale sample is unchanged:
        this is only the technician's check)."""
        h = self.health()
        if h.state is not Health.NO_DATA or self._thread is None:
            return h
        end = time.monotonic() + (self.SELFTEST_GRACE_S if grace_s is None else grace_s)
        while time.monotonic() < end:
            time.sleep(0.02)
            h = self.health()
            if h.state is not Health.NO_DATA:
                return h
        return h

    def selftest(self) -> tuple[bool, str]:
        """A quick check for `fieldguard selftest`: reachable and streaming."""
        h = self.selftest_health()
        return h.ok, h.reason or "streaming"


def check_timeout(name: str, timeout_s: float, period_s: float, what: str) -> None:
    """A periodic device's ``timeout_s`` must be longer than its sample period (else it is never
    fresh: a STOP that never clears). The defaults are one period + 60 ms (docs/hardware.md,
    "within two cycles"). ConfigError naming the key otherwise."""
    if timeout_s <= period_s:
        raise ConfigError(f"timeout_s ({timeout_s:g} s) must be longer than {what} "
                          f"({period_s:.3g} s); one period + 0.06 s = {period_s + 0.06:.2f} s "
                          f"stops within two cycles of a missing sample",
                          key=f"devices.{name}.timeout_s")


class StereoCamera(Device[StereoFrame]):
    """A rectified colour stereo pair."""

    kind = "stereo"

    @property
    @abstractmethod
    def calibration(self) -> StereoCalibration: ...


class DepthCamera(Device[DepthFrame]):
    """Colour + registered depth (Kinect-class)."""

    kind = "rgbd"


class SafetyLaser(Device[LaserScan]):
    """A planar scanning laser."""

    kind = "laser"


class StrobeTrigger(Device[dict]):
    """Fires the cameras (and at night a strobe) at a fixed rate. Samples are status dicts
    (``{"stamp_ns", "rate_hz", "armed", "strobe", "fault"}``)."""

    kind = "trigger"

    @abstractmethod
    def set_rate(self, rate_hz: float) -> None: ...

    @abstractmethod
    def set_strobe(self, on: bool) -> None: ...


class VehicleLink(Device[VehicleState]):
    """The box's link to the vehicle: sends the gate output every cycle, receives speed and
    attitude (its samples). ``send`` returns True when the message went out; False or an
    exception means it did not, and the gate treats that as a fault."""

    kind = "link"

    @abstractmethod
    def send(self, output: GateOutput) -> bool: ...

    def peers(self) -> list[dict[str, Any]]:
        """Peers seen on the link (for status)."""
        return []
