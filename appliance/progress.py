"""A small progress bar on stderr (a terminal gets a live bar, a log gets a line per 10 %)."""
from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, label: str, total: int, stream=None):
        self.label, self.total = label, max(1, total)
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = time.monotonic()
        self._last_decile = -1

    def __call__(self, done: int, total: int | None = None) -> None:
        if total:
            self.total = max(1, total)
        frac = min(1.0, done / self.total)
        el = time.monotonic() - self.t0
        eta = el / frac - el if frac > 0 else 0.0
        if self.tty:
            bar = "#" * int(30 * frac)
            self.stream.write(f"\r{self.label} [{bar:<30}] {done}/{self.total} "
                              f"{el:5.1f}s eta {eta:5.1f}s")
            if done >= self.total:
                self.stream.write("\n")
            self.stream.flush()
        else:
            dec = int(frac * 10)
            if dec != self._last_decile:
                self._last_decile = dec
                self.stream.write(f"{self.label}: {done}/{self.total} ({frac:.0%}, "
                                  f"{el:.1f} s)\n")
                self.stream.flush()
