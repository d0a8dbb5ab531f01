"""A housekeeping job of the daemon's on its own thread, every so many seconds (the heap trim,
the novelty model's save): never in the loop's thread, never taking the box down."""
from __future__ import annotations

import logging
import threading


class Periodic:
    """Calls :meth:`tick` every ``period_s`` seconds on a daemon thread named ``name`` from
    :meth:`start` until :meth:`stop` (0 or less, or :meth:`enabled` False: never). An exception
    in :meth:`tick` is logged and the next period comes."""

    name = "periodic"
    logger = "fieldguard"

    def __init__(self, period_s: float):
        self.period_s = float(period_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def enabled(self) -> bool:
        return self.period_s > 0

    def tick(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        if not self.enabled() or self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
            self._thread = None

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.tick()
            except Exception:                    # noqa: BLE001 - housekeeping: log, go on
                logging.getLogger(self.logger).exception("%s", self.name)
