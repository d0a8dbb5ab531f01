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
        # since when every cycle, watched without a break, wanted at least SLOW (1) / CLEAR (2)
        self._since: dict[int, int | None] = {1: None, 2: None}
        self._last_ns: int | None = None
        self.history: deque[StopEvent] = deque(maxlen=50)
        self.history.append(StopEvent(0, self.reason))
        self.transitions = 0
        # what the present state is for: "boot", "fault", "no-picture", "obstacle" (STOP or
        # SLOW for something in a zone, and the hold-off after it), "clear"
        self.cause = "boot"

    def decide(self, now_ns: int, faults: list[str], verdict: ZoneVerdict | None,
               source_stamp_ns: int | None = None) -> GateOutput:
        wanted, reason, cause = self._wanted(faults, verdict)
        w = _RANK[wanted]
        hold = self.cfg.hold_off_s
        # a clock step back, or a gap longer than the hold-off, is a break: the box was not
        # watching (found by tests/test_properties.py: one calm cycle and an hour's jump
        # counted as an hour held)
        watched = self._last_ns is None or 0 <= now_ns - self._last_ns <= hold * 1e9 + 1
        self._last_ns = now_ns
        for lvl in (1, 2):
            if w < lvl:
                self._since[lvl] = None
            elif self._since[lvl] is None or not watched:
                self._since[lvl] = now_ns
        if w < _RANK[self.state] or wanted is GateState.STOP:
            # tightening (or staying in STOP): at once
            self._set(wanted, reason, now_ns)
            self.cause = cause
        elif w > _RANK[self.state]:
            # loosening: to the best level every cycle of the hold-off wanted (STOP, then
            # something in the slow zone, then one clear cycle is SLOW, not CLEAR)
            held = {lvl: (now_ns - t) / 1e9 for lvl, t in self._since.items() if t is not None}
            reached = max((lvl for lvl in (1, 2)
                           if lvl <= w and held.get(lvl, -1.0) + 1e-9 >= hold), default=0)
            if reached == w:
                self._set(wanted, reason, now_ns)
                self.cause = cause
            elif reached > _RANK[self.state]:
                was = self._last_cause
                self._set(GateState.SLOW, f"holding SLOW: clear for {held.get(2, 0.0):.1f} of "
                                          f"{hold:.1f} s (was: {was})", now_ns)
                self._last_cause = was
                self.cause = "obstacle"
            else:
                self.reason = (f"holding {self.state.value}: clear for "
                               f"{held.get(_RANK[self.state] + 1, 0.0):.1f} of {hold:.1f} s "
                               f"(was: {self._last_cause})")
        else:
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
