"""The safety gate: the ONE place that may leave STOP.

It boots in STOP. Each cycle it is given the faults the loop found (stale or unhealthy required
sources, a lagging loop, a failed send, a pipeline error) and the zone verdict, and answers with
the state to send. Any fault is STOP with that fault as the reason. An obstacle in the stop zone
is STOP. A stop (or a slow-down) is released only after the zone has been clear for
``hold_off_s`` without a break, so a flickering detection cannot make the vehicle lurch.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

from appliance.config import GateConfig, ZonesConfig
from appliance.zones import ZoneVerdict
from hal.types import GateOutput, GateState

log = logging.getLogger("fieldguard.gate")

_RANK = {GateState.STOP: 0, GateState.SLOW: 1, GateState.CLEAR: 2}


@dataclass(frozen=True)
class StopEvent:
    stamp_ns: int
    reason: str


class SafetyGate:
    def __init__(self, config: GateConfig | None = None, zones: ZonesConfig | None = None):
        self.cfg = config or GateConfig()
        self.zones = zones or ZonesConfig()
        self.state = GateState.STOP
        self.reason = "booting: no cycle has run yet"
        self._seq = 0
        self._calm_since_ns: int | None = None     # since when the wanted state was >= current
        self.history: deque[StopEvent] = deque(maxlen=50)
        self.history.append(StopEvent(0, self.reason))
        self.transitions = 0
        # what the present state is for: "boot", "fault", "no-picture", "obstacle" (STOP or
        # SLOW for something in a zone, and the hold-off after it), "clear"
        self.cause = "boot"

    def decide(self, now_ns: int, faults: list[str], verdict: ZoneVerdict | None,
               source_stamp_ns: int | None = None) -> GateOutput:
        wanted, reason, cause = self._wanted(faults, verdict)
        if _RANK[wanted] < _RANK[self.state] or wanted is GateState.STOP:
            # tightening (or staying in STOP): at once
            self._calm_since_ns = None
            self._set(wanted, reason, now_ns)
            self.cause = cause
        elif _RANK[wanted] > _RANK[self.state]:
            # loosening: only after the hold-off, with no break
            if self._calm_since_ns is None:
                self._calm_since_ns = now_ns
            held = (now_ns - self._calm_since_ns) / 1e9
            if held + 1e-9 >= self.cfg.hold_off_s:
                self._set(wanted, reason, now_ns)
                self._calm_since_ns = None
                self.cause = cause
            else:
                self.reason = (f"holding {self.state.value}: clear for {held:.1f} of "
                               f"{self.cfg.hold_off_s:.1f} s (was: {self._last_cause})")
        else:
            self._calm_since_ns = None
            self.reason = reason
            self.cause = cause
        self._seq = (self._seq + 1) & 0xFFFF
        return GateOutput(
            stamp_ns=now_ns, seq=self._seq, state=self.state, reason=self.reason,
            nearest_m=None if verdict is None else verdict.nearest_m,
            speed_limit_mps=self.zones.slow_speed_mps if self.state is GateState.SLOW else None,
            sectors=() if verdict is None else verdict.sectors,
            source_stamp_ns=source_stamp_ns)

    _last_cause = "booting"

    def _wanted(self, faults, verdict) -> tuple[GateState, str, str]:
        if faults:
            more = f" (+{len(faults) - 1} more)" if len(faults) > 1 else ""
            return GateState.STOP, faults[0] + more, "fault"
        if verdict is None:
            return GateState.STOP, "no obstacle picture this cycle", "no-picture"
        if verdict.in_stop:
            if verdict.stop_reason:
                return GateState.STOP, verdict.stop_reason, "obstacle"
            return (GateState.STOP, f"obstacle {verdict.nearest_m:.1f} m ahead in the stop zone "
                                    f"({verdict.stop_len_m:.1f} m)", "obstacle")
        if verdict.in_slow:
            if verdict.slow_reason:
                return GateState.SLOW, verdict.slow_reason, "obstacle"
            return (GateState.SLOW, f"obstacle {verdict.nearest_m:.1f} m ahead in the slow zone",
                    "obstacle")
        return GateState.CLEAR, "zone clear", "clear"

    def _set(self, state: GateState, reason: str, now_ns: int) -> None:
        if state is not self.state:
            self.transitions += 1
            log.info("gate %s -> %s: %s", self.state.value, state.value, reason)
            if state is GateState.STOP:
                self.history.append(StopEvent(now_ns, reason))
        if state is not GateState.CLEAR:
            self._last_cause = reason
        self.state = state
        self.reason = reason
