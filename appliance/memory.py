"""What the daemon's memory is made of, and giving freed heap back to the system.

A box that runs for weeks must not grow. Its RSS alone cannot say why it grows: frame buffers
come and go every cycle, and glibc's allocator keeps pages it has freed inside its arenas (one
per thread that allocates) until the top of an arena is free, so a heap with holes in it
reads as growth though nothing is held. Two figures tell them apart:

- **malloc's own account** (``mallinfo2``, glibc 2.33+): bytes in use by the program
  (``in_use_mb``), bytes freed but kept in the arenas (``free_mb``), and large blocks the
  allocator mapped on their own (``mmap_mb``). A leak grows ``in_use_mb``; fragmentation
  grows ``free_mb``.
- **Python's live blocks** (``sys.getallocatedblocks()``): objects that are never freed grow
  it whatever the allocator does.

``MemoryKeeper`` calls ``malloc_trim(0)`` every ``[status] malloc_trim_s`` seconds on its own
thread: glibc then returns every whole free page inside its arenas to the system (madvise),
so RSS follows what is in use. It takes each arena's lock in turn for a moment (its time is in
the status, ``trim_ms_max``); the loop thread's allocations wait at most that long. Elsewhere
than glibc (musl) both are absent and the status says so.
"""
from __future__ import annotations

import ctypes
import os
import sys
import time

from appliance.periodic import Periodic


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                 "uordblks", "fordblks", "keepcost")]


def _libc():
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return None
    return libc


_LIBC = _libc()
_MALLINFO2 = getattr(_LIBC, "mallinfo2", None) if _LIBC is not None else None
_MALLOC_TRIM = getattr(_LIBC, "malloc_trim", None) if _LIBC is not None else None
if _MALLINFO2 is not None:
    _MALLINFO2.restype = _MallInfo2
    _MALLINFO2.argtypes = []
if _MALLOC_TRIM is not None:
    _MALLOC_TRIM.restype = ctypes.c_int
    _MALLOC_TRIM.argtypes = [ctypes.c_size_t]

MB = 2 ** 20
try:
    _PAGE = os.sysconf("SC_PAGE_SIZE")
except (ValueError, OSError, AttributeError):
    _PAGE = 4096


def malloc_stats() -> dict | None:
    """glibc's account of its heap, in MB, or None where there is no mallinfo2."""
    if _MALLINFO2 is None:
        return None
    m = _MALLINFO2()
    return {"in_use_mb": round(m.uordblks / MB, 3),      # handed out by malloc, not freed
            "free_mb": round(m.fordblks / MB, 3),        # freed, still held in the arenas
            "arena_mb": round(m.arena / MB, 3),          # the arenas' size (in use + free)
            "mmap_mb": round(m.hblkhd / MB, 3),          # large blocks mapped on their own
            "mmap_blocks": int(m.hblks)}


def resident_mb() -> float | None:
    """This process's resident set, MB (Linux), or None."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE / MB
    except (OSError, ValueError, IndexError):
        return None


def trim() -> bool | None:
    """Give the arenas' whole free pages back to the system; True if any were. None where
    there is no malloc_trim."""
    if _MALLOC_TRIM is None:
        return None
    return bool(_MALLOC_TRIM(0))


class MemoryKeeper(Periodic):
    """Trims the heap every ``trim_s`` seconds on its own thread (0: never) and reports the
    memory figures for the status document."""

    name = "memory"
    logger = "fieldguard.memory"

    def __init__(self, trim_s: float = 60.0):
        super().__init__(trim_s)
        self.trims = 0
        self.trim_ms_last = None
        self.trim_ms_max = 0.0
        self.released_mb = 0.0          # RSS before a trim minus after, summed

    @property
    def trim_s(self) -> float:
        return self.period_s

    def enabled(self) -> bool:
        return self.period_s > 0 and _MALLOC_TRIM is not None

    def trim_now(self) -> None:
        before = resident_mb()
        t = time.perf_counter()
        trim()
        ms = (time.perf_counter() - t) * 1e3
        after = resident_mb()
        self.trims += 1
        self.trim_ms_last = round(ms, 3)
        self.trim_ms_max = round(max(self.trim_ms_max, ms), 3)
        if before is not None and after is not None:
            self.released_mb = round(self.released_mb + max(0.0, before - after), 3)

    def tick(self) -> None:
        self.trim_now()

    def status(self) -> dict:
        doc = {"malloc": malloc_stats(), "py_blocks": sys.getallocatedblocks(),
               "trim_s": self.trim_s if _MALLOC_TRIM is not None else None,
               "trims": self.trims, "trim_ms_last": self.trim_ms_last,
               "trim_ms_max": self.trim_ms_max, "trim_released_mb": self.released_mb}
        if _MALLINFO2 is None:
            doc["note"] = "no glibc mallinfo2 here: malloc's own account is not available"
        return doc
