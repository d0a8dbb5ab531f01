"""Recording what the box saw: on request (``fieldguard record``) and the incident ring buffer.

The loop's only cost is a callback that appends references to the cycle's (immutable) samples to
a ring and, while a recording runs, to a bounded queue; a writer thread does all the encoding
and disk work with the run-folder writer. If the writer cannot keep up, frames are dropped AND
counted (the recording says how many), never queued without bound.

Incidents: when the gate enters STOP (for anything but booting or shutting down) the last
``incident_seconds`` before it and one second after are written as a run folder under
``[status] incident_dir``; at most ``incident_max`` incidents are kept (oldest removed first).
Memory: the ring holds ``incident_seconds x rate`` cycles of references to full frames
(a 1280x1024 stereo pair is 7.9 MB: 2 s at 10 Hz is about 160 MB).
"""
from __future__ import annotations

import logging
import queue
import re
import shutil
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from hal.types import GateState

log = logging.getLogger("fieldguard.recorder")


@dataclass
class _Job:
    path: Path
    name: str
    frames: deque = field(default_factory=deque)
    until_ns: int | None = None        # keep capturing live cycles until this stamp
    written: int = 0
    dropped: int = 0
    done: threading.Event = field(default_factory=threading.Event)
    error: str | None = None
    incident: bool = False


def _slug(text: str) -> str:
    return re.sub(r"[^a-zA-Z0-9]+", "-", text).strip("-")[:40] or "stop"


class Recorder:
    def __init__(self, rate_hz: float, incident_dir: str = "", incident_seconds: float = 2.0,
                 incident_max: int = 20, queue_frames: int = 64,
                 incident_max_mb: float = 0.0):
        self.rate_hz = rate_hz
        self.incident_dir = Path(incident_dir) if incident_dir else None
        self.ring: deque = deque(maxlen=max(1, int(round(incident_seconds * rate_hz))))
        self.incident_max = incident_max
        self.incident_max_bytes = int(incident_max_mb * 1e6)     # 0: no bound by size
        self._q: queue.Queue = queue.Queue(maxsize=queue_frames)
        self._live: list[_Job] = []
        self._lock = threading.Lock()
        self._last_state: GateState | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._writer, name="recorder", daemon=True)
        self._thread.start()
        self.incidents: deque = deque(maxlen=50)

    # -- loop side (cheap) -------------------------------------------------------------------
    def on_cycle(self, res) -> None:
        item = (res.stamp_ns, res.inputs, res.output)
        self.ring.append(item)
        st = res.output.state
        if (self.incident_dir is not None and st is GateState.STOP
                and self._last_state not in (None, GateState.STOP)):
            self._start_incident(res)
        self._last_state = st
        with self._lock:
            live = list(self._live)
        for job in live:
            if job.until_ns is not None and res.stamp_ns > job.until_ns:
                with self._lock:
                    self._live.remove(job)
                self._put((job, None))
                continue
            self._put((job, item))

    def _put(self, entry) -> None:
        try:
            self._q.put_nowait(entry)
        except queue.Full:
            if entry[1] is not None:
                entry[0].dropped += 1
            else:                      # the end marker must not be lost: wait a little
                self._q.put(entry, timeout=2.0)

    def _start_incident(self, res) -> None:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        name = base = f"{stamp}-{_slug(res.output.reason)}"
        # never into another incident's folder: two stops for the same reason in one second,
        # or a wall clock stepped back onto the names of earlier incidents
        with self._lock:        # (the writer may not have made an earlier one's folder yet)
            taken = {j.name for j in self._live} | {i["name"] for i in self.incidents}
        k = 2
        while name in taken or (self.incident_dir / name).exists():
            name, k = f"{base}-{k}", k + 1
        job = _Job(self.incident_dir / name, name, incident=True,
                   until_ns=res.stamp_ns + int(1e9))
        for item in list(self.ring)[:-1]:
            self._put((job, item))
        with self._lock:
            self._live.append(job)
        self.incidents.append({"name": name, "reason": res.output.reason,
                               "stamp_s": round(res.stamp_ns / 1e9, 3)})

    # -- requests ------------------------------------------------------------------------------
    def record(self, seconds: float, path: str, now_ns: int) -> _Job:
        p = Path(path)
        if p.exists() and any(p.iterdir()):
            raise FileExistsError(f"{p} exists and is not empty: choose a new folder "
                                  f"(no recording is ever overwritten)")
        job = _Job(p, p.name, until_ns=now_ns + int(seconds * 1e9))
        with self._lock:
            self._live.append(job)
        return job

    # -- writer thread --------------------------------------------------------------------------
    def _writer(self) -> None:
        from drivers.runfolder import RunWriter
        writers: dict[int, RunWriter] = {}
        while not self._stop.is_set() or not self._q.empty():
            try:
                job, item = self._q.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                if item is None:
                    w = writers.pop(id(job), None)
                    if w is not None:
                        w.close()
                    job.done.set()
                    if job.incident:
                        self._prune_incidents()
                    continue
                stamp, inputs, out = item
                if inputs is None or job.error is not None:
                    continue          # a job that failed once says so once, not every frame
                w = writers.get(id(job))
                if w is None:
                    w = RunWriter(job.path, job.name, rate_hz=self.rate_hz,
                                  stereo=inputs.stereo.calib if inputs.stereo else None,
                                  rgbd=inputs.rgbd.calib if inputs.rgbd else None,
                                  laser=inputs.laser.geometry if inputs.laser else None,
                                  extra_run={"recorded_by": "fieldguard",
                                             "incident": job.incident})
                    writers[id(job)] = w
                w.write_frame(job.written, stamp, vehicle=inputs.vehicle,
                              stereo=inputs.stereo if w.stereo_calib else None,
                              rgbd=inputs.rgbd if w.rgbd_calib else None,
                              laser=inputs.laser if w.laser_geom else None,
                              illumination=getattr(inputs.stereo, "illumination", None),
                              extra_columns={"gate_state": out.state.value,
                                             "gate_reason": out.reason})
                job.written += 1
            except Exception as exc:
                job.error = f"{type(exc).__name__}: {exc}"
                log.error("recording %s: %s (%d frame(s) written; the rest of this %s is not "
                          "recorded)", job.path, job.error, job.written,
                          "incident" if job.incident else "recording")
                w = writers.pop(id(job), None)
                if w is not None:
                    try:
                        w.close()
                    except Exception:          # the disk that failed may fail the close too
                        pass
                job.done.set()

    def _prune_incidents(self) -> None:
        if self.incident_dir is None or not self.incident_dir.exists():
            return
        runs = sorted(p for p in self.incident_dir.iterdir() if (p / "run.toml").exists())
        for old in runs[:-self.incident_max] if self.incident_max > 0 else []:
            shutil.rmtree(old, ignore_errors=True)
            log.info("incident buffer full: removed %s", old.name)
        runs = runs[-self.incident_max:] if self.incident_max > 0 else runs
        if self.incident_max_bytes > 0:          # and the disk budget: oldest first, never the
            sizes = [sum(f.stat().st_size for f in r.rglob("*") if f.is_file()) for r in runs]
            total = sum(sizes)
            for old, size in zip(runs[:-1], sizes):          # newest (just written) is kept
                if total <= self.incident_max_bytes:
                    break
                shutil.rmtree(old, ignore_errors=True)
                total -= size
                log.info("incident disk budget (%.0f MB) reached: removed %s",
                         self.incident_max_bytes / 1e6, old.name)

    def close(self, timeout_s: float = 5.0) -> None:
        with self._lock:
            live, self._live = list(self._live), []
        for job in live:
            self._put((job, None))
        self._stop.set()
        self._thread.join(timeout_s)
