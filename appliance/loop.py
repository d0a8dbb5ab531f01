"""The fixed-budget 10 Hz loop. One thread owns it.

Each cycle: acquire (lock-step devices publish), read the newest fresh sample of each device,
perception, fusion, zones, the safety gate, send. Every stage has a budget; an optional
pipeline that does not fit in what is left of the perception budget is skipped and counted; a
stage over budget is counted; ``lag_cycles_fault`` overrun cycles in a row are a fault (STOP).
All time comes from the injected clock, so a replay on a ManualClock is deterministic; wall
time is measured beside it for the status page and the benchmark.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from appliance.config import Config
from appliance.decision import DecisionCore, decision_name
from appliance.perception import Detections, Pipeline, SensorInputs
from appliance.zones import ZoneVerdict
from hal.clock import Clock
from hal.devices import Device, VehicleLink
from hal.health import Health
from hal.types import GateOutput, GateState

log = logging.getLogger("fieldguard.loop")

STAGES = ("acquire", "perception", "fusion", "gate", "send")
SENSOR_KINDS = ("stereo", "rgbd", "laser")


@dataclass
class CycleResult:
    index: int
    stamp_ns: int
    output: GateOutput
    faults: list[str]
    verdict: ZoneVerdict | None
    cells_xy: np.ndarray
    detections: dict[str, Detections]
    stage_ms: dict[str, float]            # injected-clock time per stage
    wall_ms: dict[str, float]             # wall time per stage
    skipped: list[str]
    sent: bool
    on_time: bool
    inputs: SensorInputs | None = None
    tracks: list = field(default_factory=list)    # appliance.tracking.TrackView, every track
    held_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # [grid] hold_blind


def run_pipeline(p, inputs: SensorInputs, what: str = "pipeline") -> tuple:
    """(``p``'s detections for ``inputs``, None) or (None, the fault's text): a pipeline that
    raises, or answers with what cannot be fused, is a fault, never a crash of the caller (the
    loop; a campaign's shadow)."""
    try:
        d = p.process(inputs)
        bad = malformed(d)
        if bad:
            raise ValueError(f"malformed detections: {bad}")
        return d, None
    except Exception as exc:
        log.exception("%s %s failed", what, p.name)
        return None, f"pipeline {p.name} failed: {type(exc).__name__}: {exc}"


def malformed(d) -> str | None:
    """Why a pipeline's answer cannot be fused (None when it can): obstacle points must be
    finite (N, 2) numbers. A NaN would fall out of the grid, i.e. be an obstacle not seen."""
    if not isinstance(d, Detections):
        return f"{type(d).__name__}, not Detections"
    p = d.points_xy
    if not isinstance(p, np.ndarray) or p.ndim != 2 or p.shape[1] != 2:
        return f"points_xy of shape {getattr(p, 'shape', None)}, expected (N, 2)"
    if p.dtype.kind not in "fiu":
        return f"points_xy of dtype {p.dtype}"
    if len(p) and not np.isfinite(p).all():
        return f"{int((~np.isfinite(p).all(axis=1)).sum())} of {len(p)} points not finite"
    return None


class _Timing:
    def __init__(self, n: int = 600):
        self.samples: deque[float] = deque(maxlen=n)
        self.last = 0.0

    def add(self, v: float) -> None:
        self.last = v
        self.samples.append(v)

    def summary(self) -> dict:
        if not self.samples:
            return {"last": None, "p50": None, "p99": None, "max": None}
        a = np.fromiter(self.samples, float)
        return {"last": round(self.last, 3), "p50": round(float(np.percentile(a, 50)), 3),
                "p99": round(float(np.percentile(a, 99)), 3), "max": round(float(a.max()), 3)}


class ApplianceLoop:
    def __init__(self, cfg: Config, clock: Clock, devices: dict[str, Device],
                 pipelines: list[Pipeline], kinds: dict[str, str] | None = None):
        self.cfg = cfg
        self.clock = clock
        self.devices = devices
        self.kinds = kinds or {n: d.kind for n, d in devices.items()}
        self.links: list[VehicleLink] = [d for d in devices.values() if isinstance(d, VehicleLink)]
        self.pipelines = pipelines
        # the one decision core (fusion, tracks, zones, gate), shared with `fieldguard eval`
        self.core = DecisionCore(cfg)
        self.grid = self.core.grid
        self.gate = self.core.gate
        self.period_ns = int(round(1e9 / cfg.loop.rate_hz))
        req = set(cfg.gate.required)
        if req:
            self.required = [n for n in devices if n in req]
        else:
            dc = {d.name: d for d in cfg.devices}
            self.required = [n for n in devices if dc.get(n) is None or dc[n].required]
        self.optional_pipelines = set(cfg.perception.optional)
        self.cycles = 0
        self.overruns = 0
        self._late_run = 0
        self._send_ok = True
        # each device's fault count at the last cycle: a fault that came and went between two
        # cycles (a wire error held 0.3 s while the loop was late, a malformed frame cleared by
        # the next good one) still stops this cycle
        self._fault_seen: dict[str, int] = {}
        self._send_error = ""
        self.skipped: dict[str, int] = {}
        self.stage_over: dict[str, int] = {s: 0 for s in STAGES}
        self.timing = {s: _Timing() for s in STAGES}
        self.timing["cycle"] = _Timing()
        self._est_ms: dict[str, float] = {}
        self.last: CycleResult | None = None
        self._lock = threading.Lock()
        self.on_cycle = []        # callbacks f(result)

    # -------------------------------------------------------------------------------------
    def _budget_ms(self, stage: str) -> float:
        return getattr(self.cfg.loop, f"budget_{stage}_ms")

    def cycle(self) -> CycleResult:
        now = self.clock.now_ns()
        stage_ms, wall_ms = {}, {}
        faults: list[str] = []

        def mark(stage, t0, w0):
            stage_ms[stage] = (self.clock.now_ns() - t0) / 1e6
            wall_ms[stage] = (time.perf_counter() - w0) * 1e3
            self.timing[stage].add(wall_ms[stage])
            if stage_ms[stage] > self._budget_ms(stage):
                self.stage_over[stage] += 1

        # ---- acquire ----
        t0, w0 = self.clock.now_ns(), time.perf_counter()
        for name, dev in self.devices.items():
            try:
                dev.service(now)
            except Exception as exc:            # a driver bug marks the device, never the loop
                dev._fault(f"driver error: {type(exc).__name__}: {exc}")
        samples = {}
        for name, dev in self.devices.items():
            h = dev.health(now)
            seen, self._fault_seen[name] = self._fault_seen.get(name), h.faults
            if name in self.required and h.state is not Health.OK:
                faults.append(f"{name}: {h.reason or h.state.value}")
            elif name in self.required and seen is not None and h.faults > seen:
                faults.append(f"{name}: {h.last_fault or 'fault'} (came and went since the "
                              f"last cycle)")
            samples[name] = dev.latest(now)
        by_kind = {}
        for name, s in samples.items():
            k = self.kinds.get(name)
            if k in SENSOR_KINDS and s is not None and k not in by_kind:
                by_kind[k] = s
        vehicle = None
        for link in self.links:
            vehicle = samples.get(link.name) or vehicle
        inputs = SensorInputs(stamp_ns=now, vehicle=vehicle, **by_kind)
        mark("acquire", t0, w0)

        # ---- perception ----
        t0, w0 = self.clock.now_ns(), time.perf_counter()
        budget = self._budget_ms("perception")
        detections: dict[str, Detections] = {}
        skipped = []
        for p in self.pipelines:
            optional = p.name in self.optional_pipelines
            missing = p.missing(inputs)
            if missing:
                if not optional:
                    faults.append(f"pipeline {p.name}: no fresh {', '.join(missing)} data")
                continue
            used = (self.clock.now_ns() - t0) / 1e6
            if optional and used + self._est_ms.get(p.name, 0.0) > budget:
                skipped.append(p.name)
                self.skipped[p.name] = self.skipped.get(p.name, 0) + 1
                continue
            ps = self.clock.now_ns()
            d, msg = run_pipeline(p, inputs)
            if d is not None:
                detections[p.name] = d
            elif not optional:
                faults.append(msg)
            took = (self.clock.now_ns() - ps) / 1e6
            self._est_ms[p.name] = 0.8 * self._est_ms.get(p.name, took) + 0.2 * took
        mark("perception", t0, w0)

        # ---- fusion ----
        t0, w0 = self.clock.now_ns(), time.perf_counter()
        try:
            picture = self.core.perceive(detections, vehicle, now)
        except Exception as exc:     # a bug or malformed detections: STOP, never a dead loop
            log.exception("fusion failed")
            faults.append(f"fusion failed: {type(exc).__name__}: {exc}")
            picture = None
        if picture is None:
            cells, verdict, tracks = np.zeros((0, 2), np.float32), None, []
            held = np.zeros((0, 2))
        else:
            cells, verdict, tracks = picture.cells_xy, picture.verdict, picture.tracks
            held = picture.held_xy
        mark("fusion", t0, w0)

        # ---- gate ----
        t0, w0 = self.clock.now_ns(), time.perf_counter()
        if self._late_run >= self.cfg.loop.lag_cycles_fault:
            faults.append(f"loop lagging: {self._late_run} cycles over "
                          f"{self.period_ns / 1e6:.0f} ms in a row")
        if not self._send_ok:
            faults.append(f"last message did not go out: {self._send_error}")
        if not self.links:
            faults.append("no vehicle link configured")
        stamps = [getattr(s, "stamp_ns", None) for s in (inputs.stereo, inputs.rgbd, inputs.laser)]
        stamps = [s for s in stamps if s is not None]
        out = self.core.decide(now, faults, picture, min(stamps) if stamps else None)
        mark("gate", t0, w0)

        # ---- send ----
        t0, w0 = self.clock.now_ns(), time.perf_counter()
        sent_all, errs = bool(self.links), []
        for link in self.links:
            try:
                ok = link.send(out)
            except Exception as exc:
                ok = False
                link._fault(f"send failed: {type(exc).__name__}: {exc}")
                errs.append(f"{link.name}: {exc}")
            else:
                if not ok:
                    errs.append(f"{link.name}: send returned False")
            sent_all &= bool(ok)
        self._send_ok, self._send_error = sent_all, "; ".join(errs) or "no link"
        mark("send", t0, w0)

        # ---- timing ----
        end = self.clock.now_ns()
        total_ms = (end - now) / 1e6
        self.timing["cycle"].add(sum(wall_ms.values()))
        on_time = total_ms <= self.period_ns / 1e6
        if on_time:
            self._late_run = 0
        else:
            self._late_run += 1
            self.overruns += 1
        self.cycles += 1
        res = CycleResult(self.cycles, now, out, faults, verdict, cells, detections, stage_ms,
                          wall_ms, skipped, sent_all, on_time, inputs, tracks, held)
        with self._lock:
            self.last = res
        for cb in self.on_cycle:
            try:
                cb(res)
            except Exception:
                log.exception("cycle callback failed")
        return res

    # -------------------------------------------------------------------------------------
    def run(self, stop: threading.Event, max_cycles: int | None = None,
            pace: float | None = None) -> None:
        """Run cycles every period until ``stop`` is set. ``pace`` (lock-step clocks only):
        wall seconds per clock second (1 = real time, 0 = as fast as possible)."""
        next_ns = self.clock.now_ns()
        wall0, clock0 = time.monotonic(), self.clock.now_ns()
        n = 0
        while not stop.is_set() and (max_cycles is None or n < max_cycles):
            self.cycle()
            n += 1
            next_ns += self.period_ns
            now = self.clock.now_ns()
            if now > next_ns:                     # missed ticks: count them, do not burst
                missed = (now - next_ns) // self.period_ns + 1
                self._late_run += int(missed)
                self.overruns += int(missed)
                next_ns += missed * self.period_ns
            self.clock.sleep_until(next_ns)
            if pace:
                target = wall0 + pace * (self.clock.now_ns() - clock0) / 1e9
                delay = target - time.monotonic()
                if delay > 0:
                    stop.wait(delay)

    def send_stop_everywhere(self, reason: str) -> None:
        """On shutdown: tell every link STOP, whatever the gate thinks."""
        now = self.clock.now_ns()
        self.gate._set(GateState.STOP, reason, now)
        out = GateOutput(stamp_ns=now, seq=(self.gate._seq + 1) & 0xFFFF, state=GateState.STOP,
                         reason=reason)
        for link in self.links:
            try:
                link.send(out)
            except Exception as exc:
                log.error("could not send STOP on %s: %s", link.name, exc)

    # -------------------------------------------------------------------------------------
    def status(self) -> dict:
        with self._lock:
            last = self.last
        now = self.clock.now_ns()
        out = {
            "state": self.gate.state.value,
            "reason": self.gate.reason,
            "cycles": self.cycles,
            "devices": {n: d.health(now).to_dict() | {"required": n in self.required}
                        for n, d in self.devices.items()},
            "timing_ms": {k: t.summary() for k, t in self.timing.items()},
            "budget_ms": {s: self._budget_ms(s) for s in STAGES},
            "overruns": self.overruns,
            "stage_over_budget": dict(self.stage_over),
            "skipped": dict(self.skipped),
            "last_stops": [{"stamp_s": round(e.stamp_ns / 1e9, 3), "reason": e.reason}
                           for e in list(self.gate.history)[-10:]],
            "links": {l.name: l.peers() for l in self.links},
            "pipelines": [p.name for p in self.pipelines],
            "pipeline_notes": {p.name: n for p in self.pipelines if (n := p.notes())},
        }
        if last is not None:
            v = last.verdict
            out["faults"] = list(last.faults)
            out["obstacles"] = {
                "occupied_cells": int(len(last.cells_xy)),
                "in_stop_zone": None if v is None else v.in_stop,
                "in_slow_zone": None if v is None else v.in_slow,
                "nearest_m": None if v is None or v.nearest_m is None else round(v.nearest_m, 2),
                "stop_zone_m": None if v is None else round(v.stop_len_m, 2),
                "grid_cells": int(len(self.core.last.grid_cells_xy)) if self.core.last else None,
                "decision": decision_name(self.cfg.tracking),
                # [grid] laser_confirm_by: laser returns a camera had in view this cycle and
                # did not confirm (a SLOW, not a STOP); None when off
                "laser_unconfirmed": (self.core.laser_unconfirmed
                                      if self.cfg.grid.laser_confirm_by else None),
                # [zones] follow_path: "path" when the zones lie along the planned path this
                # cycle, else why not (the zones are then straight); None when off
                "zones_along": ((("path" if v is not None and v.path is not None else
                                  self.core.path_refused or "straight"))
                                if self.cfg.zones.follow_path else None),
            }
            # the confirmed tracks (the obstacles the box holds), nearest first
            out["tracks"] = [t.to_dict() for t in sorted(
                (t for t in last.tracks if t.confirmed), key=lambda t: t.x_m ** 2 + t.y_m ** 2)]
            out["tentative_tracks"] = sum(1 for t in last.tracks if not t.confirmed)
        return out
