"""Health states shared by every device."""
from __future__ import annotations

import enum
from dataclasses import dataclass, field


class Health(enum.Enum):
    """What a device says of itself. Only OK may count towards CLEAR."""

    STARTING = "starting"   # opened, no data yet
    OK = "ok"               # fresh data, no fault
    NO_DATA = "no_data"     # newest sample older than the device's timeout
    FAULT = "fault"         # the driver reported an error (cable out, bad data, exception)
    CLOSED = "closed"


@dataclass(frozen=True)
class HealthReport:
    name: str
    kind: str
    state: Health
    reason: str = ""
    age_s: float | None = None          # age of the newest sample, None if none yet
    samples: int = 0                     # samples published since open
    faults: int = 0                      # faults reported since open
    counters: dict = field(default_factory=dict)   # driver-specific (dropped frames, resends…)
    last_fault: str = ""                 # the newest fault's reason, kept after it cleared

    @property
    def ok(self) -> bool:
        return self.state is Health.OK

    def to_dict(self) -> dict:
        return {
            "name": self.name, "kind": self.kind, "state": self.state.value,
            "reason": self.reason,
            "age_s": None if self.age_s is None else round(self.age_s, 4),
            "samples": self.samples, "faults": self.faults, "counters": dict(self.counters),
            "last_fault": self.last_fault,
        }
