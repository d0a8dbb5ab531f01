"""The loop's hand-over to the console (and the live Foxglove server): cheap on the loop side.

On the loop thread, ``on_cycle`` does at most ``rate_hz`` times a second what it must: it keeps
a reference to the cycle's result (its samples are immutable) and a copy of the grid's evidence
(one array copy, ~0.1 ms) in a newest-only slot and wakes the encoder thread. Nothing queues: a
slow encoder skips cycles, it never holds the loop or grows memory. A cycle that enters STOP is
always handed over (its own slot), so the console keeps a picture of every stop.

The encoder thread renders and JPEG-encodes the pictures and hands the finished ``View`` to the
console and to any other consumer (the Foxglove live server). OpenCV releases the GIL while it
resizes and encodes, so the loop thread keeps running meanwhile.
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from hal.types import GateState

log = logging.getLogger("fieldguard.console")


@dataclass
class View:
    index: int                      # the loop's cycle number
    stamp_ns: int
    state: str
    reason: str
    res: object                     # the CycleResult (None in the kept stops)
    evidence: np.ndarray | None     # copy of the grid's evidence at that cycle
    tracks: list = field(default_factory=list)
    camera_jpeg: bytes | None = None
    grid_jpeg: bytes = b""
    wall_s: float = 0.0             # time.time() when handed over


class FrameTap:
    def __init__(self, cfg, evidence_fn, tracks_fn=None, rate_hz: float = 2.0,
                 stops_kept: int = 10):
        self.cfg = cfg
        self.evidence_fn = evidence_fn          # () -> the grid's evidence array (not a copy)
        self.tracks_fn = tracks_fn              # (res) -> tracks or None
        self.period_s = 1.0 / rate_hz
        self.consumers: list = []               # f(View) on the encoder thread
        self.latest: View | None = None
        self.stops: deque[View] = deque(maxlen=stops_kept)
        self.handed = 0                         # hand-overs on the loop side
        self.rendered = 0                       # views the encoder finished
        self.encode_ms: deque[float] = deque(maxlen=200)
        self._slot = None
        self._stop_slot = None
        self._last_t = -1e9
        self._last_state: GateState | None = None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._quit = threading.Event()
        self._thread: threading.Thread | None = None

    # -- loop thread ----------------------------------------------------------------------
    def on_cycle(self, res) -> None:
        st = res.output.state
        entering_stop = st is GateState.STOP and self._last_state not in (None, GateState.STOP)
        self._last_state = st
        now = time.monotonic()
        if not entering_stop and now - self._last_t < self.period_s:
            return
        self._last_t = now
        item = (res, self.evidence_fn().copy(), time.time())
        with self._lock:
            self._slot = item
            if entering_stop:
                self._stop_slot = item
        self.handed += 1
        self._wake.set()

    # -- encoder thread -------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="console-encoder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._quit.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._quit.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                item, stop_item = self._slot, self._stop_slot
                self._slot = self._stop_slot = None
            if stop_item is not None:
                v = self._render_safe(stop_item)
                if v is not None:
                    # kept: the pictures and the reason, not the cycle's frames (10 stereo
                    # pairs would hold ~80 MB)
                    self.stops.append(dataclasses.replace(v, res=None, evidence=None))
                    if item is stop_item:
                        self._publish(v)
                        continue
            if item is not None:
                self._publish(self._render_safe(item))

    def _render_safe(self, item) -> View | None:
        try:
            return self.render(*item)
        except Exception:
            log.exception("console: rendering a view failed")
            return None

    def _publish(self, v: View | None) -> None:
        if v is None:
            return
        self.latest = v
        for c in list(self.consumers):
            try:
                c(v)
            except Exception:
                log.exception("console: a view consumer failed")

    def render(self, res, evidence, wall_s) -> View:
        from appliance.console.views import camera_view, encode_jpeg, grid_view, track_dicts
        t0 = time.perf_counter()
        tracks = track_dicts(self.tracks_fn(res) if self.tracks_fn else None)
        cam = camera_view(res, tracks)
        v = View(index=res.index, stamp_ns=res.stamp_ns, state=res.output.state.value,
                 reason=res.output.reason, res=res, evidence=evidence, tracks=tracks,
                 camera_jpeg=None if cam is None else encode_jpeg(cam),
                 grid_jpeg=encode_jpeg(grid_view(res, evidence, self.cfg, tracks)),
                 wall_s=wall_s)
        self.encode_ms.append((time.perf_counter() - t0) * 1e3)
        self.rendered += 1
        return v

    def info(self) -> dict:
        e = list(self.encode_ms)
        return {"rate_hz": round(1 / self.period_s, 3), "handed_over": self.handed,
                "rendered": self.rendered,
                "encode_ms_p50": round(float(np.percentile(e, 50)), 2) if e else None}
