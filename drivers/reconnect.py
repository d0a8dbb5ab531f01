"""Reconnecting to a device that can go away: the one place for the schedule and the cycle that
every threaded hardware driver runs (the SICK laser on TCP, the strobe controller on a serial
port, the GigE cameras, the RGB-D helper process).

* :class:`Backoff`: exponential reconnect back-off in wall time.
* :class:`Reconnecting`: a mixin for a :class:`hal.Device` driver holding a connection. While it
  is not connected the driver's ``_acquire_once`` calls :meth:`Reconnecting._connect_when_due`;
  anything that loses the connection calls :meth:`Reconnecting._drop`, which closes what is half
  open (the driver's ``_disconnect()`` hook), schedules the next try, counts it and marks the
  device FAULT.
* :class:`WireFaults` (which Reconnecting includes; the CAN link uses it alone): corruption or a
  bus-off on a live connection is :meth:`WireFaults._wire_error`: the device is not trusted for
  ``fault_hold_s`` (samples arriving meanwhile are discarded, so the loop is sure to see the
  fault) without dropping the connection.
"""
from __future__ import annotations

import logging
import time

from hal.errors import DeviceError

log = logging.getLogger("fieldguard.drivers")


class Backoff:
    """Exponential reconnect back-off: first retry after ``first_s``, doubling up to ``max_s``;
    :meth:`reset` after a success. Uses the monotonic wall clock (device I/O happens in wall
    time whatever clock the loop uses)."""

    def __init__(self, first_s: float = 0.1, max_s: float = 2.0):
        self.first_s, self.max_s = float(first_s), float(max_s)
        self.delay_s = 0.0
        self.next_at = 0.0
        self.failures = 0

    def ready(self) -> bool:
        return time.monotonic() >= self.next_at

    def remaining_s(self) -> float:
        return max(0.0, self.next_at - time.monotonic())

    def failed(self) -> float:
        self.failures += 1
        self.delay_s = self.first_s if self.delay_s == 0 else min(self.max_s, self.delay_s * 2)
        self.next_at = time.monotonic() + self.delay_s
        return self.delay_s

    def reset(self) -> None:
        self.delay_s = 0.0
        self.next_at = 0.0
        self.failures = 0


class WireFaults:
    """Mixin (before the hal device class): corruption or a bus error on a live connection is
    a fault held for ``fault_hold_s``, during which the driver discards what arrives
    (:meth:`_distrusted`), so the next good sample cannot clear it before the loop has seen it."""

    fault_hold_s = 0.3
    _bad_until = 0.0

    def _wire_error(self, reason: str) -> None:
        """Corruption on the wire: not trusted for ``fault_hold_s``, FAULT."""
        self._bad_until = time.monotonic() + self.fault_hold_s
        self._fault(reason)

    def _distrusted(self) -> bool:
        """Still inside the hold after corruption (discard what arrives)."""
        return time.monotonic() < self._bad_until


class Reconnecting(WireFaults):
    """Mixin (before the hal device class) for threaded drivers that hold a connection.

    The driver sets ``self.backoff`` (a :class:`Backoff`) and, if it has one, ``fault_hold_s``;
    names its counter in ``reconnect_counter``; implements ``_disconnect()`` (close the handle,
    forget parse state; must not raise) and resets the back-off on its first good sample."""

    reconnect_counter = "reconnects"

    def _connect_when_due(self, connect) -> None:
        """Call ``connect()`` once the back-off allows, else wait at most 0.1 s (close() is
        never held up); a DeviceError from it drops what is half open (:meth:`_drop`)."""
        if not self.backoff.ready():
            self._stop_evt.wait(min(0.1, self.backoff.remaining_s()))
            return
        try:
            connect()
        except DeviceError as exc:
            self._drop(str(exc))

    def _disconnect(self) -> None:  # override
        pass

    def _drop(self, reason: str) -> None:
        """The connection is gone: close what is left, schedule the next try, count it, FAULT."""
        try:
            self._disconnect()
        except Exception as exc:          # closing a dead handle must not end the thread
            log.debug("%s: while dropping the connection: %s", self.name, exc)
        self.backoff.failed()
        self._count(self.reconnect_counter)
        self._fault(reason)
