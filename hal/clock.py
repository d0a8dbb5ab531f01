"""Injected time. All time in the box comes from a Clock so replays are deterministic."""
from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod


class Clock(ABC):
    @abstractmethod
    def now_ns(self) -> int:
        """Monotonic time in nanoseconds."""

    @abstractmethod
    def sleep_until(self, t_ns: int) -> None:
        """Block until now_ns() >= t_ns."""

    def now_s(self) -> float:
        return self.now_ns() / 1e9


class MonotonicClock(Clock):
    """The real clock: time.monotonic_ns()."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, t_ns: int) -> None:
        while True:
            dt = t_ns - time.monotonic_ns()
            if dt <= 0:
                return
            time.sleep(min(dt / 1e9, 0.05))


class ManualClock(Clock):
    """A clock that moves only when told: tests, lock-step simulation and replay.

    ``sleep_until`` jumps the time forward instead of waiting.
    """

    def __init__(self, start_ns: int = 0):
        self._t = int(start_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        with self._lock:
            return self._t

    def advance(self, dt_ns: int) -> None:
        if dt_ns < 0:
            raise ValueError("a clock does not go backwards")
        with self._lock:
            self._t += int(dt_ns)

    def set(self, t_ns: int) -> None:
        with self._lock:
            if t_ns < self._t:
                raise ValueError("a clock does not go backwards")
            self._t = int(t_ns)

    def sleep_until(self, t_ns: int) -> None:
        with self._lock:
            if t_ns > self._t:
                self._t = int(t_ns)
